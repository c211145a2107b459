"""``open_source(spec)``: a source from flat node parameters (the names the ingest node and
``olsplat record`` take; README.md beside this file documents each)."""

from __future__ import annotations

import time
from dataclasses import fields

import numpy as np

from ..telemetry import TelemetryConfig
from .base import Source

SOURCE_KINDS = ("replay", "exif_folder", "depthai")


def _yaml_value(value):
    return list(value) if isinstance(value, tuple) else ([] if value is None else value)


_TELEMETRY_FIELDS = {f.name: f.default for f in fields(TelemetryConfig)}

SOURCE_DEFAULTS = {
    "source_kind": "replay",  # replay | exif_folder | depthai
    "source": "",  # replay: a replay log (.mcap) or a folder with images/ + COLMAP model; exif_folder: a folder of JPEGs
    "rate_hz": 0.0,  # replay, exif_folder: 0 = the recorded pace
    "fast": False,  # replay, exif_folder: as fast as possible
    "exif_reference": [],  # exif_folder: [lat_deg, lon_deg, alt_m] of the ENU world origin; [] = the first photo
    "exif_focal_px": 0.0,  # exif_folder: focal length in pixels; 0 = from EXIF
    "exif_sensor_width_mm": 0.0,  # exif_folder: sensor width when EXIF has only FocalLength
    "depthai_device": "",  # depthai: device id or name; "" = the first found
    "depthai_socket": "CAM_A",  # depthai: dai.CameraBoardSocket name
    "depthai_width": 1280,  # depthai: output size in pixels (CROP resize of the sensor)
    "depthai_height": 720,
    "depthai_fps": 10.0,
    "depthai_retry_s": 3.0,  # depthai: look for a device this often while none is streaming
    "depthai_frame_timeout_s": 3.0,  # depthai: no frame for this long = device lost, reconnect
    "depthai_max_pending": 30,  # depthai: frames kept while waiting for telemetry (oldest dropped beyond)
    "fixed_pose": [],  # depthai without telemetry: 16 numbers, row-major world_from_camera; [] = nadir at the origin, image top north
    **{
        f"telemetry_{name}": _yaml_value(default) for name, default in _TELEMETRY_FIELDS.items()
    },  # telemetry_url "" = no telemetry
}


def telemetry_config(spec: dict) -> TelemetryConfig | None:
    """The ``TelemetryConfig`` of ``telemetry_*`` params, or None when ``telemetry_url`` is empty."""
    params = {name: spec.get(f"telemetry_{name}", SOURCE_DEFAULTS[f"telemetry_{name}"]) for name in _TELEMETRY_FIELDS}
    if not params["url"]:
        return None
    for name in ("reference", "mount_matrix"):
        if params[name] in ([], (), "", None):
            params[name] = None
    return TelemetryConfig.from_params(params)


def fixed_world_from_camera(values) -> np.ndarray:
    from .exif import camera_rotation

    if not values:
        pose = np.eye(4)
        pose[:3, :3] = camera_rotation(0.0)
        return pose
    pose = np.asarray(values, np.float64)
    if pose.size != 16:
        raise ValueError(f"fixed_pose must be 16 numbers (row-major world_from_camera), got {len(pose.reshape(-1))}")
    return pose.reshape(4, 4)


def open_source(spec: dict) -> Source:
    """A source from flat params (missing keys take ``SOURCE_DEFAULTS``; unknown keys: ValueError)."""
    unknown = sorted(set(spec) - set(SOURCE_DEFAULTS))
    if unknown:
        raise ValueError(f"unknown source parameter(s) {unknown}; known: {sorted(SOURCE_DEFAULTS)}")
    p = {**SOURCE_DEFAULTS, **spec}
    kind = p["source_kind"]
    if kind == "replay":
        from .replay import ReplaySource

        return ReplaySource(p["source"], p["rate_hz"] or None, p["fast"])
    if kind == "exif_folder":
        from .exif import ExifFolderSource

        return ExifFolderSource(
            p["source"],
            p["rate_hz"] or None,
            p["fast"],
            reference=p["exif_reference"] or None,
            focal_px=float(p["exif_focal_px"]),
            sensor_width_mm=float(p["exif_sensor_width_mm"]),
        )
    if kind == "depthai":
        from ..telemetry import FlightControllerPoses
        from .oak import DepthAISource

        config = telemetry_config(p)
        poses = FlightControllerPoses(config, clock=time.monotonic_ns) if config else None
        return DepthAISource(
            p["depthai_device"],
            p["depthai_socket"],
            int(p["depthai_width"]),
            int(p["depthai_height"]),
            float(p["depthai_fps"]),
            retry_s=float(p["depthai_retry_s"]),
            frame_timeout_s=float(p["depthai_frame_timeout_s"]),
            poses=poses,
            world_from_camera=fixed_world_from_camera(p["fixed_pose"]),
            max_pending=int(p["depthai_max_pending"]),
        )
    raise ValueError(f"source_kind must be one of {', '.join(SOURCE_KINDS)}, got source_kind={kind!r}")
