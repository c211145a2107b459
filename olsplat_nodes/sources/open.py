"""``open_source(spec)``: a source from flat node parameters (the names the ingest node and
``olsplat record`` take; README.md beside this file documents each)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields
from typing import Literal

import numpy as np

from ..params import field_defaults, parse_params
from ..telemetry import TelemetryConfig
from .base import Source

SOURCE_KINDS = ("replay", "exif_folder", "depthai")


@dataclass(frozen=True)
class SourceParams:
    """The flat source parameters of the ingest node and ``olsplat record`` (README.md beside
    this file documents each)."""

    source_kind: Literal["replay", "exif_folder", "depthai"] = "replay"
    source: str = ""  # replay: a replay log (.mcap), a folder (images/ + COLMAP) or a ROS 2 bag; exif_folder: JPEGs
    rate_hz: float = 0.0  # replay, exif_folder: 0 = the recorded pace
    fast: bool = False  # replay, exif_folder: as fast as possible
    exif_reference: tuple[float, ...] = ()  # exif_folder: (lat_deg, lon_deg, alt_m) of the ENU origin; () = first photo
    exif_focal_px: float = 0.0  # exif_folder: focal length in pixels; 0 = from EXIF
    exif_sensor_width_mm: float = 0.0  # exif_folder: sensor width when EXIF has only FocalLength
    exif_ulog: str = ""  # exif_folder: PX4 log (.ulg); "" = the folder's only *.ulg, if one; "none" = no log
    exif_mount_rpy_deg: tuple[float, float, float] = (0.0, -90.0, 0.0)  # exif_folder + log: camera mount, body FRD
    exif_ulog_tolerance_s: float = 0.5  # exif_folder + log: log samples this close to a trigger
    # bag_*: a ROS 2 bag as the replay source (sources/rosbag.py BagParams)
    bag_image_topic: str = ""  # replay, bag: Image or CompressedImage topic; "" = the only one
    bag_camera_info_topic: str = ""  # replay, bag: CameraInfo topic; "" = the only one (or the image's sibling)
    bag_pose_topic: str = ""  # replay, bag: Odometry/PoseStamped topic; "" = tf (the only one without /tf)
    bag_world_frame: str = "map"  # replay, bag: the tf world frame (ENU, REP-105)
    bag_camera_frame: str = ""  # replay, bag: the camera's tf frame; "" = the image's header.frame_id
    bag_body_frame: str = ""  # replay, bag + pose topic: the frame the poses are of; "" = Odometry child_frame_id
    bag_mount: tuple[float, ...] = ()  # replay, bag + pose topic: 16 numbers, row-major body_from_camera; () = tf
    bag_camera_axes: Literal["optical", "link"] = "optical"  # replay, bag: camera frame axes, optical or FLU link
    bag_tolerance_s: float = 0.1  # replay, bag: a pose needs samples this close before and after a frame
    bag_undistort: bool = True  # replay, bag: remap distorted frames to the pinhole image of K; false keeps D
    depthai_device: str = ""  # depthai: device id or name; "" = the first found
    depthai_socket: str = "CAM_A"  # depthai: dai.CameraBoardSocket name
    depthai_width: int = 1280  # depthai: output size in pixels (CROP resize of the sensor)
    depthai_height: int = 720
    depthai_fps: float = 10.0
    depthai_retry_s: float = 3.0  # depthai: look for a device this often while none is streaming
    depthai_frame_timeout_s: float = 3.0  # depthai: no frame for this long = device lost, reconnect
    depthai_max_pending: int = 30  # depthai: frames kept while waiting for telemetry (oldest dropped beyond)
    # depthai without telemetry: 16 numbers, row-major world_from_camera; () = nadir at the origin, image top north
    fixed_pose: tuple[float, ...] = ()
    # telemetry_*: TelemetryConfig's fields (telemetry/config.py); telemetry_url "" = no telemetry
    telemetry_url: str = ""
    telemetry_baudrate: int = 57600
    telemetry_dialect: str = "all"
    telemetry_attitude: Literal["ATTITUDE", "ATTITUDE_QUATERNION"] = "ATTITUDE"
    telemetry_position: Literal["local", "global"] = "local"
    telemetry_reference: tuple[float, float, float] | None = None
    telemetry_mount_rpy_deg: tuple[float, float, float] = (0.0, -90.0, 0.0)
    telemetry_mount_matrix: tuple[float, ...] | None = None
    telemetry_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    telemetry_tolerance_s: float = 0.1
    telemetry_max_wait_s: float = 1.0
    telemetry_buffer_len: int = 1000
    telemetry_clock: Literal["receive", "system_time"] = "receive"
    telemetry_clock_window_s: float = 10.0


SOURCE_DEFAULTS = field_defaults(SourceParams)  # name -> default, for tools that list them


def telemetry_config(spec: dict | SourceParams) -> TelemetryConfig | None:
    """The ``TelemetryConfig`` of ``telemetry_*`` params, or None when ``telemetry_url`` is empty."""
    p = spec if isinstance(spec, SourceParams) else parse_params(SourceParams, spec, "source")
    params = {f.name: getattr(p, f"telemetry_{f.name}") for f in fields(TelemetryConfig)}
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


def open_source(spec: dict | SourceParams) -> Source:
    """A source from flat params (a mapping checked against ``SourceParams``: unknown names and
    wrong types are a ``ParameterError``, a ValueError), or from ``SourceParams`` itself."""
    p = asdict(spec) if isinstance(spec, SourceParams) else asdict(parse_params(SourceParams, spec, "source"))
    kind = p["source_kind"]
    if kind == "replay":
        from .replay import ReplaySource

        bag = {name: value for name, value in p.items() if name.startswith("bag_")}
        return ReplaySource(p["source"], p["rate_hz"] or None, p["fast"], bag=bag)
    if kind == "exif_folder":
        from .exif import ExifFolderSource

        return ExifFolderSource(
            p["source"],
            p["rate_hz"] or None,
            p["fast"],
            reference=p["exif_reference"] or None,
            focal_px=float(p["exif_focal_px"]),
            sensor_width_mm=float(p["exif_sensor_width_mm"]),
            ulog=p["exif_ulog"],
            mount_rpy_deg=p["exif_mount_rpy_deg"],
            ulog_tolerance_s=float(p["exif_ulog_tolerance_s"]),
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
