"""Record any source to the replay log format (``replay_log.write_mcap``) or a ROS 2 bag
(``rosbag_write.write_rosbag2``, a folder).

Frames keep their stamps, names, intrinsics and poses exactly; images go in as JPEG: the
source's original bytes when it has them (photos, a replay log), else encoded once at
``jpeg_quality``. Replaying the log (``read_replay``) gives the same frames every time.
"""

from __future__ import annotations

import shutil
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Literal

from .base import Source, SourceFrame
from .replay_log import write_mcap


def record(
    source: Source,
    out: str | Path,
    *,
    frames: int | None = None,
    seconds: float | None = None,
    stop: threading.Event | None = None,
    jpeg_quality: int = 95,
    report: Callable[[str], None] | None = None,
    report_every_s: float = 5.0,
    out_format: Literal["mcap", "rosbag2"] = "mcap",
    storage: Literal["mcap", "sqlite3"] = "mcap",
) -> int:
    """Write the source's frames to ``out`` until it is done, ``frames`` were written, ``seconds``
    passed or ``stop`` is set; returns the number written (0: no file is left behind).

    ``out_format`` "mcap": the replay log file; "rosbag2": a new bag folder in ``storage``
    (``write_rosbag2``: whole once closed, so a cut recording leaves no bag; record in the field
    with the replay log)."""
    stop = stop or threading.Event()
    start = time.monotonic()
    last_report = start
    written = 0

    def items() -> Iterator[SourceFrame]:
        nonlocal written, last_report
        while not source.done and not stop.is_set():
            if frames is not None and written >= frames:
                return
            if seconds is not None and time.monotonic() - start >= seconds:
                return
            frame = source.read(0.2)
            now = time.monotonic()
            if report is not None and now - last_report >= report_every_s:
                level, message = source.status()
                report(f"{written} frames; source level {level}: {message}")
                last_report = now
            if frame is None:
                continue
            written += 1
            yield frame

    if out_format not in ("mcap", "rosbag2"):
        raise ValueError(f"out_format must be 'mcap' or 'rosbag2', got {out_format!r}")
    out = Path(out)
    if out_format == "rosbag2":
        from .rosbag_write import write_rosbag2

        count = write_rosbag2(out, items(), storage, jpeg_quality)
        if count == 0:
            shutil.rmtree(out, ignore_errors=True)
        return count
    count = write_mcap(out, items(), jpeg_quality)
    if count == 0:
        out.unlink(missing_ok=True)
    return count
