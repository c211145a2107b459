"""``olsplat sim make --bag``: replay_bag/ holds replay.mcap's frames, as rosbags' AnyReader reads them."""

from __future__ import annotations

import json

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from olsplat_nodes.cli import main
from olsplat_nodes.scene.camera import k_to_opencv
from olsplat_nodes.scene.rotations import quat_to_rotmat
from olsplat_nodes.sources.replay_log import read_replay


def _matrix(transform) -> np.ndarray:
    out = np.eye(4)
    r, t = transform.rotation, transform.translation
    out[:3, :3] = quat_to_rotmat([r.w, r.x, r.y, r.z])
    out[:3, 3] = [t.x, t.y, t.z]
    return out


def test_sim_make_bag_writes_the_replay_logs_frames(tmp_path):
    out = tmp_path / "scene"
    assert main(["sim", "make", "--preset", "tiny", "--views", "3", "--out", str(out), "--bag", "sqlite3"]) == 0
    frames = list(read_replay(out / "replay.mcap"))
    bag = out / "replay_bag"
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "replay_bag.db3"]
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert json.loads(info["custom_data"]["olsplat.frame_names"]) == [f.name for f in frames]
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        decoded: dict[str, list] = {}
        for connection, log_ns, raw in reader.messages():
            decoded.setdefault(connection.topic, []).append((log_ns, reader.deserialize(raw, connection.msgtype)))
    ((_, static),) = decoded["/tf_static"]
    link_from_optical = _matrix(static.transforms[0].transform)
    images, infos, poses = decoded["/camera/image/compressed"], decoded["/camera/camera_info"], decoded["/tf"]
    for frame, (log_ns, image), (_, camera_info), (_, tf) in zip(frames, images, infos, poses, strict=True):
        assert log_ns == frame.stamp_ns
        assert bytes(image.data) == frame.jpeg == (out / "images" / frame.name).read_bytes()
        np.testing.assert_array_equal(camera_info.k.reshape(3, 3), k_to_opencv(frame.camera.K))  # ROS pixel centres
        assert (camera_info.width, camera_info.height) == (320, 240)
        world_from_camera = _matrix(tf.transforms[0].transform) @ link_from_optical
        np.testing.assert_allclose(world_from_camera, frame.camera.world_from_camera, rtol=0, atol=1e-9)
    # and the replay source reads the bag as it reads the log (sources/rosbag.py)
    again = list(read_replay(bag))
    assert [(f.name, f.stamp_ns, f.jpeg) for f in again] == [(f.name, f.stamp_ns, f.jpeg) for f in frames]
    for a, b in zip(frames, again, strict=True):
        np.testing.assert_array_equal(b.image, a.image)
        np.testing.assert_array_equal(b.camera.K, a.camera.K)
        np.testing.assert_allclose(b.camera.world_from_camera, a.camera.world_from_camera, rtol=0, atol=1e-9)
