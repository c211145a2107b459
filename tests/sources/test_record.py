"""``olsplat record``: any source -> the MCAP replay log, re-read identically."""

from __future__ import annotations

import cv2
import numpy as np

from olsplat_nodes.cli import main
from olsplat_nodes.sources import PacedSource, SourceFrame, open_source
from olsplat_nodes.sources.record import record
from olsplat_nodes.sources.replay_log import encode_jpeg, read_replay


def assert_same_camera(a, b):
    assert (a.name, a.width, a.height, a.model) == (b.name, b.width, b.height, b.model)
    np.testing.assert_array_equal(a.K, b.K)
    np.testing.assert_array_equal(a.dist, b.dist)
    np.testing.assert_allclose(a.world_from_camera, b.world_from_camera, rtol=0, atol=1e-12)  # through a quaternion


def test_record_a_replay_source_and_read_it_back(tiny, tmp_path, capsys):
    scene, _ = tiny
    original = list(read_replay(scene / "replay.mcap"))
    out = tmp_path / "session.mcap"
    assert main(["record", "--source-kind", "replay", "--source", str(scene / "replay.mcap"), "--out", str(out)]) == 0
    assert f"{len(original)} frames" in capsys.readouterr().out
    again = list(read_replay(out))
    assert len(again) == len(original)
    for a, b in zip(original, again, strict=True):
        assert (a.seq, a.stamp_ns, a.name) == (b.seq, b.stamp_ns, b.name)
        assert_same_camera(a.camera, b.camera)
        # the log's JPEG bytes are copied, not re-encoded: the images are exactly the original ones
        assert b.jpeg == a.jpeg
        np.testing.assert_array_equal(a.image, b.image)


def test_record_encodes_frames_without_jpeg_once(tiny, tmp_path):
    """Frames without JPEG bytes (a live camera) are encoded once, at ``jpeg_quality``."""
    scene, _ = tiny
    original = list(read_replay(scene / "replay.mcap"))[:4]
    bare = [SourceFrame(f.seq, f.stamp_ns, f.name, f.image, f.camera) for f in original]
    out = tmp_path / "bare.mcap"
    assert record(PacedSource(bare, fast=True), out, jpeg_quality=80) == 4
    again = list(read_replay(out))
    for a, b in zip(original, again, strict=True):
        assert (a.seq, a.stamp_ns, a.name) == (b.seq, b.stamp_ns, b.name)
        assert_same_camera(a.camera, b.camera)
        assert b.jpeg == encode_jpeg(a.image, 80)
        decoded = cv2.imdecode(np.frombuffer(b.jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        np.testing.assert_array_equal(b.image, decoded)
        assert not np.array_equal(a.image, b.image)  # a second generation of JPEG


def test_record_keeps_original_jpeg_bytes_and_limits(photo_folder, tmp_path):
    source = open_source({"source_kind": "exif_folder", "source": str(photo_folder), "fast": True})
    frames = list(open_source({"source_kind": "exif_folder", "source": str(photo_folder), "fast": True}))
    out = tmp_path / "photos.mcap"
    assert record(source, out, frames=3) == 3
    again = list(read_replay(out))
    assert [f.name for f in again] == [f.name for f in frames[:3]]
    for a, b in zip(frames, again, strict=False):  # again: the first 3
        assert b.jpeg == a.jpeg  # the photo's own bytes: no re-encoding
        np.testing.assert_array_equal(a.image, b.image)
        assert a.stamp_ns == b.stamp_ns
        assert_same_camera(a.camera, b.camera)


def test_record_without_a_camera_writes_nothing_and_fails(tmp_path, capsys):
    from olsplat_nodes.sources import discover_devices

    if discover_devices():
        import pytest

        pytest.skip("a DepthAI device is attached")
    out = tmp_path / "none.mcap"
    code = main(
        ["record", "--source-kind", "depthai", "--set", "depthai_retry_s=0.2", "--out", str(out), "--seconds", "1.5"]
    )
    assert code == 1 and not out.exists()
    assert "no DepthAI device found" in capsys.readouterr().err
    assert main(["record", "--source-kind", "nope", "--out", str(out)]) == 1
    assert (
        "source.source_kind: expected one of 'replay', 'exif_folder', 'depthai', got 'nope'" in capsys.readouterr().err
    )
