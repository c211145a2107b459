"""PX4 flight logs (ULog) as a pose prior for photos: the camera triggers, the vehicle's pose at
each trigger, and which photo each trigger took.

Reading (``read_flight_log``, pyulog 1.3.0, imported when called). Topics and fields are taken by
name only (PX4 reorders fields between versions and pads them; pyulog flattens arrays to
``q[0]``..``q[3]``); instance 0 of each topic. Stamps are microseconds since the autopilot booted
(``timestamp``; ``timestamp_sample``, the sensor sample's time, when a topic has it).

- ``camera_capture``: one row per trigger: ``timestamp`` (the trigger), ``timestamp_utc`` (µs UTC
  from GPS, 0 without), ``seq``, ``result`` (1 success, 0 failure, -1 the camera gives no
  feedback: only 0 counts as a missed photo), ``lat``/``lon``/``alt`` and ``q``.
- ``vehicle_attitude``: ``q`` wxyz, body FRD -> NED (``pose.py``'s frames).
- ``vehicle_global_position``: ``lat``/``lon`` degrees, ``alt`` metres above mean sea level
  (the datum of EXIF GPS altitude); samples flagged invalid (``lat_lon_valid``/``alt_valid``)
  are dropped. Without it, ``vehicle_local_position`` ``x``/``y``/``z`` (NED metres) when it is
  georeferenced (``xy_global``/``z_global``), converted to latitude/longitude/altitude around its
  own ``ref_lat``/``ref_lon``/``ref_alt`` sample by sample (an EKF origin reset cannot tear
  the track).

Why not ``camera_capture.q`` and its position: PX4 copies the latest *vehicle* attitude and
global position into the capture when it handles the trigger (not the gimbal's, and up to one
sample old). So the attitude is slerped and the position interpolated linearly at the trigger
time (``capture_poses``), with ``matching.bracket``'s rules: a sample at or before and one at or
after the trigger, each within ``tolerance_s``, no extrapolation. A capture whose series cannot
be interpolated falls back to its own fields when they are valid (``*_source`` says which); a
capture left without an attitude is refused (``reason``) and its photo keeps its EXIF prior.

Damage is reported, not fatal: pyulog skips damaged bytes and sets ``file_corruption``, and stops
silently at a message cut by the end of the file (a log ended by a power loss); both are one
warning naming the file, and what was read is used. Fatal (``SceneFormatError`` naming the
file): not a ULog, no ``camera_capture`` message, no attitude at all.

Matching photos to triggers (``match_photos``): see its docstring.
"""

from __future__ import annotations

import contextlib
import io
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import SceneFormatError
from ..scene.rotations import quat_to_rotmat
from .matching import interpolate_attitude, interpolate_position
from .pose import CameraMount, geodetic_to_ned, world_from_camera

log = logging.getLogger(__name__)

TOPICS = ("camera_capture", "vehicle_attitude", "vehicle_global_position", "vehicle_local_position")


@dataclass(frozen=True)
class Track:
    """Samples of one quantity, sorted by stamp (strictly increasing: a repeated stamp keeps the last)."""

    stamps_us: np.ndarray  # [N] int64, µs since boot
    values: np.ndarray  # [N, K] float64: quaternions wxyz (K = 4) or lat_deg, lon_deg, alt_m (K = 3)
    topic: str


@dataclass(frozen=True)
class Captures:
    """The rows of ``camera_capture`` in log order (NaN where a field is absent or invalid)."""

    stamps_us: np.ndarray  # [M] int64, the trigger, µs since boot
    utc_us: np.ndarray  # [M] int64, µs since the Unix epoch (GPS); 0 = unknown
    seq: np.ndarray  # [M] int64, the trigger's sequence number
    ok: np.ndarray  # [M] bool: result != 0 (all True without a result field)
    geodetic: np.ndarray  # [M, 3] lat_deg, lon_deg, alt_m AMSL
    quats: np.ndarray  # [M, 4] wxyz, body FRD -> NED


@dataclass(frozen=True)
class FlightLog:
    """What ``read_flight_log`` found in one file."""

    path: Path
    captures: Captures
    attitude: Track | None
    position: Track | None
    problems: tuple[str, ...] = ()  # the warnings logged while reading (damage, missing topics)


@dataclass(frozen=True)
class CapturePose:
    """The vehicle's pose at one trigger."""

    index: int  # row in camera_capture
    seq: int
    stamp_us: int  # µs since boot
    utc_us: int  # µs since the Unix epoch; 0 = unknown
    ok: bool  # the camera did not report a failure
    quat_ned_from_body: np.ndarray | None  # [4] wxyz; None = refused
    geodetic: np.ndarray | None  # [3] lat_deg, lon_deg, alt_m AMSL; None = no position
    attitude_source: str  # "vehicle_attitude", "camera_capture" or "" (none)
    position_source: str  # "vehicle_global_position", "vehicle_local_position", "camera_capture" or ""
    reason: str = ""  # why a series was not used, e.g. "attitude:gap", "position:no_sample_after"

    def world_from_camera(self, reference, mount: CameraMount, position_geodetic=None) -> np.ndarray | None:
        """[4, 4] world (ENU around ``reference`` = lat_deg, lon_deg, alt_m) from camera (OpenCV).

        ``position_geodetic`` (lat, lon, alt) stands in when the log has no position; None when
        neither a position nor an attitude is known.
        """
        where = self.geodetic if self.geodetic is not None else position_geodetic
        if self.quat_ned_from_body is None or where is None:
            return None
        lat, lon, alt = (float(v) for v in where)
        ned = geodetic_to_ned(lat, lon, alt, reference)
        return world_from_camera(ned, quat_to_rotmat(self.quat_ned_from_body), mount)


class _WatchedFile:
    """The file handle pyulog reads, noting whether its last read came up short. pyulog stops
    without a flag at a message cut by the end of the file; a clean end is a 3-byte header read
    that returns nothing."""

    def __init__(self, handle):
        self._handle = handle
        self.cut = False

    def read(self, size: int = -1) -> bytes:
        data = self._handle.read(size)
        self.cut = 0 <= size and len(data) < size and not (size == 3 and not data)
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._handle.seek(offset, whence)

    def tell(self) -> int:
        return self._handle.tell()

    def close(self) -> None:
        self._handle.close()


def read_flight_log(path: str | Path) -> FlightLog:
    """The captures and the attitude and position series of a ``.ulg`` file (rules in the module
    docstring). Warnings are logged once each, naming the file; ``SceneFormatError`` when unusable."""
    from pyulog import ULog, ULogException

    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(path, "no such ULog file")
    watched = _WatchedFile(path.open("rb"))
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints its findings; we report them
            ulog = ULog(watched, list(TOPICS), True)
    except ULogException as exc:
        raise SceneFormatError(path, f"not a readable ULog file ({exc})") from None
    finally:
        watched.close()
    topics = {}
    for topic in TOPICS:
        try:
            topics[topic] = ulog.get_dataset(topic).data
        except (IndexError, KeyError, ValueError):  # pyulog: IndexError when the topic is absent
            pass
    problems: list[str] = []
    if ulog.file_corruption:
        problems.append("damaged: pyulog skipped bytes it could not parse; the rest is used")
    elif watched.cut:  # after damage a bogus size can run past the end: "damaged" says it
        problems.append("cut short: a message runs past the end of the file; the messages before it are used")
    if "camera_capture" not in topics:
        raise SceneFormatError(path, "no camera_capture message: the log has no camera trigger to match photos to")
    captures = _captures(path, topics["camera_capture"])
    attitude = _attitude(path, topics.get("vehicle_attitude"))
    position = _global_position(path, topics.get("vehicle_global_position")) or _local_position(
        path, topics.get("vehicle_local_position")
    )
    if attitude is None:
        if not np.isfinite(captures.quats).all(-1).any():
            raise SceneFormatError(
                path, "no vehicle_attitude message and camera_capture.q is empty: no attitude for the photos"
            )
        problems.append(
            "no vehicle_attitude message: attitudes from camera_capture.q (copied when PX4 handled each trigger)"
        )
    if position is None:
        problems.append(
            "no vehicle_global_position or georeferenced vehicle_local_position: positions from camera_capture "
            "lat/lon/alt where valid"
        )
    for problem in problems:
        log.warning("%s: %s", path, problem)
    return FlightLog(path, captures, attitude, position, tuple(problems))


def _column(path: Path, data: dict, topic: str, name: str) -> np.ndarray:
    if name not in data:
        raise SceneFormatError(path, f"{topic} has no field {name!r} (fields: {', '.join(sorted(data))})")
    return np.asarray(data[name])


def _stamps(path: Path, data: dict, topic: str) -> np.ndarray:
    stamps = _column(path, data, topic, "timestamp").astype(np.int64)
    sample = np.asarray(data.get("timestamp_sample", np.zeros_like(stamps)), np.int64)
    return np.where(sample > 0, sample, stamps)


def _quats(path: Path, data: dict, topic: str) -> np.ndarray:
    """[N, 4] unit wxyz, NaN rows where the quaternion is not finite or far from unit."""
    q = np.stack([_column(path, data, topic, f"q[{i}]").astype(np.float64) for i in range(4)], -1)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    good = np.isfinite(q).all(-1, keepdims=True) & (np.abs(norm - 1.0) < 0.1)  # zeros = "not set"
    return np.where(good, q / np.where(good, norm, 1.0), np.nan)


def _track(stamps: np.ndarray, values: np.ndarray, topic: str) -> Track | None:
    good = np.isfinite(values).all(-1) & (stamps > 0)
    stamps, values = stamps[good], values[good]
    if len(stamps) == 0:
        return None
    order = np.argsort(stamps, kind="stable")
    stamps, values = stamps[order], values[order]
    last = np.r_[stamps[1:] != stamps[:-1], True]  # bracket() needs strictly increasing stamps
    return Track(stamps[last], values[last], topic)


def _flag(data: dict, name: str, n: int) -> np.ndarray:
    return np.asarray(data[name], bool) if name in data else np.ones(n, bool)


def _captures(path: Path, data: dict) -> Captures:
    stamps = _column(path, data, "camera_capture", "timestamp").astype(np.int64)
    n = len(stamps)
    utc = np.asarray(data.get("timestamp_utc", np.zeros(n)), np.int64)
    seq = np.asarray(data.get("seq", np.arange(n)), np.int64)
    ok = np.asarray(data["result"], np.int64) != 0 if "result" in data else np.ones(n, bool)
    geodetic = np.full((n, 3), np.nan)
    if {"lat", "lon", "alt"} <= data.keys():
        geodetic = np.stack([np.asarray(data[k], np.float64) for k in ("lat", "lon", "alt")], -1)
        geodetic[(geodetic[:, 0] == 0) & (geodetic[:, 1] == 0)] = np.nan  # (0, 0): no fix
    quats = _quats(path, data, "camera_capture") if "q[0]" in data else np.full((n, 4), np.nan)
    return Captures(stamps, utc, seq, ok, geodetic, quats)


def _attitude(path: Path, data: dict | None) -> Track | None:
    if data is None:
        return None
    return _track(_stamps(path, data, "vehicle_attitude"), _quats(path, data, "vehicle_attitude"), "vehicle_attitude")


def _global_position(path: Path, data: dict | None) -> Track | None:
    if data is None:
        return None
    topic = "vehicle_global_position"
    lla = np.stack([_column(path, data, topic, k).astype(np.float64) for k in ("lat", "lon", "alt")], -1)
    valid = _flag(data, "lat_lon_valid", len(lla)) & _flag(data, "alt_valid", len(lla))
    lla[~valid | ((lla[:, 0] == 0) & (lla[:, 1] == 0))] = np.nan
    return _track(_stamps(path, data, topic), lla, topic)


def _local_position(path: Path, data: dict | None) -> Track | None:
    if data is None:
        return None
    import pymap3d

    topic = "vehicle_local_position"
    x, y, z, lat0, lon0, alt0 = (
        _column(path, data, topic, k).astype(np.float64) for k in ("x", "y", "z", "ref_lat", "ref_lon", "ref_alt")
    )
    n = len(x)
    valid = _flag(data, "xy_valid", n) & _flag(data, "z_valid", n)
    valid &= _flag(data, "xy_global", n) & _flag(data, "z_global", n)
    lat, lon, alt = pymap3d.ned2geodetic(x, y, z, lat0, lon0, alt0)
    lla = np.stack([lat, lon, alt], -1)
    lla[~valid] = np.nan
    return _track(_stamps(path, data, topic), lla, topic)


def capture_poses(flight: FlightLog, tolerance_s: float = 0.5) -> list[CapturePose]:
    """The vehicle's pose at every capture (rules in the module docstring).

    tolerance_s  # each bracketing sample within this of the trigger (PX4 logs vehicle_global_position
                 # at 5 Hz by default, so less than 0.2 s would refuse most triggers)
    """
    if not tolerance_s > 0:
        raise ValueError(f"tolerance_s must be positive, got tolerance_s={tolerance_s}")
    tolerance_us = int(round(tolerance_s * 1e6))
    caps = flight.captures
    out = []
    for i, stamp in enumerate(caps.stamps_us.tolist()):
        reasons = []
        quat, att_source = None, ""
        if flight.attitude is not None:
            status, reason, q = interpolate_attitude(
                flight.attitude.stamps_us, flight.attitude.values, stamp, tolerance_us
            )
            if status == "ok":
                quat, att_source = q, flight.attitude.topic
            else:
                reasons.append(f"attitude:{reason}")
        if quat is None and np.isfinite(caps.quats[i]).all():
            quat, att_source = caps.quats[i], "camera_capture"
        where, pos_source = None, ""
        if flight.position is not None:
            status, reason, p = interpolate_position(
                flight.position.stamps_us, flight.position.values, stamp, tolerance_us
            )
            if status == "ok":
                where, pos_source = p, flight.position.topic
            else:
                reasons.append(f"position:{reason}")
        if where is None and np.isfinite(caps.geodetic[i]).all():
            where, pos_source = caps.geodetic[i], "camera_capture"
        out.append(
            CapturePose(
                i,
                int(caps.seq[i]),
                stamp,
                int(caps.utc_us[i]),
                bool(caps.ok[i]),
                quat,
                where,
                att_source,
                pos_source,
                ", ".join(reasons),
            )
        )
    return out


@dataclass(frozen=True)
class PhotoMatch:
    """Which capture took which photo."""

    capture_of_photo: np.ndarray  # [N] int64 index into the captures given; -1 = no match
    method: Literal["order", "time", "none"]
    offset_s: float | None = None  # "time": photo clock - capture clock, seconds
    tolerance_s: float | None = None  # "time": a pair is at most this far apart after the offset

    @property
    def matched(self) -> int:
        return int((self.capture_of_photo >= 0).sum())

    @property
    def unmatched(self) -> int:
        return int((self.capture_of_photo < 0).sum())


def match_photos(photo_stamps_ns: Sequence[int | None], capture_stamps_us, vote_photos: int = 200) -> PhotoMatch:
    """Pair photos (in shooting order) with the successful captures (in trigger order).

    photo_stamps_ns    # [N] ns since the Unix epoch (EXIF), None = unknown
    capture_stamps_us  # [M] µs, increasing: ``timestamp_utc`` when every capture has one, else ``timestamp``

    Equal counts: the i-th photo with the i-th capture (one trigger, one photo), unless the photo
    stamps contradict it (a photo's difference to its capture strays more than the tolerance from
    the median difference: a dropped photo and a stray one). Otherwise by time, with the camera's
    clock offset unknown (it is set by hand, or in another zone): every photo-capture difference
    votes for an offset; the offset matching the most pairs within ``tolerance`` = half the
    shortest interval between captures wins (a tie, which regular triggering makes possible, goes
    to the offset nearest zero), refined by the median of its pairs' residuals. Then each photo
    takes the nearest capture within the tolerance, one photo per capture (the nearest keeps it).
    A constant offset is assumed (drift of the camera clock over a flight must stay inside the
    tolerance); ``vote_photos`` evenly spaced photos vote, bounding the work.
    """
    captures = np.asarray(capture_stamps_us, np.int64) / 1e6  # seconds
    n, m = len(photo_stamps_ns), len(captures)
    known = np.array([s is not None for s in photo_stamps_ns], bool)
    photos = np.array([s if s is not None else 0 for s in photo_stamps_ns], np.int64) / 1e9
    gaps = np.diff(captures)
    tolerance = 0.5 * float(gaps[gaps > 0].min()) if (gaps > 0).any() else 0.5
    if n == m and n > 0:
        residuals = photos[known] - captures[known]
        if not known.any() or np.abs(residuals - np.median(residuals)).max() <= tolerance:
            return PhotoMatch(np.arange(n, dtype=np.int64), "order")
        # the stamps contradict one-to-one (a dropped photo and a stray one): match by time
    if m == 0 or not known.any():
        return PhotoMatch(np.full(n, -1, np.int64), "none")
    voters = np.flatnonzero(known)
    voters = voters[np.unique(np.linspace(0, len(voters) - 1, min(len(voters), vote_photos)).round().astype(int))]
    diffs = np.sort((photos[voters, None] - captures[None, :]).reshape(-1))
    ends = np.searchsorted(diffs, diffs + tolerance, side="right")
    counts = ends - np.arange(len(diffs))
    best = np.flatnonzero(counts == counts.max())
    centres = np.array([np.median(diffs[i : ends[i]]) for i in best])
    offset = float(centres[np.argmin(np.abs(centres))])
    for _ in range(2):  # pair, then re-centre the offset on the pairs found
        pairs, residuals = _nearest(photos, known, captures, offset, tolerance)
        if (pairs >= 0).any():
            offset += float(np.median(residuals[pairs >= 0]))
    pairs, _ = _nearest(photos, known, captures, offset, tolerance)
    return PhotoMatch(pairs, "time", offset, tolerance)


def _nearest(photos, known, captures, offset: float, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Each known photo's nearest capture within ``tolerance`` after the offset, one photo per
    capture: ([N] capture index or -1, [N] residual seconds)."""
    shifted = photos - offset
    right = (
        np.clip(np.searchsorted(captures, shifted), 1, len(captures) - 1)
        if len(captures) > 1
        else np.zeros(len(photos), np.int64)
    )
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(captures[left] - shifted) <= np.abs(captures[right] - shifted), left, right)
    residuals = shifted - captures[nearest]
    pairs = np.where(known & (np.abs(residuals) <= tolerance), nearest, -1)
    for j in np.unique(pairs[pairs >= 0]):  # a capture claimed twice: the nearer photo keeps it
        claimants = np.flatnonzero(pairs == j)
        pairs[claimants[claimants != claimants[np.argmin(np.abs(residuals[claimants]))]]] = -1
    return pairs.astype(np.int64), residuals
