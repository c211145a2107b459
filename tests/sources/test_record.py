"""``olsplat record``: any source -> the MCAP replay log, re-read identically."""

from __future__ import annotations

import cv2
import numpy as np

from olsplat_nodes.cli import main
from olsplat_nodes.sources import open_source
from olsplat_nodes.sources.record import record
from olsplat_sim.replay_log import encode_jpeg, read_replay


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
    for a, b in zip(original, again):
        assert (a.seq, a.stamp_ns, a.name) == (b.seq, b.stamp_ns, b.name)
        assert_same_camera(a.camera, b.camera)
        # the log stores JPEG: the re-read image is exactly the decoded JPEG the recorder wrote
        jpeg = encode_jpeg(a.image, 95)
        np.testing.assert_array_equal(b.image, cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1])
    # replaying the recording is reproducible bit for bit: recording it again changes nothing but the JPEG generation
    assert [f.stamp_ns for f in read_replay(out)] == [f.stamp_ns for f in again]
    assert all(np.array_equal(x.image, y.image) for x, y in zip(read_replay(out), again))


def test_record_keeps_original_jpeg_bytes_and_limits(photo_folder, tmp_path):
    source = open_source({"source_kind": "exif_folder", "source": str(photo_folder), "fast": True})
    frames = list(open_source({"source_kind": "exif_folder", "source": str(photo_folder), "fast": True}))
    out = tmp_path / "photos.mcap"
    assert record(source, out, frames=3) == 3
    again = list(read_replay(out))
    assert [f.name for f in again] == [f.name for f in frames[:3]]
    for a, b in zip(frames, again):
        np.testing.assert_array_equal(a.image, b.image)  # the photo's own bytes: no re-encoding
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
    assert "source_kind must be one of" in capsys.readouterr().err
