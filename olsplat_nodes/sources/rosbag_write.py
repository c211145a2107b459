"""Write frames to a ROS 2 bag (rosbag2, metadata version 8) with ``rosbags``, for ROS tools.

The bag is a folder ``OUT/`` holding ``metadata.yaml`` and ``OUT.mcap`` (storage ``mcap``) or
``OUT.db3`` (storage ``sqlite3``). Every message is CDR with the ROS 2 Humble definitions (the
same as Jazzy's for these types), and its log time is its header stamp:

| topic                      | type                          | per frame                                   |
|----------------------------|-------------------------------|---------------------------------------------|
| /camera/image/compressed   | sensor_msgs/msg/CompressedImage | the JPEG bytes, format "jpeg"             |
| /camera/camera_info        | sensor_msgs/msg/CameraInfo    | size, K, D, R = I, P = [K or 0]             |
| /tf                        | tf2_msgs/msg/TFMessage        | map -> camera_link at the frame's stamp     |
| /tf_static (once, latched) | tf2_msgs/msg/TFMessage        | camera_link -> camera_optical_frame         |

Images and camera_info carry ``header.frame_id = camera_optical_frame`` (REP-103 optical axes:
x right, y down, z forward, the OpenCV axes of ``scene.Camera``); ``camera_link`` is FLU (x
forward, y left, z up). So ``map -> camera_optical_frame`` (the chain /tf then /tf_static) is the
frame's ``world_from_camera``. The frame names go to the bag's ``custom_data`` under
``olsplat.frame_names`` (a JSON list in write order), which ROS tools keep and ignore.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Iterable
from functools import cache
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import OlsplatInputError
from ..scene import Camera
from ..scene.camera import k_to_opencv
from ..scene.rotations import rotmat_to_quat
from ..telemetry.tf import LINK_FROM_OPTICAL
from .base import SourceFrame
from .replay_log import encode_jpeg

__all__ = [
    "CAMERA_LINK",
    "FRAME_NAMES_KEY",
    "LINK_FROM_OPTICAL",
    "OPTICAL_FRAME",
    "TOPICS",
    "WORLD_FRAME",
    "write_rosbag2",
]

WORLD_FRAME, CAMERA_LINK, OPTICAL_FRAME = "map", "camera_link", "camera_optical_frame"
FRAME_NAMES_KEY = "olsplat.frame_names"  # custom_data key: JSON list of the frame names, in write order
TOPICS = {
    "/camera/image/compressed": "sensor_msgs/msg/CompressedImage",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
}
# camera_link (FLU) from camera_optical_frame (telemetry/tf.py, REP-103): a rotation, inverted by its transpose
_OPTICAL_FROM_LINK = LINK_FROM_OPTICAL.T
_MAX_STAMP_NS = 2**31 * 1_000_000_000  # builtin_interfaces/Time.sec is an int32


@cache
def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _qos(depth: int, latched: bool):
    """KEEP_LAST ``depth``, RELIABLE; TRANSIENT_LOCAL when ``latched`` (a late subscriber of
    ``ros2 bag play`` still gets /tf_static), else VOLATILE; no deadline, lifespan or lease."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    durability = QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE
    history, reliable, automatic = QosHistory.KEEP_LAST, QosReliability.RELIABLE, QosLiveliness.AUTOMATIC
    return Qos(history, depth, reliable, durability, zero, zero, automatic, zero, False)


def _header(stamp_ns: int, frame_id: str) -> Any:
    t = _typestore().types
    stamp = t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def _transform(header, child: str, parent_from_child: np.ndarray) -> Any:
    """A TransformStamped: ``parent_from_child`` [4, 4] as a translation and an xyzw quaternion."""
    t = _typestore().types
    w, x, y, z = rotmat_to_quat(parent_from_child[:3, :3]).tolist()
    tx, ty, tz = parent_from_child[:3, 3].tolist()
    return t["geometry_msgs/msg/TransformStamped"](
        header=header,
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
            rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )


def _distortion(camera: Camera) -> tuple[str, np.ndarray]:
    """(distortion_model, D): up to 5 OpenCV coefficients zero-padded to 5 as plumb_bob; more as
    rational_polynomial (6 or 7 padded to 8; 12 or 14 kept whole, as OpenCV takes them)."""
    dist = np.asarray(camera.dist, np.float64)
    if len(dist) <= 5:
        return "plumb_bob", np.r_[dist, np.zeros(5 - len(dist))]
    return "rational_polynomial", np.r_[dist, np.zeros(max(0, 8 - len(dist)))]


def _cdr(message) -> memoryview:
    return _typestore().serialize_cdr(message, message.__msgtype__)


def _frame_messages(frame: SourceFrame, jpeg: bytes, stamp_ns: int) -> dict[str, Any]:
    """The /tf, /camera/camera_info and /camera/image/compressed messages of one frame."""
    t = _typestore().types
    camera = frame.camera
    header = _header(stamp_ns, OPTICAL_FRAME)
    model, dist = _distortion(camera)
    k_ros = k_to_opencv(camera.K)  # CameraInfo's pixel centres are at integers, ours at +0.5
    info = t["sensor_msgs/msg/CameraInfo"](
        header=header,
        height=camera.height,
        width=camera.width,
        distortion_model=model,
        d=dist,
        k=k_ros.reshape(-1).copy(),
        r=np.eye(3).reshape(-1),
        p=np.c_[k_ros, np.zeros(3)].reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    # map_from_link = world_from_optical @ optical_from_link, so that /tf then /tf_static give world_from_camera
    map_from_link = camera.world_from_camera @ _OPTICAL_FROM_LINK
    pose = _transform(_header(stamp_ns, WORLD_FRAME), CAMERA_LINK, map_from_link)
    tf = t["tf2_msgs/msg/TFMessage"](transforms=[pose])
    image = t["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=np.frombuffer(jpeg, np.uint8))
    return {"/tf": tf, "/camera/camera_info": info, "/camera/image/compressed": image}


def write_rosbag2(
    path: str | Path,
    frames: Iterable[SourceFrame],
    storage: Literal["mcap", "sqlite3"] = "mcap",
    jpeg_quality: int = 92,
) -> int:
    """Write the frames to a new rosbag2 folder ``path``; returns how many. Atomic.

    A frame's ``jpeg`` bytes go in as they are; a frame without them is encoded once at
    ``jpeg_quality``. Stamps (ns since the Unix epoch, as header stamps and log times), names
    (``custom_data``), intrinsics and poses are kept; ``seq`` is not. The bag is written into a
    hidden folder beside ``path`` (``.NAME.*.partial``) and renamed to ``path`` once closed, so
    ``path`` is either absent or whole; on an error the partial folder is removed. An existing
    ``path`` raises ``OlsplatInputError``; a stamp outside the int32 seconds of ROS time raises
    ``ValueError`` naming the frame.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
    if storage not in plugins:
        raise OlsplatInputError(f"rosbag2 storage must be 'mcap' or 'sqlite3', got {storage!r}")
    if path.exists() or path.is_symlink():
        raise OlsplatInputError(f"{path}: already exists; a rosbag2 bag is written to a new folder")
    typestore = _typestore()
    partial = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    inner = partial / path.name  # the storage file is named after the folder: OUT/OUT.mcap
    names: list[str] = []
    try:
        with Writer(inner, version=8, storage_plugin=plugins[storage]) as writer:
            stream, latched = [_qos(10, False)], [_qos(1, True)]
            connections = {
                topic: writer.add_connection(
                    topic,
                    msgtype,
                    typestore=typestore,
                    offered_qos_profiles=latched if topic == "/tf_static" else stream,
                )
                for topic, msgtype in TOPICS.items()
            }
            for frame in frames:
                stamp_ns = int(frame.stamp_ns)
                if not 0 <= stamp_ns < _MAX_STAMP_NS:
                    raise ValueError(f"frame {frame.name!r}: stamp {stamp_ns} ns is outside ROS time (int32 seconds)")
                if not names:  # the static mount once, at the first frame's stamp
                    mount = _transform(_header(stamp_ns, CAMERA_LINK), OPTICAL_FRAME, LINK_FROM_OPTICAL)
                    static = typestore.types["tf2_msgs/msg/TFMessage"](transforms=[mount])
                    writer.write(connections["/tf_static"], stamp_ns, _cdr(static))
                names.append(frame.name)
                jpeg = frame.jpeg if frame.jpeg is not None else encode_jpeg(frame.image, jpeg_quality)
                # the pose and calibration before the image: a player delivers them first
                for topic, message in _frame_messages(frame, jpeg, stamp_ns).items():
                    writer.write(connections[topic], stamp_ns, _cdr(message))
            writer.set_custom_data(FRAME_NAMES_KEY, json.dumps(names))
        inner.rename(path)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return len(names)
