"""What every camera source shares: the frame it yields and the polling interface a node drives.

A source is polled, never blocks for long: ``read(timeout_s)`` returns the next frame or None
(nothing yet, or nothing ever again: see ``done``), so that a node keeps heartbeating while a
camera is absent. ``status()`` is the source's health as a ``DiagnosticStatus`` level and
message; ``stats`` are its counters (flat dict of numbers) for the same heartbeat.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import OlsplatInputError
from ..scene import Camera
from ..scene.geodesy import Georeference

OK, WARN, ERROR, STALE = 0, 1, 2, 3  # DiagnosticStatus levels (msgs/: 0 OK, 1 WARN, 2 ERROR, 3 STALE)


@dataclass
class SourceFrame:
    """One camera frame: what every source yields and what the replay log (``replay_log.py``) stores.

    seq       # the source's frame index (a replay log: 0, 1, 2, ... in the log; DepthAI: the device's sequence number)
    stamp_ns  # acquisition time, ns since the Unix epoch (live cameras: host-synced, converted to wall clock)
    name      # image name, unique within a flight (e.g. "frame_0003.jpg"; COLMAP's image name)
    image     # [H, W, 3] uint8 RGB, H = camera.height rows, W = camera.width columns
    camera    # intrinsics (K in pixels, OpenCV distortion) + world_from_camera [4, 4] (metres;
              # OpenCV camera axes: x right, y down, z forward; ENU world for field sources)
    jpeg      # the image's original JPEG bytes when the source has them (photos, replay logs,
              # JPEG image folders), else None; recording keeps them as they are
    """

    seq: int
    stamp_ns: int
    name: str
    image: np.ndarray
    camera: Camera
    jpeg: bytes | None = None


class Source:
    """Base class. Subclasses implement ``read``; finite ones set ``done`` when exhausted."""

    kind = ""
    live = False  # True: frames carry their own acquisition stamps (do not re-stamp them)

    def __init__(self) -> None:
        self.done = False
        self.counts: dict[str, int] = {"frames": 0}

    def read(self, timeout_s: float = 0.1) -> SourceFrame | None:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def stats(self) -> dict[str, float]:
        return dict(self.counts)

    def status(self) -> tuple[int, str]:
        return (OK, "finished" if self.done else "streaming")

    def close(self) -> None:
        pass

    def georeference(self) -> Georeference | None:
        """Where the source's world frame lies on the Earth (its ENU origin), when the source
        knows it (photos with GPS: the first photo or ``exif_reference``), else None. The ingest
        node writes it into the run's map folder, so that the run's answers carry latitude and
        longitude."""
        return None

    def __iter__(self) -> Iterator[SourceFrame]:
        """Every frame until the source is done (live sources: forever)."""
        while not self.done:
            frame = self.read(0.5)
            if frame is not None:
                yield frame

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Pacer:
    """When a frame is due: the recorded pace (stamp differences), a fixed rate, or at once.

    The rule ``replay_log.paced`` sleeps by, asked instead of sleeping here, so that a
    node can wait for a frame in small steps (and heartbeat) between two distant photos.
    """

    def __init__(self, rate_hz: float | None = None, fast: bool = False, clock=time.monotonic):
        if rate_hz is not None and rate_hz <= 0:
            raise OlsplatInputError(f"the replay rate must be positive, got rate_hz={rate_hz}")
        self.rate_hz, self.fast, self.clock = rate_hz, fast, clock
        self.start: float | None = None
        self.first_ns = 0
        self.index = 0

    def due(self, stamp_ns: int) -> float:
        """Monotonic time at which the next frame (stamped ``stamp_ns``) is due."""
        if self.fast:
            return -float("inf")
        if self.start is None:
            self.start, self.first_ns = self.clock(), stamp_ns
        return self.start + (self.index / self.rate_hz if self.rate_hz else (stamp_ns - self.first_ns) / 1e9)

    def sent(self) -> None:
        self.index += 1


class PacedSource(Source):
    """A finite source of ``SourceFrame``s, delivered at a ``Pacer``'s pace."""

    def __init__(self, frames: Iterable[SourceFrame], rate_hz: float | None = None, fast: bool = False):
        super().__init__()
        self._frames = iter(frames)
        self._pacer = Pacer(rate_hz, fast)
        self._next: SourceFrame | None = None

    def read(self, timeout_s: float = 0.1) -> SourceFrame | None:
        if self.done:
            return None
        if self._next is None:
            try:
                self._next = self._frames.__next__()
            except StopIteration:
                self.done = True
                return None
        wait = self._pacer.due(self._next.stamp_ns) - time.monotonic()
        if wait > timeout_s:
            time.sleep(max(timeout_s, 0.0))
            return None
        if wait > 0:
            time.sleep(wait)
        frame, self._next = self._next, None
        self._pacer.sent()
        self.counts["frames"] += 1
        return frame
