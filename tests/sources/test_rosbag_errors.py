"""Bad bags: each gets one line naming the path and, where one is at fault, the topic and message index."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.sources.replay_log import read_replay, write_mcap
from olsplat_nodes.sources.rosbag import read_bag

from .bags import (
    LINK_FROM_OPTICAL,
    T0,
    camera_info,
    compressed,
    contract_messages,
    jpeg_bytes,
    patches,
    rigid,
    tf_message,
    transform,
    write_bag,
)


def problem(path, params=None) -> str:
    """The one line read_bag raises for ``path``, without the path it starts with."""
    with pytest.raises(SceneFormatError) as caught:
        list(read_bag(path, params))
    message = str(caught.value)
    assert "\n" not in message and caught.value.path == str(path)
    return caught.value.problem


def replaced(messages, topic, message):
    """The messages with the first one on ``topic`` replaced (None: every one on it dropped)."""
    if message is None:
        return [m for m in messages if m[0] != topic]
    index = next(i for i, m in enumerate(messages) if m[0] == topic)
    return [*messages[:index], (topic, messages[index][1], message), *messages[index + 1 :]]


@pytest.fixture
def good():
    messages, custom, _ = contract_messages(count=3)
    return messages, custom


def test_paths_that_are_not_bags(tmp_path, good):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    assert problem(text) == "not a ROS 2 bag: expected a rosbag2 folder (metadata.yaml), a .mcap or a .db3"
    assert problem(tmp_path / "missing") == "does not exist"
    assert problem(tmp_path) == "not a ROS 2 bag: a rosbag2 folder has a metadata.yaml"
    log = tmp_path / "log.mcap"
    write_mcap(log, list(read_replay(write_bag(tmp_path / "b", good[0], custom=good[1]))))
    assert problem(log) == "an olsplat replay log (MCAP profile ''), not a ROS 2 bag: replay it as it is"
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(b"not mcap at all")
    assert problem(fake) == "not an MCAP file (no MCAP header)"


def test_a_cut_mcap(tmp_path, good):
    bag = write_bag(tmp_path / "cut", good[0], custom=good[1])
    inner = bag / "cut.mcap"
    inner.write_bytes(inner.read_bytes()[: inner.stat().st_size // 2])
    expected = (
        "cannot open the bag (AnyReaderError: File end magic is invalid.) "
        "(a .mcap needs its footer: a recording that did not finish?)"
    )
    assert problem(inner) == expected and problem(bag) == expected
    with pytest.raises(SceneFormatError) as caught:
        read_replay(inner)
    assert str(caught.value) == f"{inner}: {expected}"


def test_a_corrupt_message_is_named_by_topic_and_index(tmp_path, good):
    bag = write_bag(tmp_path / "corrupt", good[0], custom=good[1], storage="sqlite3")
    with sqlite3.connect(bag / "corrupt.db3") as db:
        (topic_id,) = db.execute("SELECT id FROM topics WHERE name = '/camera/image/compressed'").fetchone()
        ids = [
            row[0] for row in db.execute("SELECT id FROM messages WHERE topic_id = ? ORDER BY timestamp", (topic_id,))
        ]
        db.execute("UPDATE messages SET data = x'000100000500' WHERE id = ?", (ids[1],))
    assert problem(bag).startswith(
        "/camera/image/compressed message 1: does not deserialise as sensor_msgs/msg/CompressedImage ("
    )


def test_topic_choices(tmp_path, good):
    messages = good[0]
    bag = write_bag(tmp_path / "b", messages, custom=good[1])
    assert problem(bag, {"bag_image_topic": "/camera/camera_info"}) == (
        "bag_image_topic: /camera/camera_info is sensor_msgs/msg/CameraInfo; image topics: ['/camera/image/compressed']"
    )
    assert (
        problem(bag, {"bag_pose_topic": "/odom"})
        == "bag_pose_topic: no topic '/odom' in the bag; odometry or pose topics: []"
    )
    second = [("/camera2/image", T0, compressed(T0, jpeg_bytes(patches(60, 80))))]
    bag2 = write_bag(tmp_path / "two", messages + second)
    assert problem(bag2) == (
        "several image topics: /camera/image/compressed, /camera2/image; choose one with bag_image_topic=TOPIC"
    )
    assert problem(write_bag(tmp_path / "noinfo", replaced(messages, "/camera/camera_info", None))) == (
        "no camera_info topic (topics: /camera/image/compressed, /tf, /tf_static)"
    )
    bare = [m for m in messages if m[0].startswith("/camera")]
    assert problem(write_bag(tmp_path / "nopose", bare)) == (
        "no pose: no /tf and no odometry or pose topic (topics: /camera/camera_info, /camera/image/compressed)"
    )


def test_tf_chain_faults_list_the_known_frames(tmp_path, good):
    messages = good[0]
    unlinked = replaced(
        messages, "/tf_static", tf_message(transform(T0, "base", "camera_optical_frame", LINK_FROM_OPTICAL))
    )
    assert problem(write_bag(tmp_path / "split", unlinked)) == (
        "/camera/image/compressed: no tf chain from 'map' to 'camera_optical_frame': 'map' is under root 'map', "
        "'camera_optical_frame' under root 'base'; known frames: base, camera_link, camera_optical_frame, map "
        "(bag_world_frame='map')"
    )
    assert problem(write_bag(tmp_path / "world", messages), {"bag_world_frame": "odom"}) == (
        "/camera/image/compressed: no tf frame 'odom'; known frames: camera_link, camera_optical_frame, map "
        "(bag_world_frame='odom')"
    )
    two_parents = [*messages, ("/tf", T0, tf_message(transform(T0, "odom", "camera_link", rigid())))]
    assert problem(write_bag(tmp_path / "parents", two_parents)) == (
        "/tf message 1: frame 'camera_link' has two parents, 'map' and 'odom' (tf is a tree)"
    )


def test_no_posed_frame_at_all(tmp_path, good):
    messages = good[0]
    late = [(t, s + 10**10, m) if t == "/camera/image/compressed" else (t, s, m) for t, s, m in messages]
    late = [(t, s, compressed(s, jpeg_bytes(patches(60, 80)))) if t == "/camera/image/compressed" else (t, s, m)
            for t, s, m in late]  # fmt: skip
    assert problem(write_bag(tmp_path / "late", late)) == (
        "/camera/image/compressed: none of the 3 frames has a pose within bag_tolerance_s=0.1 "
        "(3 no_sample_after map->camera_link)"
    )


INFO = "/camera/camera_info message 0: "


@pytest.mark.parametrize(
    ("info", "expected"),
    [
        (camera_info(T0, 80, 60, K=np.zeros((3, 3))), INFO + "K is all zero (an uncalibrated camera)"),
        (camera_info(T0, 80, 60, binning=(2, 2)), INFO + "binning 2x2 is not supported"),
        (camera_info(T0, 80, 60, roi=(10, 10, 40, 30)), INFO + "a region of interest (40x30 at 10,10)"),
        (camera_info(T0, 80, 60, D=[0.1, 0, 0, 0, 0], model="kannala"), INFO + "unknown distortion model 'kannala'"),
        (
            camera_info(T0, 640, 480),
            "/camera/image/compressed message 0: the image is 80x60 but /camera/camera_info message 0 says 640x480",
        ),
    ],
)
def test_camera_info_refusals(tmp_path, good, info, expected):
    messages = good[0]
    messages = [m for m in messages if m[0] != "/camera/camera_info"] + [("/camera/camera_info", T0, info)]
    assert problem(write_bag(tmp_path / "info", messages)).startswith(expected)
