"""ROS 2 bags (rosbag2: MCAP or sqlite3 storage) as a camera source, read with ``rosbags`` (no ROS).

``read_replay`` hands a bag here, so every replay source reads bags: a rosbag2 folder
(``metadata.yaml`` inside), its ``.mcap`` (MCAP header profile ``ros2``; olsplat's own replay
logs have profile ``""``) or its ``.db3``. ``read_bag(path, params)`` yields ``SourceFrame``s
exactly like the replay log reader; ``bag_summary(path)`` is what ``olsplat bag info`` prints.

Topics (chosen by type; ``BagParams`` names them when there are several candidates):
- images: ``sensor_msgs/msg/CompressedImage`` or ``sensor_msgs/msg/Image`` (``ros_image.py``);
- intrinsics: ``sensor_msgs/msg/CameraInfo``, the one with the image's header stamp, else the
  latest logged before the image, else the bag's first; undistorted when D is not zero
  (``undistort.py``) unless ``undistort`` is off;
- pose: a tf chain ``world_frame`` -> the image's ``header.frame_id`` through ``/tf`` and
  ``/tf_static`` (``telemetry/tf.py``), the optical frame being OpenCV's camera axes
  (REP-103), or an Odometry / PoseStamped topic and a camera mount (the static tf from the body
  frame, else ``mount``).
Times are header stamps (ns since the Unix epoch); the log time stands in for a zero stamp.
Frames without a pose within ``tolerance_s`` are dropped, counted by reason and reported in
one WARN line (``on_warning``); a bag where no frame has a pose is an error. Frame names come
from the bag's custom data ``olsplat.frame_names`` (a JSON list, ``rosbag_write.py`` writes
it), else ``frame_{i:04d}.jpg``, ``i`` the image's index on its topic (also the frame's ``seq``).

Every problem is one ``SceneFormatError`` naming the path and, where it is one, the topic and
the message's index on it: ``BAG: /camera/camera_info message 0: K is all zero (...)``.
"""

from __future__ import annotations

import json
import logging
import weakref
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import SceneFormatError
from ..scene import Camera
from ..scene.camera import k_from_opencv
from ..telemetry.tf import LINK_FROM_OPTICAL, TfBuffer, TfError, TfTimeError, TfTreeError, quat_from_ros
from .base import SourceFrame

log = logging.getLogger(__name__)

__all__ = [
    "BagParams",
    "Selection",
    "add_tf_message",
    "check_bag_path",
    "close_bag",
    "frame_names",
    "is_rosbag2",
    "open_bag",
    "read_bag",
    "select_topics",
    "topic_role",
    "topic_roles",
]

IMAGE_TYPES = ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = {
    "nav_msgs/msg/Odometry": "odometry",
    "geometry_msgs/msg/PoseStamped": "pose",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "pose",
}
FRAME_NAMES_KEY = "olsplat.frame_names"


@dataclass(frozen=True)
class BagParams:
    """How to read a bag: the ``bag_*`` source parameters without their prefix (sources/README.md)."""

    image_topic: str = ""  # "" = the only image topic
    camera_info_topic: str = ""  # "" = the only CameraInfo topic (or the one beside the image topic)
    pose_topic: str = ""  # Odometry/PoseStamped topic; "" = tf (the only pose topic when there is no dynamic /tf)
    world_frame: str = "map"  # tf: the world frame (ENU, REP-105)
    camera_frame: str = ""  # "" = the image's header.frame_id
    body_frame: str = ""  # pose topic: the frame its poses are of; "" = Odometry child_frame_id
    mount: tuple[float, ...] = ()  # pose topic: 16 numbers, row-major body_from_camera (OpenCV camera axes)
    camera_axes: Literal["optical", "link"] = "optical"  # the camera frame's axes: optical (OpenCV) or link (FLU)
    tolerance_s: float = 0.1  # a pose needs samples this close before and after the frame
    undistort: bool = True  # remap distorted frames to the pinhole image of K; false keeps D in the Camera

    @classmethod
    def from_params(cls, params: Mapping[str, Any] | None) -> BagParams:
        """From flat source params: the ``bag_*`` entries (others ignored)."""
        names = {f.name for f in fields(cls)}
        values = {k[4:]: v for k, v in (params or {}).items() if k.startswith("bag_") and k[4:] in names}
        values["mount"] = tuple(values.get("mount") or ())
        return cls(**values)


def _mcap_profile(path: Path) -> str | None:
    """The MCAP header's profile, or None when the file does not start like an MCAP file."""
    from mcap.records import Header
    from mcap.stream_reader import StreamReader

    try:
        with open(path, "rb") as stream:
            first = next(iter(StreamReader(stream).records))
    except Exception:  # not MCAP at all: the caller says what was expected
        return None
    return first.profile if isinstance(first, Header) else None


def is_rosbag2(path: str | Path) -> bool:
    """A rosbag2 folder (``metadata.yaml`` inside), a ``.db3`` file, or a ``.mcap`` with profile ``ros2``."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if path.suffix == ".db3":
        return path.is_file()
    return path.suffix == ".mcap" and path.is_file() and _mcap_profile(path) == "ros2"


def check_bag_path(path: Path) -> None:
    """One line for a path that is not a bag rosbags can open."""
    if not path.exists():
        raise SceneFormatError(path, "does not exist")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise SceneFormatError(path, "not a ROS 2 bag: a rosbag2 folder has a metadata.yaml")
    if path.is_file() and path.suffix not in (".mcap", ".db3"):
        raise SceneFormatError(path, "not a ROS 2 bag: expected a rosbag2 folder (metadata.yaml), a .mcap or a .db3")
    if path.is_file() and path.suffix == ".mcap":
        profile = _mcap_profile(path)
        if profile is None:
            raise SceneFormatError(path, "not an MCAP file (no MCAP header)")
        if profile == "":
            raise SceneFormatError(path, "an olsplat replay log (MCAP profile ''), not a ROS 2 bag: replay it as it is")
        if profile != "ros2":
            raise SceneFormatError(path, f"an MCAP file with profile {profile!r}, not a ROS 2 bag (profile 'ros2')")


def open_bag(path: Path):
    """An open ``rosbags`` AnyReader; messages without definitions in the bag (Humble's .db3)
    are read with Humble's types (identical up to Jazzy for the messages used here)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    check_bag_path(path)
    humble = get_typestore(Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=humble)
        reader.open()
    except Exception as exc:  # rosbags' reader, apsw, YAML, a cut file: all mean "unreadable bag"
        cut = " (a .mcap needs its footer: a recording that did not finish?)" if "end magic" in str(exc) else ""
        raise SceneFormatError(path, f"cannot open the bag ({type(exc).__name__}: {exc}){cut}") from None
    if any(c.msgtype not in reader.typestore.fielddefs for c in reader.connections):  # some types undefined
        reader.typestore.register({k: v for k, v in humble.fielddefs.items() if k not in reader.typestore.fielddefs})
    return reader


def _custom_data(path: Path) -> dict:
    """The bag's ``custom_data`` (rosbag2 metadata version 6+): from the folder's metadata.yaml,
    else the copy inside a lone .mcap (metadata record ``rosbag2``) or .db3 (table ``metadata``)."""
    import yaml

    folder = path if path.is_dir() else path.parent
    texts = []
    if (folder / "metadata.yaml").is_file():
        texts.append((folder / "metadata.yaml").read_text())
    if path.suffix == ".mcap":
        from mcap.reader import make_reader

        try:
            with open(path, "rb") as stream:
                texts += [r.metadata.get("serialized_metadata", "") for r in make_reader(stream).iter_metadata()]
        except Exception:  # no summary: the metadata.yaml (if any) is all there is
            pass
    elif path.suffix == ".db3":
        import sqlite3

        try:
            with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
                texts += [row[0] for row in db.execute("SELECT metadata FROM metadata ORDER BY metadata_version")]
        except sqlite3.Error:  # Humble's .db3 has no metadata table
            pass
    for text in texts:
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError:
            continue
        data = data.get("rosbag2_bagfile_information", data) if isinstance(data, dict) else {}
        if isinstance(data, dict) and isinstance(data.get("custom_data"), dict):
            return data["custom_data"]
    return {}


def frame_names(path: Path) -> list[str]:
    text = _custom_data(path).get(FRAME_NAMES_KEY)
    if text is None:
        return []
    try:
        names = json.loads(text)
    except (TypeError, ValueError):
        names = None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise SceneFormatError(path, f"custom data {FRAME_NAMES_KEY} is not a JSON list of names")
    return names


def topic_role(topic: str, msgtype: str, transient_local: bool = False) -> str:
    """image, camera_info, tf, tf_static, odometry, pose, or "" (not used here)."""
    if msgtype in IMAGE_TYPES:
        return "image"
    if msgtype == INFO_TYPE:
        return "camera_info"
    if msgtype == TF_TYPE:
        return "tf_static" if topic.endswith("tf_static") or transient_local else "tf"
    return POSE_TYPES.get(msgtype, "")


def topic_roles(reader) -> dict[str, tuple[str, str]]:
    """topic -> (msgtype, role)."""
    roles = {}
    for c in reader.connections:
        latched = any(q.durability.name == "TRANSIENT_LOCAL" for q in getattr(c.ext, "offered_qos_profiles", []))
        roles[c.topic] = (c.msgtype, topic_role(c.topic, c.msgtype, latched))
    return roles


@dataclass(frozen=True)
class Selection:
    """The topics a bag is read from."""

    image: str
    camera_info: str
    pose: str  # "" = tf
    tf: tuple[str, ...]  # dynamic tf topics
    tf_static: tuple[str, ...]


def _pick(path: Path, roles, wanted: tuple[str, ...], chosen: str, param: str, near: str = "") -> str:
    """The topic named by ``param`` (checked), or the only candidate, or the one beside ``near``."""
    candidates = sorted(t for t, (_, role) in roles.items() if role in wanted)
    what = " or ".join(wanted)
    if chosen:
        if chosen not in roles:
            raise SceneFormatError(path, f"{param}: no topic {chosen!r} in the bag; {what} topics: {candidates}")
        if roles[chosen][1] not in wanted:
            raise SceneFormatError(path, f"{param}: {chosen} is {roles[chosen][0]}; {what} topics: {candidates}")
        return chosen
    if len(candidates) > 1 and near:  # a camera's CameraInfo sits in its namespace: /cam/image_raw -> /cam/camera_info
        beside = [t for t in candidates if near.startswith(t.rsplit("/", 1)[0] + "/")]
        longest = max((len(t.rsplit("/", 1)[0]) for t in beside), default=-1)
        beside = [t for t in beside if len(t.rsplit("/", 1)[0]) == longest]
        candidates = beside if len(beside) == 1 else candidates
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise SceneFormatError(path, f"no {what} topic (topics: {', '.join(sorted(roles)) or 'none'})")
    raise SceneFormatError(path, f"several {what} topics: {', '.join(candidates)}; choose one with {param}=TOPIC")


def select_topics(path: Path, roles: dict[str, tuple[str, str]], params: BagParams) -> Selection:
    """Which topics to read (rules in ``BagParams``); one line when a choice is missing or wrong."""
    image = _pick(path, roles, ("image",), params.image_topic, "bag_image_topic")
    info = _pick(path, roles, ("camera_info",), params.camera_info_topic, "bag_camera_info_topic", near=image)
    tf = tuple(sorted(t for t, (_, role) in roles.items() if role == "tf"))
    static = tuple(sorted(t for t, (_, role) in roles.items() if role == "tf_static"))
    pose = ""
    moving = [t for t, (_, role) in roles.items() if role in ("odometry", "pose")]
    if params.pose_topic or (not tf and (moving or not static)):  # /tf_static alone cannot move a camera
        try:
            pose = _pick(path, roles, ("odometry", "pose"), params.pose_topic, "bag_pose_topic")
        except SceneFormatError as exc:
            if params.pose_topic:
                raise
            raise SceneFormatError(path, f"no pose: no /tf and {exc.problem}") from None
    return Selection(image, info, pose, tf, static)


def _stamp_ns(header, log_ns: int) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec) or int(log_ns)


class _Messages:
    """Deserialised messages of some topics in log order, with their index on their topic;
    a message that does not deserialise is one line naming its topic and index."""

    def __init__(self, path: Path, reader, topics) -> None:
        self.path, self.reader = path, reader
        self.connections = [c for c in reader.connections if c.topic in set(topics)]
        self.counts: dict[str, int] = {}

    def __iter__(self) -> Iterator[tuple[str, int, int, Any]]:
        """(topic, index on the topic, log time ns, message)."""
        try:
            stream = self.reader.messages(connections=self.connections) if self.connections else ()  # [] = all
            for connection, log_ns, raw in stream:
                index = self.counts.get(connection.topic, 0)
                self.counts[connection.topic] = index + 1
                try:
                    message = self.reader.deserialize(raw, connection.msgtype)
                except Exception as exc:
                    raise SceneFormatError(
                        self.path,
                        f"{connection.topic} message {index}: does not deserialise as {connection.msgtype} ({exc})",
                    ) from None
                yield connection.topic, index, log_ns, message
        except SceneFormatError:
            raise
        except Exception as exc:  # the storage itself (a bad chunk, a damaged database)
            after = ", ".join(f"{t} message {n}" for t, n in self.counts.items()) or "the first message"
            raise SceneFormatError(self.path, f"unreadable after {after} ({type(exc).__name__}: {exc})") from None

    def error(self, topic: str, index: int, problem: str) -> SceneFormatError:
        return SceneFormatError(self.path, f"{topic} message {index}: {problem}")


def add_tf_message(tf: TfBuffer, message, static: bool, log_ns: int) -> None:
    for t in message.transforms:
        r, v = t.transform.rotation, t.transform.translation
        q = quat_from_ros(r.x, r.y, r.z, r.w)
        parent, child = t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/")  # tf2 drops a leading slash
        if static:
            tf.add_static(parent, child, [v.x, v.y, v.z], q)
        else:
            tf.add(parent, child, _stamp_ns(t.header, log_ns), [v.x, v.y, v.z], q)


def _read_poses(messages: _Messages, selection: Selection):
    """Pass 1: the tf tree, the pose topic's track (as a one-edge TfBuffer) and every CameraInfo."""
    tf, track = TfBuffer(), TfBuffer()
    infos: list[tuple[int, int, int, Any]] = []  # (log ns, header stamp ns, index, message)
    track_frames = ("", "")  # (world, body) of the pose topic
    for topic, index, log_ns, message in messages:
        try:
            if topic in selection.tf or topic in selection.tf_static:
                add_tf_message(tf, message, topic in selection.tf_static, log_ns)
            elif topic == selection.camera_info:
                infos.append((log_ns, _stamp_ns(message.header, log_ns), index, message))
            elif topic == selection.pose:
                pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
                p, r = pose.position, pose.orientation
                if not track_frames[0]:
                    track_frames = (
                        message.header.frame_id or "world",
                        getattr(message, "child_frame_id", "") or "body",
                    )
                track.add(
                    *track_frames, _stamp_ns(message.header, log_ns), [p.x, p.y, p.z], quat_from_ros(r.x, r.y, r.z, r.w)
                )
        except TfError as exc:
            raise messages.error(topic, index, str(exc)) from None
    return tf, track, track_frames, infos


def _is_rectified(topic: str) -> bool:
    """An ``image_rect*`` topic carries undistorted images (image_proc): K is P's, D is none."""
    return any(part.startswith("image_rect") for part in topic.split("/"))


class _CameraPoses:
    """world_from_camera [4, 4] of an image frame at a stamp: tf chain, or pose track + mount."""

    def __init__(
        self,
        path: Path,
        params: BagParams,
        selection: Selection,
        tf: TfBuffer,
        track: TfBuffer,
        track_frames: tuple[str, str],
    ):
        self.path, self.params, self.selection = path, params, selection
        self.tf, self.track, self.track_frames = tf, track, track_frames
        self.tolerance_ns = int(round(params.tolerance_s * 1e9))
        self.mount = None
        if params.mount:
            mount = np.asarray(params.mount, np.float64)
            if mount.size != 16 or not np.allclose(
                mount.reshape(4, 4)[:3, :3] @ mount.reshape(4, 4)[:3, :3].T, np.eye(3), atol=1e-4
            ):
                raise SceneFormatError(
                    path, f"bag_mount must be 16 numbers of a rigid transform (row-major), got {list(params.mount)}"
                )
            self.mount = mount.reshape(4, 4)
        self.checked: set[str] = set()

    def check(self, frame_id: str) -> None:
        """The chain for this camera frame exists (once per frame name); one line when not."""
        if frame_id in self.checked:
            return
        p, s = self.params, self.selection
        try:
            if not s.pose:
                self.tf.check_chain(p.world_frame, frame_id)
            elif self.mount is None:
                body = p.body_frame or self.track_frames[1]
                if body == "body":
                    raise TfTreeError(f"{s.pose} names no body frame: set bag_body_frame or bag_mount")
                self.tf.check_chain(body, frame_id)
        except TfTreeError as exc:
            hint = (
                f" (bag_world_frame={p.world_frame!r})"
                if not s.pose
                else f" (the camera mount for {s.pose}: set bag_mount)"
            )
            raise SceneFormatError(self.path, f"{s.image}: {exc}{hint}") from None
        if p.camera_axes == "optical" and "optical" not in frame_id and self.mount is None:
            log.warning(
                "%s: camera frame %r is taken as an optical frame (x right, y down, z forward); "
                "set bag_camera_axes=link for a FLU camera_link",
                self.path,
                frame_id,
            )
        self.checked.add(frame_id)

    def __call__(self, frame_id: str, stamp_ns: int) -> np.ndarray:
        """Raises ``TfTimeError`` when a sample is missing around the stamp."""
        p, s, tol = self.params, self.selection, self.tolerance_ns
        if not s.pose:
            pose = self.tf.lookup(p.world_frame, frame_id, stamp_ns, tol)
        else:
            world, body = self.track_frames
            pose = self.track.lookup(world, body, stamp_ns, tol)
            if self.mount is not None:
                return pose @ self.mount
            pose = pose @ self.tf.lookup(p.body_frame or self.track_frames[1], frame_id, stamp_ns, tol)
        return pose @ LINK_FROM_OPTICAL if p.camera_axes == "link" else pose


class _CameraInfos:
    """The CameraInfo for an image: the same header stamp, else the latest logged at or before
    the image, else the first; each turned into ``Intrinsics`` once (refusals name the message)."""

    def __init__(self, messages: _Messages, topic: str, infos, rectified: bool) -> None:
        if not infos:
            raise SceneFormatError(messages.path, f"{topic}: no CameraInfo message in the bag")
        self.messages, self.topic, self.rectified = messages, topic, rectified
        self.infos = sorted(infos, key=lambda item: item[0])
        self.log_ns = np.array([item[0] for item in self.infos], np.int64)
        self.by_stamp = {item[1]: n for n, item in enumerate(self.infos)}
        self.cache: dict[int, Any] = {}

    def __call__(self, stamp_ns: int, log_ns: int):
        from .ros_image import camera_intrinsics

        n = self.by_stamp.get(stamp_ns)
        if n is None:
            n = max(int(np.searchsorted(self.log_ns, log_ns, side="right")) - 1, 0)
        if n not in self.cache:
            _, _, index, message = self.infos[n]
            try:
                self.cache[n] = (index, camera_intrinsics(message, self.rectified))
            except ValueError as exc:
                raise self.messages.error(self.topic, index, str(exc)) from None
        return self.cache[n]


def read_bag(
    path: str | Path,
    params: BagParams | Mapping[str, Any] | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> Iterator[SourceFrame]:
    """The frames of a ROS 2 bag, in log order (rules in the module docstring).

    Checked at once (before the first frame): the path is a bag rosbags opens, the topics can
    be chosen. Then, while iterating: the tf tree and poses (pass 1), images with intrinsics
    and poses (pass 2). ``params``: ``BagParams``, or flat source params (their ``bag_*``).
    The WARN line on dropped frames is logged and given to ``on_warning``.
    """
    path = Path(path)
    if path.name == "metadata.yaml":
        path = path.parent
    params = params if isinstance(params, BagParams) else BagParams.from_params(params)
    if not params.tolerance_s > 0:
        raise SceneFormatError(path, f"bag_tolerance_s must be positive, got {params.tolerance_s}")
    reader = open_bag(path)  # kept open for the frames (rosbags parses every topic's QoS YAML on opening)
    try:
        selection = select_topics(path, topic_roles(reader), params)
        names = frame_names(path)
    except BaseException:
        close_bag(reader)
        raise
    frames = _read_frames(path, reader, params, selection, names, on_warning)
    weakref.finalize(frames, close_bag, reader)  # closed also when the frames are dropped before the end
    return frames


def close_bag(reader) -> None:
    """Close an ``open_bag`` reader (again: nothing)."""
    if reader.stack is not None:
        reader.close()


def _read_frames(
    path: Path, reader, params: BagParams, selection: Selection, names: list[str], on_warning
) -> Iterator[SourceFrame]:
    from .ros_image import decode_image_message
    from .undistort import undistort_image

    try:
        first = _Messages(path, reader, [*selection.tf, *selection.tf_static, selection.camera_info, selection.pose])
        tf, track, track_frames, infos = _read_poses(first, selection)
        images = _Messages(path, reader, [selection.image])
        cameras = _CameraInfos(images, selection.camera_info, infos, _is_rectified(selection.image))
        poses = _CameraPoses(path, params, selection, tf, track, track_frames)
        dropped: dict[str, int] = {}
        yielded, zero_stamps = 0, 0
        for topic, index, log_ns, message in images:
            stamp_ns = _stamp_ns(message.header, log_ns)
            if not (message.header.stamp.sec or message.header.stamp.nanosec):
                zero_stamps += 1
                if zero_stamps == 1:  # a driver that leaves stamps unset: said once
                    log.warning("%s: %s message %d has a zero header stamp: its log time is used", path, topic, index)
            frame_id = (params.camera_frame or message.header.frame_id).lstrip("/")
            if not frame_id:
                raise images.error(topic, index, "the image has no header.frame_id: set bag_camera_frame")
            poses.check(frame_id)
            try:
                pose = poses(frame_id, stamp_ns)
            except TfTimeError as exc:
                dropped[str(exc)] = dropped.get(str(exc), 0) + 1
                continue
            try:
                image, jpeg = decode_image_message(message)
            except ValueError as exc:
                raise images.error(topic, index, str(exc)) from None
            info_index, intrinsics = cameras(stamp_ns, log_ns)
            if image.shape[:2] != (intrinsics.height, intrinsics.width):
                raise images.error(
                    topic,
                    index,
                    f"the image is {image.shape[1]}x{image.shape[0]} but "
                    f"{selection.camera_info} message {info_index} says {intrinsics.width}x{intrinsics.height}",
                )
            dist, model = intrinsics.dist, intrinsics.model
            if dist.size and params.undistort:
                image = undistort_image(image, intrinsics.K, dist, intrinsics.fisheye)
                jpeg, dist, model = None, np.zeros(0), "PINHOLE"  # new pixels: the bag's JPEG is not theirs
            elif dist.size and intrinsics.fisheye:
                raise images.error(
                    selection.camera_info,
                    info_index,
                    "equidistant (fisheye) distortion cannot be kept in "
                    "a Camera (OpenCV pinhole coefficients): leave bag_undistort on",
                )
            name = names[index] if index < len(names) else f"frame_{index:04d}.jpg"
            K = k_from_opencv(intrinsics.K)  # undistortion above ran with the bag's own K
            camera = Camera(name, intrinsics.width, intrinsics.height, K, pose, dist, model)
            yielded += 1
            yield SourceFrame(index, stamp_ns, name, image, camera, jpeg)
    finally:
        close_bag(reader)
    total = yielded + sum(dropped.values())
    reasons = ", ".join(f"{count} {reason}" for reason, count in sorted(dropped.items(), key=lambda kv: -kv[1]))
    if not total:
        raise SceneFormatError(path, f"{selection.image}: no image message")
    if not yielded:
        raise SceneFormatError(
            path,
            f"{selection.image}: none of the {total} frames has a pose within "
            f"bag_tolerance_s={params.tolerance_s} ({reasons})",
        )
    if dropped:
        message = (
            f"{path}: {total - yielded} of {total} frames on {selection.image} had no pose and were dropped ({reasons})"
        )
        log.warning(message)
        if on_warning is not None:
            on_warning(message)
