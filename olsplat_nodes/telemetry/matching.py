"""Poses for frames by timestamp: clock offset, interpolation and rejection (pure, no I/O).

Clocks. Autopilot samples carry ``time_boot_ms`` (milliseconds since the autopilot booted); frames
carry host stamps in nanoseconds. Samples are stored in autopilot time (``time_boot_ms * 1e6``,
monotonic per message type, so the buffer never reorders), and a frame's host stamp is mapped into
autopilot time with the offset known *at lookup*: ``autopilot_ns = host_ns - offset_ns``.
``BootClock`` estimates that offset in one of two ways:

- ``"receive"`` (default): every message gives ``host_receive_ns - time_boot_ms * 1e6``, which is
  the true offset plus a transport delay that is never negative (serial transmission, USB
  buffering, the reader's poll). The smallest value over a sliding window (default 10 s) is the
  least delayed message and the estimate; the window lets it follow the drift of the
  autopilot's crystal. The host clock is whatever the reader stamps receptions with: it must be
  the clock the frames are stamped with (DepthAI's host-synced stamps: ``time.monotonic_ns``).
- ``"system_time"``: SYSTEM_TIME pairs the autopilot's Unix time (from GPS) with its boot time,
  so ``offset = time_unix_usec * 1e3 - time_boot_ms * 1e6`` maps boot time to Unix nanoseconds,
  independent of link delays. Use it when frames carry wall-clock stamps (``time.time_ns``) on a
  host whose clock is disciplined (NTP/GPS). No offset until a SYSTEM_TIME with a non-zero Unix
  time (i.e. a GPS fix) arrived.

A reboot of the autopilot (``time_boot_ms`` going back by more than ``reboot_threshold_ms``)
resets the estimate; ``BootClock.observe`` reports it so that the caller clears the samples.

Matching rule. A frame gets a pose only when each track (attitude, position) has a sample at
or before the frame and one at or after it, each within ``tolerance_s`` of the frame (no
extrapolation). Position is interpolated linearly, attitude with slerp (shortest arc). A frame
newer than the newest sample waits (status ``"wait"``) for the next sample; the caller asks again
or gives up with ``final=True``, which rejects it. Every rejected frame is counted by reason.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Status = Literal["ok", "wait", "rejected"]


def bracket(stamps_ns, stamp_ns: int, tolerance_ns: int) -> tuple[Status, str, int, int, float]:
    """Where ``stamp_ns`` falls in the sorted sample stamps.

    stamps_ns  # [N] int64, strictly increasing
    Returns (status, reason, i0, i1, s): on "ok" the value at the stamp is
    ``(1 - s) * value[i0] + s * value[i1]`` (i0 == i1 and s = 0 on an exact hit); otherwise the
    reason is "no_samples", "no_sample_after" (wait), "no_sample_before" or "gap" (rejected).
    """
    stamps = np.asarray(stamps_ns, np.int64)
    if len(stamps) == 0:
        return "wait", "no_samples", -1, -1, 0.0
    if stamp_ns > stamps[-1]:
        return "wait", "no_sample_after", -1, -1, 0.0
    if stamp_ns < stamps[0]:
        return "rejected", "no_sample_before", -1, -1, 0.0
    i1 = int(np.searchsorted(stamps, stamp_ns, side="left"))  # first sample at or after the stamp
    if stamps[i1] == stamp_ns:
        return "ok", "", i1, i1, 0.0
    i0 = i1 - 1
    t0, t1 = int(stamps[i0]), int(stamps[i1])
    if stamp_ns - t0 > tolerance_ns or t1 - stamp_ns > tolerance_ns:
        return "rejected", "gap", i0, i1, 0.0
    return "ok", "", i0, i1, (stamp_ns - t0) / (t1 - t0)


def slerp(q0, q1, s: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (wxyz [4]) along the shortest arc.

    s = 0 gives q0, s = 1 gives q1 (or -q1, the same rotation); the result is unit, w-sign free.
    """
    q0 = np.asarray(q0, np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, np.float64) / np.linalg.norm(q1)
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are the same rotation: take the shorter way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: sin(theta) ~ 0, linear interpolation is exact enough
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    return (np.sin((1.0 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


def interpolate_position(
    stamps_ns, positions, stamp_ns: int, tolerance_ns: int
) -> tuple[Status, str, np.ndarray | None]:
    """positions [N, 3] at stamps_ns [N] -> (status, reason, [3] linear interpolation or None)."""
    status, reason, i0, i1, s = bracket(stamps_ns, stamp_ns, tolerance_ns)
    if status != "ok":
        return status, reason, None
    p = np.asarray(positions, np.float64)
    return status, reason, (1.0 - s) * p[i0] + s * p[i1]


def interpolate_attitude(stamps_ns, quats, stamp_ns: int, tolerance_ns: int) -> tuple[Status, str, np.ndarray | None]:
    """quats [N, 4] wxyz at stamps_ns [N] -> (status, reason, [4] slerp or None)."""
    status, reason, i0, i1, s = bracket(stamps_ns, stamp_ns, tolerance_ns)
    if status != "ok":
        return status, reason, None
    q = np.asarray(quats, np.float64)
    return status, reason, slerp(q[i0], q[i1], s)


@dataclass(frozen=True)
class PoseMatch:
    """The outcome of one lookup."""

    status: Status
    reason: str = ""  # e.g. "position:gap", "attitude:no_sample_after"; "" when ok
    position_ned: np.ndarray | None = None  # [3] metres
    quat_ned_from_body: np.ndarray | None = None  # [4] wxyz, body FRD -> NED
    world_from_camera: np.ndarray | None = None  # [4, 4] ENU from OpenCV camera (set by FlightControllerPoses)


@dataclass
class PoseBuffer:
    """The last ``maxlen`` attitude and position samples, in one clock, and frame lookups.

    Samples must come in increasing stamp order per track; a sample not newer than the last one
    is dropped and counted (``stale_samples``).
    """

    tolerance_s: float = 0.1
    maxlen: int = 1000
    stats: dict[str, int] = field(default_factory=lambda: {"matched": 0, "rejected": 0, "stale_samples": 0})

    def __post_init__(self) -> None:
        if not self.tolerance_s > 0:
            raise ValueError(f"tolerance_s must be positive, got tolerance_s={self.tolerance_s}")
        if self.maxlen < 2:
            raise ValueError(f"maxlen must be at least 2, got maxlen={self.maxlen}")
        self._tracks: dict[str, tuple[deque, deque]] = {
            "attitude": (deque(maxlen=self.maxlen), deque(maxlen=self.maxlen)),
            "position": (deque(maxlen=self.maxlen), deque(maxlen=self.maxlen)),
        }

    def __len__(self) -> int:
        return min(len(stamps) for stamps, _ in self._tracks.values())

    def add_attitude(self, stamp_ns: int, quat_ned_from_body) -> bool:
        """Append an attitude sample (wxyz [4]); False when it is not newer than the last one."""
        return self._add("attitude", stamp_ns, np.asarray(quat_ned_from_body, np.float64).reshape(4))

    def add_position(self, stamp_ns: int, position_ned) -> bool:
        """Append a position sample (NED metres [3]); False when it is not newer than the last one."""
        return self._add("position", stamp_ns, np.asarray(position_ned, np.float64).reshape(3))

    def _add(self, track: str, stamp_ns: int, value: np.ndarray) -> bool:
        stamps, values = self._tracks[track]
        if stamps and int(stamp_ns) <= stamps[-1]:
            self.stats["stale_samples"] += 1
            return False
        stamps.append(int(stamp_ns))
        values.append(value)
        return True

    def clear(self) -> None:
        for stamps, values in self._tracks.values():
            stamps.clear()
            values.clear()

    def count_rejection(self, track: str, reason: str) -> None:
        """Count a rejected frame under "rejected" and "rejected_<track>_<reason>"."""
        self.stats["rejected"] += 1
        key = f"rejected_{track}_{reason}"
        self.stats[key] = self.stats.get(key, 0) + 1

    def lookup(self, stamp_ns: int, final: bool = False) -> PoseMatch:
        """Pose at ``stamp_ns`` (same clock as the samples). ``final`` turns a wait into a rejection.

        Only final outcomes are counted: "matched", "rejected" and "rejected_<track>_<reason>".
        """
        tolerance_ns = int(round(self.tolerance_s * 1e9))
        att_stamps, att_values = self._tracks["attitude"]
        pos_stamps, pos_values = self._tracks["position"]
        att = interpolate_attitude(
            np.fromiter(att_stamps, np.int64, len(att_stamps)),
            list(att_values) or np.zeros((0, 4)),
            stamp_ns,
            tolerance_ns,
        )
        pos = interpolate_position(
            np.fromiter(pos_stamps, np.int64, len(pos_stamps)),
            list(pos_values) or np.zeros((0, 3)),
            stamp_ns,
            tolerance_ns,
        )
        for wanted in ("rejected", "wait"):
            for track, (status, reason, _) in (("attitude", att), ("position", pos)):
                if status == wanted:
                    if status == "wait" and not final:
                        return PoseMatch("wait", f"{track}:{reason}")
                    self.count_rejection(track, reason)
                    return PoseMatch("rejected", f"{track}:{reason}")
        self.stats["matched"] += 1
        return PoseMatch("ok", "", position_ned=pos[2], quat_ned_from_body=att[2])


@dataclass
class BootClock:
    """Offset between autopilot boot time and the host clock (rule in the module docstring)."""

    mode: Literal["receive", "system_time"] = "receive"
    window_s: float = 10.0  # "receive": the minimum is taken over receptions this recent
    reboot_threshold_ms: int = 1000  # time_boot_ms going back by more than this = the autopilot rebooted
    stats: dict[str, int] = field(default_factory=lambda: {"reboots": 0})

    def __post_init__(self) -> None:
        if self.mode not in ("receive", "system_time"):
            raise ValueError(f"mode must be 'receive' or 'system_time', got mode={self.mode!r}")
        if not self.window_s > 0:
            raise ValueError(f"window_s must be positive, got window_s={self.window_s}")
        self._window: deque[tuple[int, int]] = deque()  # (host_ns, offset_ns), offsets increasing
        self._latest_boot_ms: int | None = None
        self._system_offset_ns: int | None = None

    @property
    def offset_ns(self) -> int | None:
        """host_ns - autopilot_ns, or None while unknown."""
        if self.mode == "system_time":
            return self._system_offset_ns
        return self._window[0][1] if self._window else None

    def reset(self) -> None:
        self._window.clear()
        self._latest_boot_ms = None
        self._system_offset_ns = None

    def observe(self, time_boot_ms: int, host_ns: int) -> bool:
        """Account for one message stamped ``time_boot_ms`` received at ``host_ns``.

        Returns True when this message shows a reboot (the estimate was reset first).
        """
        rebooted = self._latest_boot_ms is not None and time_boot_ms < self._latest_boot_ms - self.reboot_threshold_ms
        if rebooted:
            self.reset()
            self.stats["reboots"] += 1
        self._latest_boot_ms = max(time_boot_ms, self._latest_boot_ms or 0)
        if self.mode == "receive":
            offset = int(host_ns) - int(time_boot_ms) * 1_000_000
            # Monotonic deque: the front is the minimum of the window, O(1) per message.
            while self._window and self._window[-1][1] >= offset:
                self._window.pop()
            self._window.append((int(host_ns), offset))
            horizon = int(host_ns) - int(self.window_s * 1e9)
            while self._window[0][0] < horizon:
                self._window.popleft()
        return rebooted

    def observe_system_time(self, time_unix_usec: int, time_boot_ms: int) -> None:
        """SYSTEM_TIME: sets the offset in "system_time" mode (ignored while Unix time is 0)."""
        if self.mode == "system_time" and time_unix_usec > 0:
            self._system_offset_ns = int(time_unix_usec) * 1000 - int(time_boot_ms) * 1_000_000

    def to_autopilot_ns(self, host_ns: int) -> int | None:
        """A host stamp in autopilot time (ns since boot), or None while the offset is unknown."""
        offset = self.offset_ns
        return None if offset is None else int(host_ns) - offset
