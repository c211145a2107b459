"""The shipped models against their checksums.

Each folder of shipped model files (``encoders/assets/NAME/``, ``structure/assets/``) holds a
``SHA256SUMS`` manifest in coreutils' format (``HEX  FILE`` per line), so that
``sha256sum -c SHA256SUMS`` in the folder checks it by hand too. After changing a model,
rewrite it in that folder with ``sha256sum $(ls | grep -v SHA256SUMS) > SHA256SUMS``; a test
holds the manifests to the files.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from ._row import Row, blocker, ok, warn

MANIFEST = "SHA256SUMS"
_ROOT = Path(__file__).resolve().parents[2]  # olsplat_nodes/


def shipped_model_folders() -> list[Path]:
    """Every folder of shipped models: one per shipped encoder, and the 3D branch's."""
    return [*sorted(p for p in (_ROOT / "encoders" / "assets").iterdir() if p.is_dir()), _ROOT / "structure" / "assets"]


def sha256(path: Path, chunk: int = 2**20) -> str:
    """The file's SHA-256 as 64 hex digits."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(path: Path) -> dict[str, str]:
    """``SHA256SUMS`` -> {file name: hex digest}; ValueError naming the line for a bad one."""
    sums = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        digest, sep, name = line.partition("  ")
        if not sep or len(digest) != 64 or not name:
            raise ValueError(f"{path}:{number}: expected 'SHA256  FILE', got {line!r}")
        sums[name.lstrip("*")] = digest.lower()
    return sums


def model_folder(folder: Path) -> Row:
    """One folder of shipped models: every file its ``SHA256SUMS`` lists is there, readable and
    has that checksum, and no file is there that the manifest does not list."""
    name = f"model {folder.name if folder.name != 'assets' else folder.parent.name}"
    fix = f"reinstall olsplat: pip install --force-reinstall --no-deps olsplat (damaged files in {folder})"
    try:
        sums = read_manifest(folder / MANIFEST)
    except (OSError, ValueError) as exc:
        return blocker(name, f"no usable {MANIFEST}: {exc}", fix)
    size = 0
    for file, expected in sums.items():
        path = folder / file
        try:
            actual = sha256(path)
        except OSError as exc:
            return blocker(name, f"{file}: cannot be read ({exc.strerror or exc})", fix)
        if actual != expected:
            return blocker(name, f"{file}: checksum {actual[:12]}... differs from {MANIFEST}'s {expected[:12]}...", fix)
        size += path.stat().st_size
    extra = sorted(p.name for p in folder.iterdir() if p.is_file() and p.name != MANIFEST and p.name not in sums)
    figure = f"{len(sums)} files, {size / 2**20:.1f} MB, sha256 match"
    if extra:
        return warn(name, f"{figure}; not in {MANIFEST}: {', '.join(extra)}", f"remove them or add them to {MANIFEST}")
    return ok(name, figure)
