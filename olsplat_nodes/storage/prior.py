"""Which prior map a run was made over: ``STORE/prior_map.json`` holds the map file's absolute
path, size, modification time and SHA-256, written by the accumulator once per store (hashed
front to back in 8 MB reads, off the node's loop: ~1 s per GB). A review of the run
(``olsplat ground web --run DIR``) finds the map from it, wherever the run folder lies, and
checks it is still the same file."""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from ..errors import OlsplatInputError

PRIOR_FILE = "prior_map.json"
_READ = 8 << 20  # bytes per read while hashing


@dataclass(frozen=True)
class PriorMapRecord:
    path: str  # the map file, absolute
    sha256: str  # hex digest of its bytes
    bytes: int  # its size
    mtime_ns: int  # its modification time when hashed (ns since the Unix epoch)
    hash_seconds: float = 0.0  # how long the hashing took


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 8 MB pieces (a map of any size in little memory)."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        while piece := stream.read(_READ):
            digest.update(piece)
    return digest.hexdigest()


def _same_file(record: PriorMapRecord, path: Path) -> bool:
    """The record is of this very file as it is now (path, size, modification time)."""
    stat = path.stat()
    return record.path == str(path) and record.bytes == stat.st_size and record.mtime_ns == stat.st_mtime_ns


def read_prior_record(store: str | Path) -> PriorMapRecord | None:
    """The store's record, or None when it has none; a damaged one is an OlsplatInputError naming it."""
    file = Path(store) / PRIOR_FILE
    if not file.is_file():
        return None
    try:
        return PriorMapRecord(**json.loads(file.read_text()))
    except (ValueError, TypeError) as exc:
        raise OlsplatInputError(f"{file}: not a prior-map record ({exc})") from None


def record_prior_map(store: str | Path, map_path: str | Path) -> PriorMapRecord:
    """Write ``STORE/prior_map.json`` for ``map_path`` (atomically) and return it; a record of the
    same file as it is now (path, size, modification time) is kept without hashing again."""
    from ..durable import write_atomic

    path = Path(map_path).resolve()
    old = read_prior_record(store)
    if old is not None and _same_file(old, path):
        return old
    start = time.perf_counter()
    stat = path.stat()
    digest = file_sha256(path)
    record = PriorMapRecord(str(path), digest, stat.st_size, stat.st_mtime_ns, round(time.perf_counter() - start, 3))
    write_atomic(Path(store) / PRIOR_FILE, json.dumps(asdict(record), indent=1).encode())
    return record


def recorded_prior_map(store: str | Path) -> Path | None:
    """The prior map the store's record names, checked to be that file still (its size, then
    its SHA-256); None when the store has no record. A missing or changed file is one
    OlsplatInputError line that asks for ``--map``."""
    record = read_prior_record(store)
    if record is None:
        return None
    path = Path(record.path)
    where = f"{Path(store) / PRIOR_FILE} names the prior map {path}"
    if not path.is_file():
        raise OlsplatInputError(f"{where}, which is gone: give the PLY the run was made with (--map)")
    if path.stat().st_size != record.bytes or (not _same_file(record, path) and file_sha256(path) != record.sha256):
        raise OlsplatInputError(
            f"{where}, but that file has changed since (its SHA-256 is not {record.sha256[:12]}...): "
            "give the PLY the run was made with (--map)"
        )
    return path
