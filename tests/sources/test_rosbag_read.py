"""ROS 2 bags written here by rosbags' Writer, read by the replay source: the bag writer's layout
with no parameter, both storages, as a folder and as its file, through every entry point."""

from __future__ import annotations

import sqlite3
from dataclasses import fields

import cv2
import numpy as np
import pytest

from olsplat_nodes.sources import ReplaySource, SourceParams, open_source
from olsplat_nodes.sources.replay_log import read_replay, write_mcap
from olsplat_nodes.sources.rosbag import BagParams, is_rosbag2, read_bag

from .bags import T0, compressed, contract_messages, jpeg_bytes, patches, write_bag


def test_bag_params_are_the_bag_source_params():
    bag = {f.name.removeprefix("bag_"): f.default for f in fields(SourceParams) if f.name.startswith("bag_")}
    assert bag == {f.name: f.default for f in fields(BagParams)}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("inner", [False, True])
def test_the_writers_layout_reads_with_no_parameter(tmp_path, storage, inner):
    messages, custom, expected = contract_messages(count=4)
    bag = write_bag(tmp_path / "flight_bag", messages, storage=storage, custom=custom)
    path = bag / f"flight_bag.{'mcap' if storage == 'mcap' else 'db3'}" if inner else bag
    assert is_rosbag2(path)
    frames = list(read_replay(path))
    assert [f.name for f in frames] == [f"shot_{i}.jpg" for i in range(4)]
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    for frame, (stamp, pose, data) in zip(frames, expected, strict=True):
        assert frame.stamp_ns == stamp and frame.jpeg == data
        np.testing.assert_array_equal(frame.image, cv2.imdecode(np.frombuffer(data, np.uint8), 1)[..., ::-1])
        np.testing.assert_allclose(frame.camera.world_from_camera, pose, atol=1e-9)
        assert (frame.camera.width, frame.camera.height, frame.camera.model) == (80, 60, "PINHOLE")
        np.testing.assert_array_equal(
            frame.camera.K, [[100, 0, 40.5], [0, 100, 30.5], [0, 0, 1]]
        )  # +0.5: pixel centres
        assert frame.camera.dist.size == 0


def test_a_bag_through_open_source_and_the_metadata_file(tmp_path):
    messages, custom, expected = contract_messages(count=3, names=False)
    bag = write_bag(tmp_path / "b", messages, custom=custom)
    with open_source({"source_kind": "replay", "source": str(bag), "fast": True}) as source:
        frames = list(source)
    assert [f.name for f in frames] == ["frame_0000.jpg", "frame_0001.jpg", "frame_0002.jpg"]  # no custom data
    assert source.status() == (0, "finished")
    assert [f.stamp_ns for f in read_bag(bag / "metadata.yaml")] == [s for s, _, _ in expected]


def test_our_replay_log_still_reads_as_a_replay_log(tmp_path):
    messages, custom, _ = contract_messages(count=2)
    frames = list(read_replay(write_bag(tmp_path / "b", messages, custom=custom)))
    log = tmp_path / "log.mcap"
    write_mcap(log, frames)
    assert not is_rosbag2(log)
    again = list(read_replay(log))
    assert [f.name for f in again] == [f.name for f in frames] and again[1].jpeg == frames[1].jpeg


def test_a_humble_db3_without_message_definitions(tmp_path):
    messages, custom, expected = contract_messages(count=2)
    bag = write_bag(tmp_path / "humble", messages, storage="sqlite3", custom=custom)
    with sqlite3.connect(bag / "humble.db3") as db:  # Humble writes no definitions: rosbags falls back on its types
        db.execute("DELETE FROM message_definitions")
    frames = list(read_bag(bag))
    np.testing.assert_allclose(frames[1].camera.world_from_camera, expected[1][1], atol=1e-9)


def test_images_without_a_pose_are_dropped_and_reported(tmp_path):
    messages, custom, _ = contract_messages(count=3)
    late = T0 + 10 * 10**9  # an image long after the last /tf sample
    messages.append(("/camera/image/compressed", late, compressed(late, jpeg_bytes(patches(60, 80)))))
    bag = write_bag(tmp_path / "b", messages, custom=custom)
    source = ReplaySource(bag, fast=True)
    assert [f.seq for f in source] == [0, 1, 2]
    level, message = source.status()
    assert level == 1 and message == (
        f"{bag}: 1 of 4 frames on /camera/image/compressed had no pose and were dropped "
        "(1 no_sample_after map->camera_link)"
    )


def test_olsplat_record_turns_a_bag_into_a_replay_log(tmp_path, capsys):
    from olsplat_nodes.cli import main

    messages, custom, expected = contract_messages(count=3)
    bag = write_bag(tmp_path / "flight_bag", messages, custom=custom)
    out = tmp_path / "flight.mcap"
    assert main(["record", "--source-kind", "replay", "--source", str(bag), "--out", str(out)]) == 0
    frames = list(read_replay(out))
    assert [f.name for f in frames] == ["shot_0.jpg", "shot_1.jpg", "shot_2.jpg"]
    assert [(f.stamp_ns, f.jpeg) for f in frames] == [(s, data) for s, _, data in expected]
    np.testing.assert_allclose(frames[2].camera.world_from_camera, expected[2][1], atol=1e-9)


def test_a_zero_header_stamp_falls_back_on_the_log_time(tmp_path, caplog):
    messages, _, expected = contract_messages(count=2)
    log_ns = expected[1][0]
    messages = [m for m in messages if m[0] != "/camera/image/compressed"]
    messages.append(("/camera/image/compressed", log_ns, compressed(0, expected[1][2])))  # a driver that stamps nothing
    (frame,) = read_bag(write_bag(tmp_path / "b", messages))
    assert frame.stamp_ns == log_ns and frame.seq == 0
    np.testing.assert_allclose(frame.camera.world_from_camera, expected[1][1], atol=1e-9)
    assert "/camera/image/compressed message 0 has a zero header stamp: its log time is used" in caplog.text
