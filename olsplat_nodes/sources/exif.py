"""A folder of aerial photos without a COLMAP model: poses and intrinsics from their EXIF/XMP.

Pose prior (world = ENU metres around the first photo, or ``reference``; camera = OpenCV axes):
- position: EXIF GPS latitude/longitude/altitude, converted exactly through WGS-84
  (``telemetry.pose.geodetic_to_ned``). GPS altitude is above mean sea level; only differences
  matter, so the world origin is at the first photo's altitude (the ground is at z < 0).
- orientation: a nadir camera (straight down) unless DJI XMP gimbal angles say otherwise, with the
  image top towards a compass heading from, in this order, XMP ``drone-dji:GimbalYawDegree``,
  ``drone-dji:FlightYawDegree``, ``Camera:Yaw``, else the direction of travel to the next photo
  (the last photo: from the previous one; a photo taken while hovering: its neighbour's).
  Angles follow DJI: yaw clockwise from north, gimbal pitch -90 = nadir, which is exactly
  ``telemetry.pose.mount_rotation(roll, pitch, yaw)`` written in NED.
- a PX4 flight log (``.ulg``) beside the photos (or ``ulog``) replaces both for each photo matched
  to a camera trigger: the vehicle's interpolated position and attitude at the trigger, through
  the camera mount ``mount_rpy_deg`` (rules in ``exif_ulog.py`` and ``telemetry/ulog.py``).
- intrinsics: pinhole, principal point at the image centre, no distortion; focal length in pixels
  from ``focal_px`` when given, else ``FocalLengthIn35mmFilm`` (35 mm equivalent, by the
  diagonal as the EXIF standard defines it), else ``FocalLength`` × ``FocalPlaneXResolution``
  (pixels per unit on the sensor, for an image ``ExifImageWidth`` wide: scaled to the actual
  width, so downscaled copies work), else ``FocalLength`` and ``sensor_width_mm``.
- stamps: ``DateTimeOriginal`` (+ ``SubSecTimeOriginal``), in the zone of ``OffsetTimeOriginal``;
  without one, the zone is derived from the GPS UTC time (``GPSDateStamp``/``GPSTimeStamp``,
  rounded to 15 minutes); without both, the local time is taken as UTC.

Images are decoded as stored (the EXIF Orientation tag is not applied: intrinsics and pose refer
to the sensor's layout).
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import OlsplatInputError
from ..scene import Camera
from ..scene.geodesy import Georeference
from ..telemetry.pose import ENU_FROM_NED, CameraMount, geodetic_to_ned, mount_rotation
from .base import PacedSource, SourceFrame
from .exif_ulog import find_ulog, ulog_priors

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg")
_GPS_IFD, _EXIF_IFD = 0x8825, 0x8769
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # FocalPlaneResolutionUnit -> millimetres per unit
_XMP_KEYS = {
    "gimbal_yaw": ("drone-dji:GimbalYawDegree",),
    "gimbal_pitch": ("drone-dji:GimbalPitchDegree",),
    "gimbal_roll": ("drone-dji:GimbalRollDegree",),
    "flight_yaw": ("drone-dji:FlightYawDegree", "Camera:Yaw"),
}


@dataclass
class ExifPhoto:
    """What one photo's metadata says (None: absent)."""

    path: Path
    width: int  # pixels, as stored
    height: int
    lat: float | None = None  # degrees, north positive
    lon: float | None = None  # degrees, east positive
    alt: float | None = None  # metres above mean sea level
    stamp_ns: int | None = None  # ns since the Unix epoch (UTC)
    stamp_source: str = "none"  # "offset", "gps_zone", "local_as_utc", "none"
    focal_mm: float | None = None
    focal_35mm: float | None = None
    focal_plane_px_per_mm: float | None = None  # at an image exif_width pixels wide
    exif_width: int | None = None
    orientation: int = 1
    gimbal_yaw: float | None = None  # degrees clockwise from north
    gimbal_pitch: float | None = None  # degrees, -90 = nadir
    gimbal_roll: float | None = None
    flight_yaw: float | None = None

    @property
    def has_gps(self) -> bool:
        return self.lat is not None and self.lon is not None and self.alt is not None


def _float(value) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return out if math.isfinite(out) else None


def _dms(value, ref) -> float | None:
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    sign = -1.0 if str(ref).strip().upper() in ("S", "W") else 1.0
    return sign * (d + m / 60.0 + s / 3600.0)


def _xmp_value(xmp: str, key: str) -> float | None:
    # attribute form (key="12.3") or element form (<key>12.3</key>)
    match = re.search(re.escape(key) + r'\s*=\s*"([^"]*)"', xmp) or re.search("<" + re.escape(key) + r">([^<]*)<", xmp)
    return _float(match.group(1)) if match else None


def _stamp(exif_ifd: dict, gps: dict) -> tuple[int | None, str]:
    text = exif_ifd.get(0x9003)  # DateTimeOriginal
    try:
        local = dt.datetime.strptime(str(text).strip(), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None, "none"
    subsec = str(exif_ifd.get(0x9291, "") or "").strip()  # SubSecTimeOriginal
    if subsec.isdigit():
        local += dt.timedelta(seconds=float("0." + subsec))
    offset_text = str(exif_ifd.get(0x9011, "") or "").strip()  # OffsetTimeOriginal "+02:00"
    match = re.fullmatch(r"([+-])(\d\d):(\d\d)", offset_text)
    if match:
        sign = -1 if match.group(1) == "-" else 1
        zone = dt.timezone(sign * dt.timedelta(hours=int(match.group(2)), minutes=int(match.group(3))))
        source = "offset"
    else:
        zone, source = dt.UTC, "local_as_utc"
        try:
            h, m, s = (float(v) for v in gps[7])  # GPSTimeStamp (UTC)
            day = dt.datetime.strptime(str(gps[29]).strip(), "%Y:%m:%d")  # GPSDateStamp
            utc = day + dt.timedelta(hours=h, minutes=m, seconds=s)
            quarter = round((local.replace(microsecond=0) - utc).total_seconds() / 900.0) * 900
            if abs(quarter) <= 14 * 3600:
                zone, source = dt.timezone(dt.timedelta(seconds=quarter)), "gps_zone"
        except (KeyError, TypeError, ValueError, ZeroDivisionError):
            pass
    stamp = local.replace(tzinfo=zone)
    return int(round(stamp.timestamp() * 1e6)) * 1000, source


def read_exif(path: str | Path) -> ExifPhoto:
    """The metadata of one JPEG (Pillow reads only the header here)."""
    from PIL import Image

    path = Path(path)
    with Image.open(path) as image:
        exif = image.getexif()
        xmp_raw = image.info.get("xmp", b"")
        photo = ExifPhoto(path, image.width, image.height)
    gps = dict(exif.get_ifd(_GPS_IFD))
    exif_ifd = dict(exif.get_ifd(_EXIF_IFD))
    photo.orientation = int(exif.get(0x0112, 1) or 1)
    if 2 in gps and 4 in gps:
        photo.lat, photo.lon = _dms(gps[2], gps.get(1, "N")), _dms(gps[4], gps.get(3, "E"))
    altitude = _float(gps.get(6))
    if altitude is not None:
        below = gps.get(5, 0)
        below = below[0] if isinstance(below, bytes) and below else below
        photo.alt = -altitude if below == 1 else altitude
    photo.stamp_ns, photo.stamp_source = _stamp(exif_ifd, gps)
    photo.focal_mm = _float(exif_ifd.get(0x920A))
    photo.focal_35mm = _float(exif_ifd.get(0xA405)) or None
    resolution, unit = _float(exif_ifd.get(0xA20E)), exif_ifd.get(0xA210, 2)
    exif_width = exif_ifd.get(0xA002)
    if resolution and unit in _UNIT_MM:
        photo.focal_plane_px_per_mm = resolution / _UNIT_MM[unit]
        photo.exif_width = int(exif_width) if exif_width else photo.width
    xmp = xmp_raw.decode("utf-8", "replace") if isinstance(xmp_raw, bytes) else str(xmp_raw)
    for field, keys in _XMP_KEYS.items():
        for key in keys:
            value = _xmp_value(xmp, key)
            if value is not None:
                setattr(photo, field, value)
                break
    return photo


def focal_length_px(photo: ExifPhoto, sensor_width_mm: float = 0.0) -> tuple[float, str]:
    """(focal length in pixels of the stored image, which rule gave it); ValueError if none can."""
    if photo.focal_35mm:
        return photo.focal_35mm * math.hypot(photo.width, photo.height) / math.hypot(
            36.0, 24.0
        ), "FocalLengthIn35mmFilm"
    if photo.focal_mm and photo.focal_plane_px_per_mm:
        scale = photo.width / photo.exif_width if photo.exif_width else 1.0
        return photo.focal_mm * photo.focal_plane_px_per_mm * scale, "FocalLength+FocalPlaneXResolution"
    if photo.focal_mm and sensor_width_mm > 0:
        return photo.focal_mm * photo.width / sensor_width_mm, "FocalLength+sensor_width_mm"
    raise ValueError(
        f"{photo.path.name}: no focal length in pixels can be derived from its EXIF "
        f"(FocalLength={photo.focal_mm}, FocalLengthIn35mmFilm={photo.focal_35mm}); set exif_focal_px or "
        "exif_sensor_width_mm"
    )


def headings_from_track(positions_enu: np.ndarray, min_step_m: float = 0.5) -> np.ndarray:
    """[N] compass headings (degrees clockwise from north) of the direction of travel.

    positions_enu  # [N, 3] metres
    Photo i looks towards photo i+1 (the last one: from its predecessor); steps shorter than
    ``min_step_m`` (hovering) take the nearest valid neighbour's heading; all 0 without any.
    """
    positions = np.asarray(positions_enu, np.float64)
    n = len(positions)
    steps = np.diff(positions[:, :2], axis=0)  # [N-1, 2] east, north
    valid = np.hypot(steps[:, 0], steps[:, 1]) >= min_step_m
    step_headings = np.degrees(np.arctan2(steps[:, 0], steps[:, 1])) % 360.0
    out = np.zeros(n)
    if not valid.any():
        return out
    good = np.flatnonzero(valid)
    for i in range(n):
        j = min(i, n - 2)  # photo i uses step i (the last photo: step i-1)
        if not valid[j]:
            j = good[np.argmin(np.abs(good - j))]
        out[i] = step_headings[j]
    return out


def camera_rotation(yaw_deg: float, pitch_deg: float = -90.0, roll_deg: float = 0.0) -> np.ndarray:
    """[3, 3] world (ENU) from camera (OpenCV) for DJI-style angles: yaw clockwise from north (the
    image top's heading for a nadir camera), pitch -90 = straight down."""
    return ENU_FROM_NED @ mount_rotation(roll_deg, pitch_deg, yaw_deg)


def pose_priors(photos: list[ExifPhoto], reference=None) -> tuple[np.ndarray, tuple[float, float, float], list[str]]:
    """([N, 4, 4] world_from_camera, the reference (lat, lon, alt), heading source per photo)."""
    reference = tuple(float(v) for v in reference) if reference else (photos[0].lat, photos[0].lon, photos[0].alt)
    ned = geodetic_to_ned([p.lat for p in photos], [p.lon for p in photos], [p.alt for p in photos], reference)
    positions = ned @ ENU_FROM_NED.T  # [N, 3] ENU
    travel = headings_from_track(positions)
    poses = np.tile(np.eye(4), (len(photos), 1, 1))
    sources = []
    for i, photo in enumerate(photos):
        if photo.gimbal_yaw is not None:
            yaw, source = photo.gimbal_yaw, "gimbal_yaw"
        elif photo.flight_yaw is not None:
            yaw, source = photo.flight_yaw, "flight_yaw"
        else:
            yaw, source = travel[i], "travel"
        pitch = photo.gimbal_pitch if photo.gimbal_pitch is not None else -90.0
        roll = photo.gimbal_roll if photo.gimbal_roll is not None else 0.0
        poses[i, :3, :3] = camera_rotation(yaw, pitch, roll)
        poses[i, :3, 3] = positions[i]
        sources.append(source)
    return poses, reference, sources


class ExifFolderSource(PacedSource):
    """Photos of a folder (``*.jpg``/``*.jpeg``, sorted by stamp then name) with EXIF pose priors."""

    kind = "exif_folder"

    def __init__(
        self,
        folder: str | Path,
        rate_hz: float | None = None,
        fast: bool = False,
        *,
        reference=None,
        focal_px: float = 0.0,
        sensor_width_mm: float = 0.0,
        ulog: str = "",
        mount_rpy_deg=(0.0, -90.0, 0.0),
        ulog_tolerance_s: float = 0.5,
    ):
        folder = Path(folder)
        if not folder.is_dir():
            raise OlsplatInputError(f"exif_folder source: {folder} is not a folder")
        self.folder, self.reference_given = folder, bool(reference)
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        photos = [read_exif(p) for p in files]
        # a PX4 log beside the photos: poses at the camera triggers (exif_ulog.py)
        ulog_path = find_ulog(folder, ulog)
        self.ulog = ulog_priors(photos, ulog_path, ulog_tolerance_s) if ulog_path else None
        if self.ulog:
            photos = self.ulog.with_log_positions(photos)
        without_gps = [p.path.name for p in photos if not p.has_gps]
        photos = [p for p in photos if p.has_gps]
        if without_gps:
            log.warning("%d photos without EXIF GPS skipped: %s", len(without_gps), ", ".join(without_gps[:5]))
        if not photos:
            raise OlsplatInputError(
                f"exif_folder source: no JPEG with EXIF GPS latitude/longitude/altitude in {folder} ({len(files)} "
                "JPEG files)"
            )
        if all(p.stamp_ns is not None for p in photos):
            photos.sort(key=lambda p: (p.stamp_ns, p.path.name))
        self.photos = photos
        self.poses, self.reference, self.heading_sources = pose_priors(photos, reference)
        if self.ulog:
            mount = CameraMount.from_angles(*(float(a) for a in mount_rpy_deg))
            self.ulog.apply(photos, self.poses, self.heading_sources, self.reference, mount)
        self.cameras = []
        self.focal_rules = []
        for photo, pose in zip(photos, self.poses, strict=True):
            try:
                f, rule = (
                    (float(focal_px), "exif_focal_px") if focal_px > 0 else focal_length_px(photo, sensor_width_mm)
                )
            except ValueError as exc:
                raise OlsplatInputError(f"exif_folder source: {exc}") from None
            K = np.array([[f, 0.0, photo.width / 2.0], [0.0, f, photo.height / 2.0], [0.0, 0.0, 1.0]])
            self.cameras.append(Camera(photo.path.name, photo.width, photo.height, K, pose))
            self.focal_rules.append(rule)
        super().__init__(self._frames_of(), rate_hz, fast)
        self.counts.update(photos=len(photos), photos_without_gps=len(without_gps), unreadable_images=0)
        if self.ulog:
            self.counts.update(ulog_matched=len(self.ulog.pose_of_photo), ulog_triggers=self.ulog.triggers)
        log.info(
            "exif_folder %s: %d photos, world origin (ENU) lat %.7f lon %.7f alt %.2f m; headings from %s; focal from "
            "%s",
            folder,
            len(photos),
            *self.reference,
            sorted(set(self.heading_sources)),
            sorted(set(self.focal_rules)),
        )

    def georeference(self) -> Georeference:
        """The world's ENU origin: the reference photo's GPS position, altitude above mean sea
        level (EXIF GPS altitude is MSL)."""
        lat, lon, alt = (float(v) for v in self.reference)
        where = "exif_reference" if self.reference_given else "the first photo's GPS position"
        return Georeference(lat, lon, alt, height_ref="msl", source=f"exif_folder {self.folder}: {where}")

    def _frames_of(self):
        first = next((p.stamp_ns for p in self.photos if p.stamp_ns is not None), 0)
        for seq, (photo, camera) in enumerate(zip(self.photos, self.cameras, strict=True)):
            data = photo.path.read_bytes()
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
            if image is None:
                self.counts["unreadable_images"] += 1
                log.warning("%s: does not decode, skipped", photo.path)
                continue
            if image.shape[:2] != (camera.height, camera.width):
                self.counts["unreadable_images"] += 1
                log.warning(
                    "%s: decodes to %s, header says %dx%d: skipped",
                    photo.path,
                    image.shape[:2],
                    camera.width,
                    camera.height,
                )
                continue
            stamp = photo.stamp_ns if photo.stamp_ns is not None else first + seq * 1_000_000_000
            # the original bytes decode to this same image only when no EXIF rotation applies
            jpeg = data if photo.orientation == 1 else None
            yield SourceFrame(seq, stamp, photo.path.name, np.ascontiguousarray(image[..., ::-1]), camera, jpeg)
