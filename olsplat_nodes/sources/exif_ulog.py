"""A PX4 flight log (ULog) beside a photo folder: each photo's pose prior from the vehicle's pose at
the camera trigger that took it (rules in ``telemetry/ulog.py``), for ``ExifFolderSource``.

A matched photo takes the log's attitude (heading, pitch and roll of the vehicle, through the
camera mount) and the log's position (EXIF GPS when the log has none); a photo without EXIF GPS
is kept when its trigger has a position. Every other photo keeps its EXIF-only prior.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError
from ..telemetry.pose import CameraMount
from ..telemetry.ulog import CapturePose, PhotoMatch, capture_poses, match_photos, read_flight_log

log = logging.getLogger(__name__)

ULOG_OFF = "none"  # exif_ulog value that turns the log off


def find_ulog(folder: Path, setting: str) -> Path | None:
    """The log ``exif_ulog`` names: a path; "" = the one ``*.ulg`` file in the photo folder (none:
    no log; several: no log, one warning); "none" = no log."""
    if setting.strip().lower() == ULOG_OFF:
        return None
    if setting:
        path = Path(setting).expanduser()
        if not path.is_file():
            raise OlsplatInputError(f"exif_folder source: exif_ulog={setting!r} is not a file")
        return path
    logs = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".ulg" and p.is_file())
    if len(logs) > 1:
        log.warning(
            "exif_folder %s: %d .ulg files (%s): none used; set exif_ulog to one of them",
            folder,
            len(logs),
            ", ".join(p.name for p in logs[:5]),
        )
    return logs[0] if len(logs) == 1 else None


@dataclass(frozen=True)
class UlogPriors:
    """The log's poses for the photos of a folder."""

    path: Path
    match: PhotoMatch  # over the photos in shooting order and the successful triggers
    pose_of_photo: dict[Path, CapturePose]  # photos whose trigger has an attitude
    triggers: int  # successful captures in the log

    def with_log_positions(self, photos: list) -> list:
        """``photos`` (``ExifPhoto``) with the trigger's position filled in where EXIF has no GPS."""
        out = []
        for photo in photos:
            pose = self.pose_of_photo.get(photo.path)
            if not photo.has_gps and pose is not None and pose.geodetic is not None:
                lat, lon, alt = (float(v) for v in pose.geodetic)
                photo = dataclasses.replace(photo, lat=lat, lon=lon, alt=alt)
            out.append(photo)
        return out

    def apply(self, photos: list, poses: np.ndarray, heading_sources: list[str], reference, mount: CameraMount) -> None:
        """Replace, in place, the priors (``poses`` [N, 4, 4], ``heading_sources`` [N]) of the
        matched ``photos`` by the log's, in the world around ``reference``."""
        for i, photo in enumerate(photos):
            pose = self.pose_of_photo.get(photo.path)
            if pose is None:
                continue
            world_from_camera = pose.world_from_camera(reference, mount, (photo.lat, photo.lon, photo.alt))
            if world_from_camera is not None:
                poses[i] = world_from_camera
                heading_sources[i] = pose.attitude_source


def ulog_priors(photos: list, path: Path, tolerance_s: float = 0.5) -> UlogPriors:
    """Read the log, interpolate the vehicle's pose at each successful trigger and match the photos
    (``ExifPhoto``, any order) to the triggers. Logs one INFO line with the match and one WARN
    naming how many photos keep their EXIF-only prior."""
    flight = read_flight_log(path)
    triggers = [p for p in capture_poses(flight, tolerance_s) if p.ok]
    by_utc = bool(triggers) and all(p.utc_us > 0 for p in triggers)
    order = (
        sorted(photos, key=lambda p: (p.stamp_ns, p.path.name))
        if all(p.stamp_ns is not None for p in photos)
        else photos
    )
    match = match_photos([p.stamp_ns for p in order], [p.utc_us if by_utc else p.stamp_us for p in triggers])
    pose_of_photo: dict[Path, CapturePose] = {}
    refused: Counter[str] = Counter()
    for photo, j in zip(order, match.capture_of_photo.tolist(), strict=True):
        if j >= 0 and triggers[j].quat_ned_from_body is not None:
            pose_of_photo[photo.path] = triggers[j]
        elif j >= 0:
            refused[triggers[j].reason or "no attitude"] += 1
    how = {
        "order": "in order (as many photos as triggers)",
        "time": f"by time (photo clock - log {'UTC' if by_utc else 'boot time'} {match.offset_s or 0.0:+.2f} s, "
        f"pairs within {match.tolerance_s or 0.0:.2f} s)",
        "none": "(no photo stamps to match by time)",
    }[match.method]
    sources = sorted({(p.attitude_source, p.position_source or "EXIF") for p in pose_of_photo.values()})
    log.info(
        "%s: %d of %d photos matched to %d camera_capture triggers %s; attitude, position from %s",
        path,
        match.matched,
        len(order),
        len(triggers),
        how,
        sources,
    )
    left = len(order) - len(pose_of_photo)
    if left:
        why = [f"{match.unmatched} without a trigger"] if match.unmatched else []
        why += [f"{n} whose trigger has no attitude ({reason})" for reason, n in sorted(refused.items())]
        log.warning("%s: %d of %d photos keep their EXIF-only prior: %s", path, left, len(order), "; ".join(why))
    return UlogPriors(path, match, pose_of_photo, len(triggers))
