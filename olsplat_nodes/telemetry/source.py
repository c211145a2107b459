"""Flight-controller telemetry -> a world-from-camera pose for each frame stamp.

``FlightControllerPoses`` ties the pieces together for a node: ``poll`` reads the serial port
and turns kept messages into samples (``add_message``, usable without a port), ``lookup`` maps
a frame's host stamp to autopilot time and returns the interpolated pose with
``world_from_camera`` (ENU world, OpenCV camera axes).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable

from ..scene.rotations import quat_to_rotmat
from .config import TelemetryConfig
from .matching import BootClock, PoseBuffer, PoseMatch
from .mavlink import MavlinkReader
from .pose import euler_to_quat, geodetic_to_ned, world_from_camera

log = logging.getLogger(__name__)


class FlightControllerPoses:
    """Poses from a MAVLink autopilot. ``clock`` (ns) must be the clock of the frame stamps."""

    def __init__(self, config: TelemetryConfig, clock: Callable[[], int] = time.monotonic_ns):
        self.config = config
        self.clock = clock
        self.mount = config.mount()
        self.reference = config.reference
        self.boot_clock = BootClock(config.clock, config.clock_window_s)
        self.buffer = PoseBuffer(config.tolerance_s, config.buffer_len)
        self.reader = (
            MavlinkReader(config.url, config.baudrate, dialect=config.dialect, clock=clock) if config.url else None
        )
        self.sample_stats = {"attitude_samples": 0, "position_samples": 0, "invalid_samples": 0}

    @property
    def stats(self) -> dict[str, int]:
        """Link, decoder, sample and match counters in one flat dict."""
        out = dict(self.reader.stats) if self.reader else {}
        out.update(self.sample_stats, **self.buffer.stats, **self.boot_clock.stats)
        return out

    def poll(self, timeout_s: float = 0.0) -> int:
        """Read what the port has (waiting up to ``timeout_s``); returns the number of samples added."""
        if self.reader is None:
            return 0
        return sum(self.add_message(r.message, r.host_ns) for r in self.reader.read(timeout_s))

    def add_message(self, message, host_ns: int) -> bool:
        """One decoded pymavlink message received at ``host_ns`` -> True when it added a sample."""
        name = message.get_type()
        boot_ms = getattr(message, "time_boot_ms", None)
        if boot_ms is None:
            return False
        if self.boot_clock.observe(int(boot_ms), int(host_ns)):
            log.warning("autopilot reboot detected (time_boot_ms went back to %d): samples cleared", boot_ms)
            self.buffer.clear()
        stamp_ns = int(boot_ms) * 1_000_000
        if name == "SYSTEM_TIME":
            self.boot_clock.observe_system_time(message.time_unix_usec, message.time_boot_ms)
            return False
        if name == "ATTITUDE" and self.config.attitude == name:
            values = (message.roll, message.pitch, message.yaw)
            if self._valid(values):
                return self._count("attitude_samples", self.buffer.add_attitude(stamp_ns, euler_to_quat(*values)))
        elif name == "ATTITUDE_QUATERNION" and self.config.attitude == name:
            quaternion = (message.q1, message.q2, message.q3, message.q4)  # w, x, y, z
            if self._valid(quaternion) and any(quaternion):
                return self._count("attitude_samples", self.buffer.add_attitude(stamp_ns, quaternion))
        elif name == "LOCAL_POSITION_NED" and self.config.position == "local":
            values = (message.x, message.y, message.z)
            if self._valid(values):
                return self._count("position_samples", self.buffer.add_position(stamp_ns, values))
        elif name == "GLOBAL_POSITION_INT" and self.config.position == "global":
            lat, lon, alt = message.lat * 1e-7, message.lon * 1e-7, message.alt * 1e-3
            if message.lat == 0 and message.lon == 0:  # autopilots send zeros before the first fix
                self.sample_stats["invalid_samples"] += 1
                return False
            if self.reference is None:
                self.reference = (lat, lon, alt)
                log.info("world origin (ENU) set to the first fix: lat %.7f lon %.7f alt %.2f m", lat, lon, alt)
            ned = geodetic_to_ned(lat, lon, alt, self.reference)
            return self._count("position_samples", self.buffer.add_position(stamp_ns, ned))
        return False

    def _valid(self, values) -> bool:
        if all(math.isfinite(v) for v in values):
            return True
        self.sample_stats["invalid_samples"] += 1  # PX4 sends NaN for unknown fields
        return False

    def _count(self, key: str, added: bool) -> bool:
        self.sample_stats[key] += int(added)
        return added

    def lookup(self, stamp_ns: int, now_ns: int | None = None) -> PoseMatch:
        """Pose for a frame stamped ``stamp_ns`` (host clock).

        "wait" while a later sample may still come; once ``max_wait_s`` has passed since the
        stamp (by ``now_ns``, default the clock) a frame still without a pose is rejected.
        """
        now_ns = self.clock() if now_ns is None else now_ns
        final = now_ns - stamp_ns > self.config.max_wait_s * 1e9
        autopilot_ns = self.boot_clock.to_autopilot_ns(stamp_ns)
        if autopilot_ns is None:
            if not final:
                return PoseMatch("wait", "clock:no_offset")
            self.buffer.count_rejection("clock", "no_offset")
            return PoseMatch("rejected", "clock:no_offset")
        match = self.buffer.lookup(autopilot_ns, final=final)
        if match.status != "ok":
            return match
        pose = world_from_camera(match.position_ned, quat_to_rotmat(match.quat_ned_from_body), self.mount)
        return dataclasses.replace(match, world_from_camera=pose)

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()

    def __enter__(self) -> FlightControllerPoses:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
