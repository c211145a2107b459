"""Writes that survive a power cut, the normal end of a drone's flight.

A rename is atomic, but after a power cut a renamed file may still be empty (its data were in
the page cache) and the rename itself may be lost (the directory entry was too). So: write a
temporary file in the same folder, fsync it, rename it into place, fsync the folder. A file is
then either absent or whole, and once the function returns it is on the disk. And before the
disk is full: ``free_mb``, and ``DiskRunway``, the views a run's free space still holds.
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO


def fsync_dir(folder: str | Path) -> None:
    """Make the folder's entries (created, renamed, removed files) durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | Path, write: Callable[[BinaryIO], object] | bytes) -> None:
    """Write ``path`` whole or not at all, durably: ``write`` is the bytes or a function that
    writes them to the open file. A failed write (a full disk, a file-size limit) removes the
    temporary file and raises one OSError naming ``path``, the reason and the free space."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            if isinstance(write, bytes):
                f.write(write)
            else:
                write(f)
            f.flush()
            # numpy writes small arrays through a C stream whose failed last flush it does not
            # report: a file cut short would otherwise be renamed into place
            written = os.fstat(f.fileno()).st_size
            if written != f.tell():
                raise OSError(errno.EIO, f"cut short at {written} of {f.tell()} bytes")
            os.fsync(f.fileno())
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OSError(
            exc.errno or errno.EIO,
            f"could not be written: {exc.strerror or exc}; {free_mb(path.parent):,.0f} MB free on its disk",
            str(path),
        ) from exc
    fsync_dir(path.parent)


def free_mb(folder: str | Path) -> float:
    """Free space on the disk of ``folder`` in MiB (nan when it cannot be read)."""
    try:
        return shutil.disk_usage(folder).free / 2**20
    except OSError:
        return float("nan")


@dataclass
class DiskRunway:
    """How many more views a run's disk holds at the run's rate so far: ``written`` bytes for
    ``views`` views (its store segments and photos; its snapshots are a bounded number of
    files), and ``margin`` for later views that see more than the first ones did. The live
    accumulator's status and the offline run's ``disk_warning`` both use it."""

    written: int = 0
    views: int = 0
    margin: float = 1.2

    def add(self, nbytes: int) -> None:
        """One more view, of ``nbytes`` bytes on the disk."""
        self.written += int(nbytes)
        self.views += 1

    @property
    def bytes_per_view(self) -> float | None:
        return self.written / self.views if self.views else None

    def need(self, views: int) -> float:
        """Bytes that ``views`` more views take at this rate, with the margin (0 before the first)."""
        return (self.bytes_per_view or 0.0) * views * self.margin

    def views_left(self, free_bytes: float) -> float | None:
        """Views that ``free_bytes`` hold at this rate (None before the first view)."""
        per_view = self.bytes_per_view
        if per_view is None:
            return None
        return free_bytes / max(per_view * self.margin, 1.0)


def append_line(path: str | Path, line: str) -> None:
    """Append ``line`` and a newline to ``path`` durably (the folder too when the file is new).
    A failed append (a full disk) leaves the file as it was, never half a line that the next
    one would be glued to, and raises one OSError naming ``path``."""
    path = Path(path)
    new = not path.exists()
    data = (line + "\n").encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        start = os.fstat(fd).st_size
        try:
            if os.write(fd, data) != len(data):
                raise OSError(errno.ENOSPC, "only part of the line was written")
            os.fsync(fd)
        except OSError as exc:
            try:
                os.ftruncate(fd, start)
            except OSError:
                pass
            raise OSError(
                exc.errno or errno.EIO,
                f"could not be appended to: {exc.strerror or exc}; {free_mb(path.parent):,.0f} MB free on its disk",
                str(path),
            ) from exc
    finally:
        os.close(fd)
    if new:
        fsync_dir(path.parent)
