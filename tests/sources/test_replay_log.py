"""The replay log format: the MCAP and the image folder give the same frames; the on-disk layout
stays as documented; bad logs fail clearly."""

from __future__ import annotations

import base64
import itertools
import json
import time

import cv2
import numpy as np
import pytest

from olsplat_nodes.errors import OlsplatInputError, SceneFormatError
from olsplat_nodes.scene import Camera, read_colmap, write_colmap
from olsplat_nodes.scene.rotations import quat_to_rotmat
from olsplat_nodes.sources import SourceFrame
from olsplat_nodes.sources.replay_log import (
    SCHEMAS,
    TOPICS,
    encode_jpeg,
    paced,
    read_replay,
    write_mcap,
    write_timestamps,
)


def test_mcap_and_folder_replay_agree(tiny):
    out, _ = tiny
    from_log = list(read_replay(out / "replay.mcap"))
    from_folder = list(read_replay(out))
    assert all(isinstance(f, SourceFrame) for f in from_log + from_folder)
    assert [f.seq for f in from_log] == list(range(12))
    assert [f.name for f in from_log] == [f.name for f in from_folder]
    assert [f.stamp_ns for f in from_log] == [f.stamp_ns for f in from_folder]
    assert all(b.stamp_ns > a.stamp_ns for a, b in itertools.pairwise(from_log))
    cameras = {c.name: c for c in read_colmap(out / "sparse" / "0")}
    for a, b in zip(from_log, from_folder, strict=True):
        # the same JPEG bytes in both, carried by the frames
        assert a.jpeg == b.jpeg == (out / "images" / a.name).read_bytes()
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_allclose(a.camera.world_from_camera, cameras[a.name].world_from_camera, atol=1e-6)
        np.testing.assert_allclose(a.camera.K, cameras[a.name].K)
        assert a.image.shape == (240, 320, 3)
    disk = cv2.imread(str(out / "images" / from_log[0].name))[..., ::-1]
    np.testing.assert_array_equal(disk, from_log[0].image)


def _frames(n: int = 3) -> list[SourceFrame]:
    """Frames with distortion and without, arbitrary rotations and source sequence numbers."""
    rng = np.random.default_rng(7)
    frames = []
    for i in range(n):
        q = rng.normal(size=4)
        pose = np.eye(4)
        pose[:3, :3] = quat_to_rotmat(q / np.linalg.norm(q))
        pose[:3, 3] = rng.normal(size=3) * 20
        dist = [0.1, -0.02, 0.001, 0.0005, 0.003][: 5 * (i % 2 == 0)]
        camera = Camera(f"oak_{i}.jpg", 48, 32, [[40, 0, 24.5], [0, 41, 16], [0, 0, 1]], pose, dist, "OPENCV")
        image = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
        frames.append(
            SourceFrame(1000 + 7 * i, 1_700_000_000_123_456_789 + i * 250_000_000, camera.name, image, camera)
        )
    return frames


def test_on_disk_layout(tmp_path):
    """The layout other tools (Foxglove, older logs) rely on: schema and topic names, encodings,
    one sequence number and one stamp per frame, the names in the ``olsplat`` metadata."""
    from mcap.reader import make_reader

    frames = _frames()
    path = tmp_path / "log.mcap"
    assert write_mcap(path, frames, jpeg_quality=90) == 3
    assert not (tmp_path / "log.mcap.tmp").exists()
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()} == {
            "/camera/image": "foxglove.CompressedImage",
            "/camera/calibration": "foxglove.CameraCalibration",
            "/tf": "foxglove.FrameTransform",
        }
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        assert {s.name: json.loads(s.data) for s in summary.schemas.values()} == SCHEMAS
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        stream.seek(0)
        messages = [(channel.topic, message) for _, channel, message in make_reader(stream).iter_messages()]
    assert json.loads(metadata["olsplat"]["frame_names"]) == [f.name for f in frames]
    assert metadata["olsplat"]["camera_axes"] == "opencv"
    assert len(messages) == 3 * len(TOPICS)
    for topic, message in messages:
        frame = frames[message.sequence]  # the log numbers frames 0, 1, 2, not by the source's seq
        assert message.log_time == message.publish_time == frame.stamp_ns
        body = json.loads(message.data)
        assert body["timestamp"] == {"sec": frame.stamp_ns // 10**9, "nsec": frame.stamp_ns % 10**9}
        if topic == "/camera/image":
            assert body["format"] == "jpeg" and body["frame_id"] == "camera"
            assert base64.b64decode(body["data"]) == encode_jpeg(frame.image, 90)
        elif topic == "/camera/calibration":
            assert (body["width"], body["height"], body["distortion_model"]) == (48, 32, "plumb_bob")
            assert body["K"] == frame.camera.K.reshape(-1).tolist()
            assert body["D"] == (frame.camera.dist.tolist() or [0.0] * 5)
        else:
            assert (body["parent_frame_id"], body["child_frame_id"]) == ("world", "camera")
            assert [body["translation"][k] for k in "xyz"] == frame.camera.world_from_camera[:3, 3].tolist()

    again = list(read_replay(path))
    assert [f.seq for f in again] == [0, 1, 2]
    for a, b in zip(frames, again, strict=True):
        assert (a.name, a.stamp_ns) == (b.name, b.stamp_ns)
        assert b.jpeg == encode_jpeg(a.image, 90)
        np.testing.assert_array_equal(
            b.image, cv2.imdecode(np.frombuffer(b.jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        )
        np.testing.assert_array_equal(a.camera.K, b.camera.K)
        np.testing.assert_array_equal(a.camera.dist, b.camera.dist)
        assert b.camera.model == ("OPENCV" if len(a.camera.dist) else "PINHOLE")
        np.testing.assert_allclose(a.camera.world_from_camera, b.camera.world_from_camera, rtol=0, atol=1e-12)
    # frames that bring their JPEG bytes are written as they are: writing the read frames again is lossless
    assert write_mcap(tmp_path / "again.mcap", again) == 3
    assert [f.jpeg for f in read_replay(tmp_path / "again.mcap")] == [f.jpeg for f in again]


def test_folder_of_png_images(tmp_path):
    """A folder replays without timestamps.csv (stamps at ``folder_rate_hz``); PNGs carry no JPEG bytes."""
    frames = _frames(2)
    (tmp_path / "images").mkdir()
    cameras = []
    for frame in frames:
        name = frame.name.replace(".jpg", ".png")
        cameras.append(
            Camera(name, frame.camera.width, frame.camera.height, frame.camera.K, frame.camera.world_from_camera)
        )
        cv2.imwrite(str(tmp_path / "images" / name), frame.image[..., ::-1])
    write_colmap(tmp_path, cameras, binary=False)
    again = list(read_replay(tmp_path, folder_rate_hz=4.0))
    assert [f.stamp_ns for f in again] == [0, 250_000_000]
    assert all(f.jpeg is None for f in again)
    for a, b in zip(frames, again, strict=True):
        np.testing.assert_array_equal(a.image, b.image)  # PNG is lossless
    write_timestamps(tmp_path / "images" / "timestamps.csv", [c.name for c in cameras], [5, 9])
    assert [f.stamp_ns for f in read_replay(tmp_path)] == [5, 9]
    with pytest.raises(ValueError, match="2 names but 1 stamps"):
        write_timestamps(tmp_path / "t.csv", [c.name for c in cameras], [5])
    (tmp_path / "images" / cameras[1].name).unlink()
    with pytest.raises(SceneFormatError, match="image missing or unreadable"):
        list(read_replay(tmp_path))


def test_pacing(tiny):
    out, _ = tiny
    frames = list(read_replay(out / "replay.mcap"))[:5]
    start = time.monotonic()
    assert len(list(paced(frames, rate_hz=40.0))) == 5
    assert time.monotonic() - start >= 4 / 40.0 - 0.005
    start = time.monotonic()
    list(paced(frames, fast=True))
    assert time.monotonic() - start < 4 / 40.0
    # the recorded pace: stamp differences, here 0.1 s apart
    spaced = [SourceFrame(i, 10**18 + i * 100_000_000, f.name, f.image, f.camera) for i, f in enumerate(frames[:3])]
    start = time.monotonic()
    assert [f.seq for f in paced(spaced)] == [0, 1, 2]
    assert time.monotonic() - start >= 0.2 - 0.005
    with pytest.raises(OlsplatInputError, match="rate must be positive"):
        paced(frames, rate_hz=0.0)


def test_a_cut_log_replays_its_whole_frames_and_reports_the_cut(tmp_path, tiny, caplog):
    """A log cut at half its bytes (a recording that did not finish) replays every whole frame
    before the cut, the same frames as the whole log's, then one WARN naming the file and the
    count; the replay source's status says it too."""
    from olsplat_nodes.sources import open_source
    from olsplat_nodes.sources.base import WARN

    out, summary = tiny
    whole = list(read_replay(out / "replay.mcap"))
    data = (out / "replay.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with caplog.at_level("WARNING", logger="olsplat_nodes.sources.replay_log"):
        with open_source({"source_kind": "replay", "source": str(cut), "fast": True}) as source:
            frames = list(source)
            level, message = source.status()
    n = len(frames)
    assert summary["views"] // 2 - 2 <= n < summary["views"], n  # the frames before the cut, no more
    for got, want in zip(frames, whole, strict=False):
        assert (got.seq, got.name, got.stamp_ns, got.jpeg) == (want.seq, want.name, want.stamp_ns, want.jpeg)
        np.testing.assert_array_equal(got.camera.world_from_camera, want.camera.world_from_camera)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and str(cut) in warnings[0] and f"replayed the {n} whole frames" in warnings[0]
    assert level == WARN and message == warnings[0]


def test_corrupt_and_missing_logs(tmp_path, tiny):
    out, _ = tiny
    data = (out / "replay.mcap").read_bytes()
    (tmp_path / "early.mcap").write_bytes(data[:200])  # cut before its first frame: nothing to replay
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all" * 10)
    for name, why in (("early.mcap", "cut before its first whole frame"), ("junk.mcap", "invalid magic")):
        with pytest.raises(SceneFormatError, match=name) as error:
            list(read_replay(tmp_path / name))
        assert why in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(SceneFormatError, match="does not exist"):
        read_replay(tmp_path / "none.mcap")
