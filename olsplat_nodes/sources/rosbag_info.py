"""What a ROS 2 bag holds and what the bag source would read from it (``olsplat bag info``).

``bag_summary(path, params)`` opens the bag (an unreadable one raises ``SceneFormatError``, one
line), lists its topics with their role for the source, deserialises the first message of each
image and CameraInfo topic (encoding, size, frame), builds the tf tree from every ``/tf_static``
message and the first ``tf_messages`` ``/tf`` messages, and says which topics and chain
``read_bag`` would use, or the one-line problem that stops it (``problem``). Reading every frame
is ``read_bag``'s job; this stays quick on a large bag.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import SceneFormatError
from ..telemetry.tf import TfBuffer, TfError
from .rosbag import (
    BagParams,
    Selection,
    add_tf_message,
    close_bag,
    frame_names,
    open_bag,
    select_topics,
    topic_roles,
)

__all__ = ["BagSummary", "TopicSummary", "bag_summary"]


@dataclass(frozen=True)
class TopicSummary:
    topic: str
    msgtype: str
    count: int  # messages
    role: str  # image, camera_info, tf, tf_static, odometry, pose, or "" (not read)
    first: str = ""  # images and CameraInfo: what the first message says (format, size, frame)


@dataclass
class BagSummary:
    path: Path
    storage: str  # mcap or sqlite3
    ros_distro: str  # as the bag's metadata says ("" when it does not)
    start_ns: int  # first log time, ns since the Unix epoch
    duration_ns: int
    message_count: int
    topics: list[TopicSummary]
    tf_tree: list[str]  # TfBuffer.tree_lines()
    tf_messages_read: int  # /tf messages in the tree (at most tf_messages)
    frame_names: int  # names in the custom data olsplat.frame_names
    selection: Selection | None = None  # what read_bag would read; None with a problem
    camera_frame: str = ""  # the image's frame (bag_camera_frame or the first image's header.frame_id)
    problem: str = ""  # why read_bag would stop, one line ("" = none seen)
    notes: list[str] = field(default_factory=list)


def _first(reader, connection) -> Any:
    for _, _, raw in reader.messages(connections=[connection]):
        return reader.deserialize(raw, connection.msgtype)
    return None


def _describe(message) -> str:
    if message is None:
        return ""
    frame = f"frame {message.header.frame_id or '(none)'}"
    kind = message.__msgtype__
    if kind.endswith("CompressedImage"):
        return f"{message.format or '(no format)'}, {len(message.data)} bytes, {frame}"
    if kind.endswith("/Image"):
        return f"{message.encoding} {message.width}x{message.height} step {message.step}, {frame}"
    return f"{message.distortion_model or '(no model)'} {message.width}x{message.height}, {frame}"


def bag_summary(
    path: str | Path, params: BagParams | Mapping[str, Any] | None = None, tf_messages: int = 500
) -> BagSummary:
    """The summary of a bag (module docstring); raises ``SceneFormatError`` when it cannot be opened."""
    from .ros_image import camera_intrinsics

    path = Path(path)
    path = path.parent if path.name == "metadata.yaml" else path
    params = params if isinstance(params, BagParams) else BagParams.from_params(params)
    reader = open_bag(path)
    try:
        roles = topic_roles(reader)
        firsts = {
            c.topic: _first(reader, c) for c in reader.connections if roles[c.topic][1] in ("image", "camera_info")
        }
        topics = [
            TopicSummary(topic, info.msgtype, info.msgcount, roles[topic][1], _describe(firsts.get(topic)))
            for topic, info in sorted(reader.topics.items())
        ]
        tf, read = TfBuffer(), 0
        tf_topics = {t: role for t, (_, role) in roles.items() if role in ("tf", "tf_static")}
        problem = ""
        connections = [c for c in reader.connections if c.topic in tf_topics]
        for connection, log_ns, raw in reader.messages(connections=connections) if connections else ():
            static = tf_topics[connection.topic] == "tf_static"
            if static or read < tf_messages:
                read += not static
                try:
                    add_tf_message(tf, reader.deserialize(raw, connection.msgtype), static, log_ns)
                except (TfError, ValueError) as exc:
                    problem = problem or f"{connection.topic}: {exc}"
        summary = BagSummary(
            path,
            "mcap" if path.suffix == ".mcap" or any(path.glob("*.mcap")) else "sqlite3",
            str(getattr(reader.readers[0], "ros_distro", "") or ""),
            int(reader.start_time) if reader.message_count else 0,
            int(reader.duration),
            int(reader.message_count),
            topics,
            tf.tree_lines(),
            read,
            len(frame_names(path)),
            problem=problem,
        )
        try:
            summary.selection = select_topics(path, roles, params)
        except SceneFormatError as exc:
            summary.problem = summary.problem or exc.problem
            return summary
        selection = summary.selection
        image, info = firsts.get(selection.image), firsts.get(selection.camera_info)
        summary.camera_frame = params.camera_frame or (image.header.frame_id if image is not None else "")
        if info is not None and not summary.problem:
            try:
                camera_intrinsics(info)
            except ValueError as exc:
                summary.problem = f"{selection.camera_info} message 0: {exc}"
        if not selection.pose and summary.camera_frame and not summary.problem:
            try:
                tf.check_chain(params.world_frame, summary.camera_frame)
            except TfError as exc:
                summary.problem = f"{selection.image}: {exc} (bag_world_frame={params.world_frame!r})"
        return summary
    finally:
        close_bag(reader)
