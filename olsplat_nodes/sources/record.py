"""Record any source to the replay log format (``replay_log.write_mcap``).

Frames keep their stamps, names, intrinsics and poses exactly; images go in as JPEG: the
source's original bytes when it has them (photos, a replay log), else encoded once at
``jpeg_quality``. Replaying the log (``read_replay``) gives the same frames every time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

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
) -> int:
    """Write the source's frames to ``out`` until it is done, ``frames`` were written, ``seconds``
    passed or ``stop`` is set; returns the number written (0: no file is left behind)."""
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

    out = Path(out)
    count = write_mcap(out, items(), jpeg_quality)
    if count == 0:
        out.unlink(missing_ok=True)
    return count
