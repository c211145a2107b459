"""ROS 2 bags written in the tests with rosbags' own ``Writer`` (not olsplat's writer), and the
messages that go in them (every field given: rosbags' message classes have no defaults)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from olsplat_nodes.scene.rotations import rotmat_to_quat

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
T = HUMBLE.types
S = 1_000_000_000
T0 = 1_700_000_000 * S  # a plausible epoch stamp
_Z = QosTime(0, 0)
LATCHED = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, _Z, _Z,
              QosLiveliness.AUTOMATIC, _Z, False)  # fmt: skip
STREAM = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE, _Z, _Z,
             QosLiveliness.AUTOMATIC, _Z, False)  # fmt: skip
TYPES = {
    "image": "sensor_msgs/msg/Image",
    "compressed": "sensor_msgs/msg/CompressedImage",
    "info": "sensor_msgs/msg/CameraInfo",
    "tf": "tf2_msgs/msg/TFMessage",
    "odometry": "nav_msgs/msg/Odometry",
    "pose": "geometry_msgs/msg/PoseStamped",
}
K_DEFAULT = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])


def header(stamp_ns: int, frame_id: str):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // S, nanosec=stamp_ns % S), frame_id=frame_id
    )


def compressed(stamp_ns: int, data: bytes, fmt: str = "jpeg", frame_id: str = "camera_optical_frame"):
    return T["sensor_msgs/msg/CompressedImage"](
        header=header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(data, np.uint8)
    )


def raw_image(stamp_ns, encoding, pixels, *, step=None, bigendian=False, frame_id="camera_optical_frame"):
    """pixels [H, W(, C)] uint8/uint16 in the encoding's channel order; rows padded to ``step`` bytes."""
    height, width = pixels.shape[:2]
    dtype = np.dtype(">u2" if bigendian else "<u2") if pixels.dtype == np.uint16 else np.dtype(np.uint8)
    rows = np.ascontiguousarray(pixels.astype(dtype)).reshape(height, -1).view(np.uint8)
    step = step or rows.shape[1]
    data = np.zeros((height, step), np.uint8)
    data[:, : rows.shape[1]] = rows
    data[:, rows.shape[1] :] = 0xAB  # padding that must not show
    return T["sensor_msgs/msg/Image"](
        header=header(stamp_ns, frame_id), height=height, width=width, encoding=encoding,
        is_bigendian=int(bigendian), step=step, data=data.reshape(-1),
    )  # fmt: skip


def camera_info(stamp_ns, width, height, K=K_DEFAULT, D=(), model="plumb_bob", frame_id="camera_optical_frame",
                binning=(0, 0), roi=(0, 0, 0, 0)):  # fmt: skip
    K = np.asarray(K, np.float64)
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(stamp_ns, frame_id), height=height, width=width, distortion_model=model,
        d=np.asarray(D, np.float64), k=K.reshape(-1), r=np.eye(3).reshape(-1),
        p=np.c_[K, np.zeros(3)].reshape(-1), binning_x=binning[0], binning_y=binning[1],
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3],
                                                  do_rectify=False),
    )  # fmt: skip


def _pose_parts(matrix):
    w, x, y, z = rotmat_to_quat(np.asarray(matrix)[:3, :3])
    t = np.asarray(matrix)[:3, 3]
    return t, (x, y, z, w)


def transform(stamp_ns, parent, child, matrix):
    t, (x, y, z, w) = _pose_parts(matrix)
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(stamp_ns, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )  # fmt: skip


def tf_message(*transforms):
    return T["tf2_msgs/msg/TFMessage"](transforms=list(transforms))


def _pose(matrix):
    t, (x, y, z, w) = _pose_parts(matrix)
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def odometry(stamp_ns, matrix, frame_id="odom", child="base_link"):
    zero3 = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=header(stamp_ns, frame_id), child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(matrix), covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)),
    )  # fmt: skip


def pose_stamped(stamp_ns, matrix, frame_id="map"):
    return T["geometry_msgs/msg/PoseStamped"](header=header(stamp_ns, frame_id), pose=_pose(matrix))


def write_bag(out: Path, messages, *, storage="mcap", types=None, latched=("/tf_static",), custom=None) -> Path:
    """messages: [(topic, log_ns, message)] in write order; topic types from the messages
    (``types`` overrides, e.g. to declare a topic of another type). Returns the bag folder."""
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    with Writer(out, version=8, storage_plugin=plugin) as writer:
        connections = {}
        for topic, _, message in messages:
            if topic not in connections:
                msgtype = (types or {}).get(topic, message.__msgtype__)
                qos = LATCHED if topic in latched else STREAM
                connections[topic] = writer.add_connection(topic, msgtype, typestore=HUMBLE, offered_qos_profiles=[qos])
        for topic, log_ns, message in messages:
            writer.write(connections[topic], log_ns, HUMBLE.serialize_cdr(message, message.__msgtype__))
        for key, value in (custom or {}).items():
            writer.set_custom_data(key, value if isinstance(value, str) else json.dumps(value))
    return out


def jpeg_bytes(image_rgb, quality=95) -> bytes:
    ok, data = cv2.imencode(".jpg", image_rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return data.tobytes()


def png_bytes(image_rgb) -> bytes:
    ok, data = cv2.imencode(".png", image_rgb[..., ::-1])
    assert ok
    return data.tobytes()


def patches(height=60, width=80, seed=0) -> np.ndarray:
    """[H, W, 3] uint8 RGB of 10-pixel flat colour patches (survive demosaicing inside each patch)."""
    rng = np.random.default_rng(seed)
    colours = rng.integers(0, 256, (height // 10 + 1, width // 10 + 1, 3), dtype=np.uint8)
    return colours.repeat(10, 0).repeat(10, 1)[:height, :width].copy()


def rigid(yaw_rad=0.0, t=(0.0, 0.0, 0.0), pitch_rad=0.0) -> np.ndarray:
    """[4, 4] rotation about z by yaw, then about y by pitch, then translation t."""
    cz, sz, cy, sy = np.cos(yaw_rad), np.sin(yaw_rad), np.cos(pitch_rad), np.sin(pitch_rad)
    matrix = np.eye(4)
    matrix[:3, :3] = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    matrix[:3, 3] = t
    return matrix


LINK_FROM_OPTICAL = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def contract_messages(count=4, size=(80, 60), D=(), names=True):
    """The layout olsplat's bag writer produces: compressed JPEG images, CameraInfo, /tf
    map -> camera_link at each frame stamp, one /tf_static camera_link -> camera_optical_frame.
    Returns (messages, custom data, [(stamp_ns, world_from_camera, jpeg)])."""
    width, height = size
    messages = [("/tf_static", T0, tf_message(transform(T0, "camera_link", "camera_optical_frame", LINK_FROM_OPTICAL)))]
    expected = []
    for i in range(count):
        stamp = T0 + i * S // 2
        link = rigid(0.3 * i, (2.0 * i, -1.0 * i, 50.0 + i), pitch_rad=0.2)
        data = jpeg_bytes(patches(height, width, seed=i))
        messages += [
            ("/tf", stamp, tf_message(transform(stamp, "map", "camera_link", link))),
            ("/camera/camera_info", stamp, camera_info(stamp, width, height, D=D or [0.0] * 5)),
            ("/camera/image/compressed", stamp, compressed(stamp, data)),
        ]
        expected.append((stamp, link @ LINK_FROM_OPTICAL, data))
    custom = {"olsplat.frame_names": [f"shot_{i}.jpg" for i in range(count)]} if names else {}
    return messages, custom, expected
