"""Replay logs: the MCAP and the image folder give the same frames; bad logs fail clearly."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.scene import read_colmap
from olsplat_sim.replay_log import paced, read_replay


def test_mcap_and_folder_replay_agree(tiny):
    out, _ = tiny
    from_log = list(read_replay(out / "replay.mcap"))
    from_folder = list(read_replay(out))
    assert [f.seq for f in from_log] == list(range(12))
    assert [f.name for f in from_log] == [f.name for f in from_folder]
    assert [f.stamp_ns for f in from_log] == [f.stamp_ns for f in from_folder]
    assert all(b.stamp_ns > a.stamp_ns for a, b in zip(from_log, from_log[1:]))
    cameras = {c.name: c for c in read_colmap(out / "sparse" / "0")}
    for a, b in zip(from_log, from_folder):
        np.testing.assert_array_equal(a.image, b.image)  # the same JPEG bytes in both
        np.testing.assert_allclose(a.camera.world_from_camera, cameras[a.name].world_from_camera, atol=1e-6)
        np.testing.assert_allclose(a.camera.K, cameras[a.name].K)
        assert a.image.shape == (240, 320, 3)
    disk = cv2.imread(str(out / "images" / from_log[0].name))[..., ::-1]
    np.testing.assert_array_equal(disk, from_log[0].image)


def test_pacing(tiny):
    out, _ = tiny
    frames = list(read_replay(out / "replay.mcap"))[:5]
    start = time.monotonic()
    assert len(list(paced(frames, rate_hz=40.0))) == 5
    assert time.monotonic() - start >= 4 / 40.0 - 0.005
    start = time.monotonic()
    list(paced(frames, fast=True))
    assert time.monotonic() - start < 4 / 40.0


def test_corrupt_and_missing_logs(tmp_path, tiny):
    out, _ = tiny
    data = (out / "replay.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all" * 10)
    for name in ("cut.mcap", "junk.mcap"):
        with pytest.raises(SceneFormatError, match=name):
            list(read_replay(tmp_path / name))
    with pytest.raises(SceneFormatError, match="does not exist"):
        read_replay(tmp_path / "none.mcap")


def test_replay_cli(tiny, capsys, tmp_path):
    out, _ = tiny
    assert main(["sim", "replay", "--log", str(out / "replay.mcap"), "--fast", "--limit", "3"]) == 0
    printed = capsys.readouterr().out
    assert "frame_0002.jpg" in printed and "3 frames in" in printed
    assert main(["sim", "replay", "--log", str(tmp_path / "missing.mcap"), "--fast"]) == 1
    assert "missing.mcap: does not exist" in capsys.readouterr().err
