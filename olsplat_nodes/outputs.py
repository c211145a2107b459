"""Where a command writes: checked before any work, so a bad output path is one clear line at
the start, not a traceback (or half the outputs) at the end."""

from __future__ import annotations

import shutil
from pathlib import Path

from .errors import OlsplatInputError


def output_folder(folder: Path, option: str = "--out", given: Path | None = None) -> Path:
    """Make ``folder`` (and its parents); OlsplatInputError naming ``option`` and the path the
    user gave (``given``, default the folder) when a part of the path is a file or cannot be made."""
    folder = Path(folder)
    shown = given if given is not None else folder
    for part in (folder, *folder.parents):
        if part.exists():
            if not part.is_dir():
                raise OlsplatInputError(f"{option} {shown}: {part} is a file, not a folder")
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OlsplatInputError(f"{option} {shown}: cannot make the folder {folder} ({exc.strerror})") from None
    return folder


def output_file(path: Path, suffix: str, option: str = "--out") -> Path:
    """The file a command will write for ``path``: with ``suffix`` added when it lacks it (the
    name numpy would write, and the one printed), its folder made; not an existing folder."""
    path = Path(path)
    if path.suffix != suffix:
        path = path.with_name(path.name + suffix)
    if path.is_dir():
        raise OlsplatInputError(f"{option} {path}: is a folder; give a file name")
    output_folder(path.parent, option, given=path)
    return path


def empty_output_folder(folder: Path, force: bool, option: str = "--out") -> Path:
    """A folder that holds nothing yet: refused when it already holds files (a new run would mix
    with the old one without a word), emptied first with ``force``."""
    folder = Path(folder)
    if folder.is_dir() and any(folder.iterdir()):
        if not force:
            count = sum(1 for _ in folder.iterdir())
            raise OlsplatInputError(
                f"{option} {folder}: the folder is not empty ({count} entries); choose a new folder, "
                "or pass --force to delete what it holds first"
            )
        shutil.rmtree(folder)
    return output_folder(folder, option)
