"""Camera sources for the ingest node: replay logs, folders of geotagged photos, OAK cameras.

``open_source(spec)`` builds one from the ingest's flat parameters (``SourceParams``, README.md
beside this file). A source is polled: ``read(timeout_s) -> SourceFrame | None``, ``done``,
``stats``, ``status() -> (level, message)`` (DiagnosticStatus levels 0 OK .. 3 STALE).
The replay log format (MCAP write/read, image folders + COLMAP) is ``replay_log``.
"""

from .base import ERROR, OK, STALE, WARN, PacedSource, Pacer, Source, SourceFrame
from .exif import (
    ExifFolderSource,
    ExifPhoto,
    camera_rotation,
    focal_length_px,
    headings_from_track,
    pose_priors,
    read_exif,
)
from .oak import DepthAISource, camera_from_calibration, crop_intrinsics, discover_devices, trim_distortion
from .open import SOURCE_DEFAULTS, SOURCE_KINDS, SourceParams, open_source, telemetry_config
from .replay import ReplaySource

__all__ = [
    "ERROR",
    "OK",
    "SOURCE_DEFAULTS",
    "SOURCE_KINDS",
    "STALE",
    "WARN",
    "DepthAISource",
    "ExifFolderSource",
    "ExifPhoto",
    "PacedSource",
    "Pacer",
    "ReplaySource",
    "Source",
    "SourceFrame",
    "SourceParams",
    "camera_from_calibration",
    "camera_rotation",
    "crop_intrinsics",
    "discover_devices",
    "focal_length_px",
    "headings_from_track",
    "open_source",
    "pose_priors",
    "read_exif",
    "telemetry_config",
    "trim_distortion",
]
