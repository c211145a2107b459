"""Replay logs: write a flight to MCAP, read it (or a folder of images + COLMAP) back as frames.

MCAP layout (sim/README.md has the full description): JSON-encoded messages
with Foxglove schemas, so Foxglove opens the file and shows the images and camera poses.

| topic                | schema                    | per frame                                  |
|----------------------|---------------------------|--------------------------------------------|
| /camera/image        | foxglove.CompressedImage  | JPEG bytes (base64 in JSON)                |
| /camera/calibration  | foxglove.CameraCalibration| K, D (OpenCV plumb_bob), width, height     |
| /tf                  | foxglove.FrameTransform   | world -> camera pose (OpenCV camera axes)  |

All three messages of a frame share its ``log_time`` (the acquisition stamp in ns) and carry
the frame index as ``sequence``. A metadata record ``olsplat`` holds the frame names.
"""

from __future__ import annotations

import base64
import csv
import json
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from olsplat_nodes.errors import OlsplatInputError, SceneFormatError
from olsplat_nodes.scene import Camera, read_colmap
from olsplat_nodes.scene.rotations import quat_to_rotmat, rotmat_to_quat

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
SCHEMAS = {
    "foxglove.CompressedImage": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    },
    "foxglove.CameraCalibration": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "width": {"type": "integer"},
            "height": {"type": "integer"},
            "distortion_model": {"type": "string"},
            **{key: {"type": "array", "items": {"type": "number"}} for key in ("D", "K", "R", "P")},
        },
    },
    "foxglove.FrameTransform": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "parent_frame_id": {"type": "string"},
            "child_frame_id": {"type": "string"},
            "translation": _VEC3,
            "rotation": _QUAT,
        },
    },
}
TOPICS = {
    "/camera/image": "foxglove.CompressedImage",
    "/camera/calibration": "foxglove.CameraCalibration",
    "/tf": "foxglove.FrameTransform",
}
CAMERA_FRAME = "camera"


@dataclass
class ReplayFrame:
    seq: int  # frame index in the flight
    stamp_ns: int  # acquisition time, ns since the Unix epoch
    name: str
    image: np.ndarray  # [H, W, 3] uint8 RGB
    camera: Camera  # intrinsics + world_from_camera (OpenCV axes)


def _stamp(stamp_ns: int) -> dict:
    return {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}


def encode_jpeg(image_rgb: np.ndarray, quality: int = 92) -> bytes:
    ok, data = cv2.imencode(".jpg", image_rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return data.tobytes()


def write_mcap(path: str | Path, frames: Iterable[tuple[int, str, bytes, Camera]]) -> int:
    """Write (stamp_ns, name, jpeg_bytes, camera) frames; returns how many. Atomic (temp + rename)."""
    from mcap.writer import Writer

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    names = []
    with open(tmp, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="olsplat")
        schema_ids = {
            name: writer.register_schema(name, "jsonschema", json.dumps(s).encode()) for name, s in SCHEMAS.items()
        }
        channels = {
            topic: writer.register_channel(topic, "json", schema_ids[schema]) for topic, schema in TOPICS.items()
        }
        for seq, (stamp_ns, name, jpeg, camera) in enumerate(frames):
            names.append(name)
            k = camera.K
            dist = list(camera.dist) + [0.0] * (5 - len(camera.dist)) if len(camera.dist) <= 5 else list(camera.dist)
            pose = camera.world_from_camera
            q = rotmat_to_quat(pose[:3, :3])
            messages = {
                "/camera/image": {"timestamp": _stamp(stamp_ns), "frame_id": CAMERA_FRAME, "data": base64.b64encode(jpeg).decode(), "format": "jpeg"},
                "/camera/calibration": {
                    "timestamp": _stamp(stamp_ns), "frame_id": CAMERA_FRAME, "width": camera.width, "height": camera.height,
                    "distortion_model": "plumb_bob" if len(dist) <= 5 else "rational_polynomial", "D": dist,
                    "K": k.reshape(-1).tolist(), "R": np.eye(3).reshape(-1).tolist(), "P": np.c_[k, np.zeros(3)].reshape(-1).tolist(),
                },
                "/tf": {
                    "timestamp": _stamp(stamp_ns), "parent_frame_id": "world", "child_frame_id": CAMERA_FRAME,
                    "translation": dict(zip("xyz", pose[:3, 3].tolist())), "rotation": dict(zip("wxyz", q.tolist())),
                },
            }  # fmt: skip
            for topic, message in messages.items():
                writer.add_message(channels[topic], stamp_ns, json.dumps(message).encode(), stamp_ns, seq)
        writer.add_metadata("olsplat", {"frame_names": json.dumps(names), "camera_axes": "opencv"})
        writer.finish()
    tmp.replace(path)
    return len(names)


def _read_mcap(path: Path) -> Iterator[ReplayFrame]:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            names = []
            for record in reader.iter_metadata():
                if record.name == "olsplat":
                    names = json.loads(record.metadata.get("frame_names", "[]"))
            stream.seek(0)
            reader = make_reader(stream)
            pending: dict[int, dict] = {}
            for _, channel, message in reader.iter_messages(topics=list(TOPICS)):
                parts = pending.setdefault(message.sequence, {})
                parts[channel.topic] = json.loads(message.data)
                parts["stamp"] = message.log_time
                if len(parts) == len(TOPICS) + 1:
                    del pending[message.sequence]
                    yield _frame_from_messages(message.sequence, parts, names, path)
    except (OSError, ValueError, KeyError) as exc:
        raise SceneFormatError(path, f"not a readable olsplat MCAP replay log ({type(exc).__name__}: {exc})") from None
    except Exception as exc:  # the mcap package raises its own types for corrupt files
        if type(exc).__module__.startswith("mcap"):
            raise SceneFormatError(path, f"corrupt MCAP file ({type(exc).__name__}: {exc})") from None
        raise


def _frame_from_messages(seq: int, parts: dict, names: list[str], path: Path) -> ReplayFrame:
    image_msg, calib, tf = parts["/camera/image"], parts["/camera/calibration"], parts["/tf"]
    image = cv2.imdecode(np.frombuffer(base64.b64decode(image_msg["data"]), np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise SceneFormatError(path, f"frame {seq}: the image does not decode")
    pose = np.eye(4)
    r = tf["rotation"]
    pose[:3, :3] = quat_to_rotmat([r["w"], r["x"], r["y"], r["z"]])
    pose[:3, 3] = [tf["translation"][k] for k in "xyz"]
    K = np.asarray(calib["K"], float).reshape(3, 3)
    dist = np.asarray(calib["D"], float)
    name = names[seq] if seq < len(names) else f"frame_{seq:04d}.jpg"
    camera = Camera(
        name,
        calib["width"],
        calib["height"],
        K,
        pose,
        dist if dist.any() else np.zeros(0),
        "OPENCV" if dist.any() else "PINHOLE",
    )
    return ReplayFrame(seq, int(parts["stamp"]), name, image[..., ::-1].copy(), camera)


def _read_folder(folder: Path, rate_hz: float) -> Iterator[ReplayFrame]:
    """A folder with images/ and a COLMAP model (sparse/0/ or the folder itself)."""
    images = folder / "images" if (folder / "images").is_dir() else folder
    cameras = read_colmap(folder)
    stamps = {}
    table = images / "timestamps.csv"
    if table.is_file():
        with open(table) as f:
            stamps = {row["name"]: int(row["stamp_ns"]) for row in csv.DictReader(f)}
    for seq, camera in enumerate(cameras):
        file = images / camera.name
        image = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if image is None:
            raise SceneFormatError(file, "image missing or unreadable (named by the COLMAP model)")
        stamp = stamps.get(camera.name, int(round(seq * 1e9 / rate_hz)))
        yield ReplayFrame(seq, stamp, camera.name, image[..., ::-1].copy(), camera)


def read_replay(path: str | Path, folder_rate_hz: float = 1.0) -> Iterator[ReplayFrame]:
    """Frames of an MCAP replay log, or of a folder of images + COLMAP model, in order.

    A folder's stamps come from ``images/timestamps.csv`` (columns name, stamp_ns) when present,
    else from ``folder_rate_hz``.
    """
    path = Path(path)
    if path.is_dir():
        return _read_folder(path, folder_rate_hz)
    if not path.is_file():
        raise SceneFormatError(path, "does not exist")
    return _read_mcap(path)


def paced(frames: Iterable[ReplayFrame], rate_hz: float | None = None, fast: bool = False) -> Iterator[ReplayFrame]:
    """Yield frames at their recorded pace, at ``rate_hz``, or as fast as possible."""
    if rate_hz is not None and rate_hz <= 0:
        raise OlsplatInputError(f"the replay rate must be positive, got rate_hz={rate_hz}")
    start = first = None
    for i, frame in enumerate(frames):
        if not fast:
            now = time.monotonic()
            if start is None:
                start, first = now, frame.stamp_ns
            due = start + (i / rate_hz if rate_hz else (frame.stamp_ns - first) / 1e9)
            if due > now:
                time.sleep(due - now)
        yield frame


def write_timestamps(path: str | Path, names: list[str], stamps: list[int]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["name", "stamp_ns"])
        writer.writerows(zip(names, stamps))
