"""``write_rosbag2`` and ``olsplat record --format rosbag2``: bags read back by rosbags' own AnyReader."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from olsplat_nodes.cli import main
from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.scene import Camera, intrinsics, look_at
from olsplat_nodes.scene.camera import k_to_opencv
from olsplat_nodes.sources import SourceFrame
from olsplat_nodes.sources.replay_log import encode_jpeg, read_replay, write_mcap
from olsplat_nodes.sources.rosbag_write import write_rosbag2

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
PLUMB_BOB = (0.1, -0.02, 0.001, 0.002, 0.003)  # OpenCV k1 k2 p1 p2 k3
RATIONAL = (*PLUMB_BOB, 0.01, 0.02, 0.004)  # + k4 k5 k6
EPOCH_NS = 1_717_200_000_123_456_789  # 2024-06-01, with nanoseconds that an int32 second field must keep
TOPICS = {
    "/camera/image/compressed": "sensor_msgs/msg/CompressedImage",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
}


def make_frames(n: int = 4, dist=(), with_jpeg: bool = True) -> list[SourceFrame]:
    """n frames of a 40 x 30 camera flying over the origin, turned and tilted differently each frame."""
    rng = np.random.default_rng(len(dist) + n)
    frames = []
    for i in range(n):
        image = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
        pose = look_at([3.0 * i - 4.0, 2.0 - i, 20.0 + i], [0.5 * i, -0.3, 0.0], (np.sin(i), np.cos(i), 0.2))
        K = intrinsics(35.0 + i, 36.5, 19.7, 15.2)
        camera = Camera(f"frame_{i:04d}.jpg", 40, 30, K, pose, dist=list(dist), model="OPENCV" if dist else "PINHOLE")
        jpeg = encode_jpeg(image, 90) if with_jpeg else None
        frames.append(SourceFrame(i + 7, EPOCH_NS + i * 333_333_333, camera.name, image, camera, jpeg))
    return frames


def rotation_xyzw(q) -> np.ndarray:
    """ROS quaternion (x, y, z, w) -> [3, 3] rotation (Hamilton; written out here, not olsplat's)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix(transform) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation_xyzw(transform.rotation)
    out[:3, 3] = [transform.translation.x, transform.translation.y, transform.translation.z]
    return out


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def read_bag(path: Path) -> dict:
    """Everything in the bag, decoded by rosbags: connections by topic, messages by topic in log
    order as (log time, message), the metadata's version and custom_data."""
    with AnyReader([path], default_typestore=HUMBLE) as reader:
        connections = {c.topic: c for c in reader.connections}
        messages: dict[str, list] = {topic: [] for topic in connections}
        for connection, log_ns, raw in reader.messages():
            messages[connection.topic].append((log_ns, reader.deserialize(raw, connection.msgtype)))
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {"connections": connections, "messages": messages, "info": info}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("dist", [(), PLUMB_BOB, RATIONAL])
def test_the_bag_as_rosbags_reads_it(tmp_path, storage, dist):
    frames = make_frames(dist=dist)
    out = tmp_path / "flight"
    assert write_rosbag2(out, frames, storage) == len(frames)
    suffix = {"mcap": ".mcap", "sqlite3": ".db3"}[storage]
    assert sorted(p.name for p in out.iterdir()) == sorted(["metadata.yaml", f"flight{suffix}"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flight"]  # no partial folder left
    bag = read_bag(out)
    info = bag["info"]
    assert info["version"] == 8 and info["storage_identifier"] == storage
    assert json.loads(info["custom_data"]["olsplat.frame_names"]) == [f.name for f in frames]
    connections, messages = bag["connections"], bag["messages"]
    assert {t: c.msgtype for t, c in connections.items()} == TOPICS
    assert {t: c.msgcount for t, c in connections.items()} == {t: 1 if t == "/tf_static" else 4 for t in TOPICS}
    for topic, connection in connections.items():
        (qos,) = connection.ext.offered_qos_profiles
        latched = topic == "/tf_static"
        assert (qos.durability.name, qos.depth) == (("TRANSIENT_LOCAL", 1) if latched else ("VOLATILE", 10))
        assert (qos.reliability.name, qos.history.name) == ("RELIABLE", "KEEP_LAST")

    ((static_log, static),) = messages["/tf_static"]
    (mount,) = static.transforms
    assert (mount.header.frame_id, mount.child_frame_id) == ("camera_link", "camera_optical_frame")
    assert static_log == stamp_ns(mount.header) == frames[0].stamp_ns
    link_from_optical = matrix(mount.transform)
    # REP-103: the optical z axis (forward) is camera_link's x, optical x (right) is -y, optical y (down) is -z
    np.testing.assert_allclose(link_from_optical[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(link_from_optical[:3, :3] @ [1, 0, 0], [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(link_from_optical[:3, :3] @ [0, 1, 0], [0, 0, -1], atol=1e-15)

    for frame, (image_log, image), (info_log, camera_info), (tf_log, tf) in zip(
        frames, messages["/camera/image/compressed"], messages["/camera/camera_info"], messages["/tf"], strict=True
    ):
        assert image_log == info_log == tf_log == frame.stamp_ns  # log time = header stamp = frame stamp
        assert stamp_ns(image.header) == stamp_ns(camera_info.header) == frame.stamp_ns
        assert image.header.frame_id == camera_info.header.frame_id == "camera_optical_frame"
        assert image.format == "jpeg" and bytes(image.data) == frame.jpeg
        camera = frame.camera
        assert (camera_info.width, camera_info.height) == (camera.width, camera.height)
        np.testing.assert_array_equal(camera_info.k.reshape(3, 3), k_to_opencv(camera.K))
        np.testing.assert_array_equal(camera_info.r.reshape(3, 3), np.eye(3))
        np.testing.assert_array_equal(camera_info.p.reshape(3, 4), np.c_[k_to_opencv(camera.K), np.zeros(3)])
        expected_d = list(dist) + [0.0] * (5 - len(dist)) if len(dist) <= 5 else list(dist)
        assert camera_info.distortion_model == ("plumb_bob" if len(dist) <= 5 else "rational_polynomial")
        assert camera_info.d.tolist() == expected_d
        (pose,) = tf.transforms
        assert (pose.header.frame_id, pose.child_frame_id, stamp_ns(pose.header)) == (
            "map",
            "camera_link",
            frame.stamp_ns,
        )
        # map -> camera_link (/tf) then camera_link -> camera_optical_frame (/tf_static): the camera's pose
        np.testing.assert_allclose(
            matrix(pose.transform) @ link_from_optical, camera.world_from_camera, rtol=0, atol=1e-9
        )


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_the_inner_file_reads_alone(tmp_path, storage):
    """rosbags opens the storage file without its folder too (how a copied .mcap is often shared)."""
    frames = make_frames(2)
    write_rosbag2(tmp_path / "b", frames, storage)
    (inner,) = [p for p in (tmp_path / "b").iterdir() if p.name != "metadata.yaml"]  # b.mcap or b.db3
    with AnyReader([inner], default_typestore=HUMBLE) as reader:
        images = [c for c in reader.connections if c.topic == "/camera/image/compressed"]
        data = [bytes(reader.deserialize(raw, c.msgtype).data) for c, _, raw in reader.messages(connections=images)]
    assert data == [f.jpeg for f in frames]


def test_frames_without_jpeg_are_encoded_once(tmp_path):
    frames = make_frames(3, with_jpeg=False)
    write_rosbag2(tmp_path / "bare", frames, jpeg_quality=75)
    images = read_bag(tmp_path / "bare")["messages"]["/camera/image/compressed"]
    assert [bytes(m.data) for _, m in images] == [encode_jpeg(f.image, 75) for f in frames]


def test_an_error_mid_write_leaves_nothing(tmp_path):
    frames = make_frames(3)

    def broken():
        yield from frames[:2]
        raise RuntimeError("camera unplugged")

    for storage in ("mcap", "sqlite3"):
        with pytest.raises(RuntimeError, match="camera unplugged"):
            write_rosbag2(tmp_path / "cut", broken(), storage)
        assert list(tmp_path.iterdir()) == []  # neither the bag nor its hidden partial folder
    late = [SourceFrame(0, 2**31 * 10**9, "late.jpg", frames[0].image, frames[0].camera, frames[0].jpeg)]
    with pytest.raises(ValueError, match=r"frame 'late\.jpg': stamp 2147483648000000000 ns is outside ROS time"):
        write_rosbag2(tmp_path / "late", late)
    assert list(tmp_path.iterdir()) == []


def test_an_existing_target_or_a_bad_storage_is_refused(tmp_path):
    (tmp_path / "taken").mkdir()
    with pytest.raises(OlsplatInputError, match="taken: already exists; a rosbag2 bag is written to a new folder"):
        write_rosbag2(tmp_path / "taken", make_frames(1))
    with pytest.raises(OlsplatInputError, match="rosbag2 storage must be 'mcap' or 'sqlite3', got 'zip'"):
        write_rosbag2(tmp_path / "new", make_frames(1), "zip")  # type: ignore[arg-type]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


@pytest.mark.parametrize("storage", [None, "sqlite3"])
def test_record_a_replay_log_to_a_bag(tmp_path, capsys, storage):
    frames = make_frames(3, dist=(0.05, 0.0, 0.0, 0.0))
    write_mcap(tmp_path / "session.mcap", frames)
    out = tmp_path / "bags" / "session"
    args = ["record", "--source", str(tmp_path / "session.mcap"), "--format", "rosbag2", "--out", str(out)]
    assert main(args + (["--storage", storage] if storage else [])) == 0
    assert f"3 frames -> {out}" in capsys.readouterr().out
    bag = read_bag(out)
    assert bag["info"]["storage_identifier"] == (storage or "mcap")
    assert json.loads(bag["info"]["custom_data"]["olsplat.frame_names"]) == [f.name for f in frames]
    images = bag["messages"]["/camera/image/compressed"]
    assert [bytes(m.data) for _, m in images] == [f.jpeg for f in read_replay(tmp_path / "session.mcap")]
    assert [log_ns for log_ns, _ in images] == [f.stamp_ns for f in frames]
    # refusals, each one line before the source is opened
    assert main(args) == 1
    assert f"--out {out}: already exists; a rosbag2 bag is written to a new folder" in capsys.readouterr().err
    assert main([*args[:-1], str(tmp_path / "x.mcap")]) == 1
    assert "a rosbag2 bag is a folder; give a name without .mcap" in capsys.readouterr().err
    assert main(["record", "--source", "s.mcap", "--storage", "sqlite3", "--out", str(tmp_path / "y")]) == 1
    assert "--storage sqlite3 is for --format rosbag2" in capsys.readouterr().err


def test_record_nothing_leaves_no_bag(tmp_path):
    from olsplat_nodes.sources import PacedSource
    from olsplat_nodes.sources.record import record

    assert record(PacedSource([], fast=True), tmp_path / "empty", out_format="rosbag2") == 0
    assert list(tmp_path.iterdir()) == []
    frames = make_frames(2)
    assert record(PacedSource(frames, fast=True), tmp_path / "two", out_format="rosbag2", storage="sqlite3") == 2
    assert (tmp_path / "two" / "two.db3").is_file()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("dist", [(), PLUMB_BOB, RATIONAL])
def test_round_trip_through_the_replay_source(tmp_path, storage, dist):
    """write_rosbag2 -> read_replay (sources/rosbag.py), as the folder and as its storage file:
    the same names, stamps, JPEG bytes, cameras, and poses within 1e-9 (D kept: bag_undistort false)."""
    frames = make_frames(dist=dist)
    bag = tmp_path / "flight"
    write_rosbag2(bag, frames, storage)
    inner = bag / ("flight.mcap" if storage == "mcap" else "flight.db3")
    for path in (bag, inner):
        again = list(read_replay(path, bag={"bag_undistort": False}))
        assert [(f.name, f.stamp_ns) for f in again] == [(f.name, f.stamp_ns) for f in frames]
        for a, b in zip(frames, again, strict=True):
            assert b.jpeg == a.jpeg
            np.testing.assert_array_equal(
                b.image, cv2.imdecode(np.frombuffer(a.jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            )
            assert (b.camera.name, b.camera.width, b.camera.height) == (a.camera.name, a.camera.width, a.camera.height)
            np.testing.assert_array_equal(b.camera.K, a.camera.K)
            np.testing.assert_array_equal(np.trim_zeros(b.camera.dist, "b"), np.trim_zeros(a.camera.dist, "b"))
            np.testing.assert_allclose(b.camera.world_from_camera, a.camera.world_from_camera, rtol=0, atol=1e-9)
