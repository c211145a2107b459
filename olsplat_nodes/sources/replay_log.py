"""The replay log format: write frames to MCAP, read them (or a folder of images + COLMAP) back.

This is the drone side's own format: ``olsplat record`` writes it, the replay source reads it,
and the simulator (``olsplat sim make``) writes its flights through this module. Every frame,
written or read, is a ``SourceFrame`` (``base.py``).

MCAP layout (the README.md beside this file has the full description): JSON-encoded messages
with Foxglove schemas, so Foxglove opens the file and shows the images and camera poses.

| topic                | schema                    | per frame                                  |
|----------------------|---------------------------|--------------------------------------------|
| /camera/image        | foxglove.CompressedImage  | JPEG bytes (base64 in JSON)                |
| /camera/calibration  | foxglove.CameraCalibration| K, D (OpenCV plumb_bob), width, height     |
| /tf                  | foxglove.FrameTransform   | world -> camera pose (OpenCV camera axes)  |

All three messages of a frame share its ``log_time`` (the acquisition stamp in ns) and carry
the frame's index in the log (0, 1, 2, ...) as ``sequence``. A metadata record ``olsplat``
holds the frame names, by index.

A log survives being cut (a power cut while recording, a copy that stopped): each message is
its own chunk and each frame's name a metadata record ``olsplat_frame`` written before the
frame's messages, so everything before the cut is whole on the disk. The reader reads the file
front to back (no summary, no index needed) and a cut log replays every whole frame before the
cut, then logs one WARN naming the file and the frames replayed.
"""

from __future__ import annotations

import base64
import csv
import json
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import SceneFormatError
from ..scene import Camera, read_colmap
from ..scene.rotations import quat_to_rotmat, rotmat_to_quat
from .base import Pacer, SourceFrame

log = logging.getLogger(__name__)

__all__ = [
    "CAMERA_FRAME",
    "SCHEMAS",
    "TOPICS",
    "encode_jpeg",
    "paced",
    "read_replay",
    "write_mcap",
    "write_timestamps",
]

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
_JPEG_MAGIC = b"\xff\xd8\xff"  # start of image + the first marker
_FRAME_METADATA = "olsplat_frame"  # per frame, before its messages: sequence, name


def _stamp(stamp_ns: int) -> dict:
    return {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}


def encode_jpeg(image_rgb: np.ndarray, quality: int = 92) -> bytes:
    """JPEG bytes of an [H, W, 3] uint8 RGB image."""
    ok, data = cv2.imencode(".jpg", image_rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return data.tobytes()


def _decode_rgb(data: bytes) -> np.ndarray | None:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return None if image is None else image[..., ::-1].copy()


def _messages(stamp_ns: int, jpeg: bytes, camera: Camera) -> dict[str, dict]:
    """The three messages of one frame, by topic."""
    k = camera.K
    dist = list(camera.dist) + [0.0] * (5 - len(camera.dist)) if len(camera.dist) <= 5 else list(camera.dist)
    pose = camera.world_from_camera
    q = rotmat_to_quat(pose[:3, :3])  # w, x, y, z
    stamp = _stamp(stamp_ns)
    return {
        "/camera/image": {
            "timestamp": stamp,
            "frame_id": CAMERA_FRAME,
            "data": base64.b64encode(jpeg).decode(),
            "format": "jpeg",
        },
        "/camera/calibration": {
            "timestamp": stamp,
            "frame_id": CAMERA_FRAME,
            "width": camera.width,
            "height": camera.height,
            "distortion_model": "plumb_bob" if len(dist) <= 5 else "rational_polynomial",
            "D": dist,
            "K": k.reshape(-1).tolist(),
            "R": np.eye(3).reshape(-1).tolist(),
            "P": np.c_[k, np.zeros(3)].reshape(-1).tolist(),
        },
        "/tf": {
            "timestamp": stamp,
            "parent_frame_id": "world",
            "child_frame_id": CAMERA_FRAME,
            "translation": dict(zip("xyz", pose[:3, 3].tolist(), strict=True)),
            "rotation": dict(zip("wxyz", q.tolist(), strict=True)),
        },
    }


def write_mcap(path: str | Path, frames: Iterable[SourceFrame], jpeg_quality: int = 92) -> int:
    """Write the frames to an MCAP replay log; returns how many. Atomic (temp file + rename).

    A frame's ``jpeg`` bytes go in as they are; a frame without them is encoded once at
    ``jpeg_quality``. Stamps, names, intrinsics and poses are kept; ``seq`` is not: the log
    numbers its frames 0, 1, 2, ... in the order written (read back as ``seq``).
    """
    from mcap.writer import Writer

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    names = []
    with open(tmp, "wb") as stream:
        # a chunk per message (chunk_size 1 closes each after its message): a cut file keeps every whole frame
        writer = Writer(stream, chunk_size=1)
        writer.start(profile="", library="olsplat")
        schema_ids = {
            name: writer.register_schema(name, "jsonschema", json.dumps(s).encode()) for name, s in SCHEMAS.items()
        }
        channels = {
            topic: writer.register_channel(topic, "json", schema_ids[schema]) for topic, schema in TOPICS.items()
        }
        for index, frame in enumerate(frames):
            names.append(frame.name)
            writer.add_metadata(_FRAME_METADATA, {"sequence": str(index), "name": frame.name})
            jpeg = frame.jpeg if frame.jpeg is not None else encode_jpeg(frame.image, jpeg_quality)
            stamp_ns = int(frame.stamp_ns)
            for topic, message in _messages(stamp_ns, jpeg, frame.camera).items():
                writer.add_message(channels[topic], stamp_ns, json.dumps(message).encode(), stamp_ns, index)
        writer.add_metadata("olsplat", {"frame_names": json.dumps(names), "camera_axes": "opencv"})
        writer.finish()
    tmp.replace(path)
    return len(names)


def _final_names(path: Path) -> list[str]:
    """The frame names of a finished log's ``olsplat`` metadata (read through its summary); []
    when the log has no summary (cut) or no such record."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as stream:
            for record in make_reader(stream).iter_metadata():
                if record.name == "olsplat":
                    return list(json.loads(record.metadata.get("frame_names", "[]")))
    except Exception:  # a cut or foreign file: the front-to-back pass below says which
        return []
    return []


def _read_mcap(path: Path, on_cut: Callable[[str], None] | None = None) -> Iterator[SourceFrame]:
    """Front to back through the records (``mcap.stream_reader``): a frame is yielded once its
    three messages are in; at a cut (the file ends inside a record or before its footer) the
    frames so far stand and the cut is logged (and told to ``on_cut``)."""
    from mcap.exceptions import EndOfFile, McapError
    from mcap.records import Channel, Footer, Message, Metadata
    from mcap.stream_reader import StreamReader

    names = dict(enumerate(_final_names(path)))
    topics: dict[int, str] = {}
    pending: dict[int, dict] = {}
    replayed = 0
    try:
        with open(path, "rb") as stream:
            for record in StreamReader(stream).records:
                if isinstance(record, Metadata) and record.name == _FRAME_METADATA:
                    names.setdefault(int(record.metadata["sequence"]), record.metadata["name"])
                elif isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message) and topics.get(record.channel_id) in TOPICS:
                    parts = pending.setdefault(record.sequence, {})
                    parts[topics[record.channel_id]] = json.loads(record.data)
                    parts["stamp"] = record.log_time
                    if len(parts) == len(TOPICS) + 1:
                        del pending[record.sequence]
                        replayed += 1
                        yield _frame_from_messages(record.sequence, parts, names, path)
                elif isinstance(record, Footer):
                    return
    except EndOfFile:
        pass  # cut inside a record
    except SceneFormatError:
        raise
    except (OSError, ValueError, KeyError) as exc:
        raise SceneFormatError(path, f"not a readable olsplat MCAP replay log ({type(exc).__name__}: {exc})") from None
    except McapError as exc:
        raise SceneFormatError(path, f"corrupt MCAP file ({type(exc).__name__}: {exc})") from None
    if not replayed:
        raise SceneFormatError(path, "MCAP replay log cut before its first whole frame")
    message = (
        f"{path}: the replay log is cut (it ends without its footer: a recording that did not finish); "
        f"replayed the {replayed} whole frames before the cut"
    )
    log.warning(message)
    if on_cut is not None:
        on_cut(message)


def _frame_from_messages(seq: int, parts: dict, names: dict[int, str], path: Path) -> SourceFrame:
    image_msg, calib, tf = parts["/camera/image"], parts["/camera/calibration"], parts["/tf"]
    data = base64.b64decode(image_msg["data"])
    image = _decode_rgb(data)
    if image is None:
        raise SceneFormatError(path, f"frame {seq}: the image does not decode")
    pose = np.eye(4)
    r = tf["rotation"]
    pose[:3, :3] = quat_to_rotmat([r["w"], r["x"], r["y"], r["z"]])
    pose[:3, 3] = [tf["translation"][k] for k in "xyz"]
    K = np.asarray(calib["K"], float).reshape(3, 3)
    dist = np.asarray(calib["D"], float)
    name = names.get(seq, f"frame_{seq:04d}.jpg")
    camera = Camera(
        name,
        calib["width"],
        calib["height"],
        K,
        pose,
        dist if dist.any() else np.zeros(0),
        "OPENCV" if dist.any() else "PINHOLE",
    )
    jpeg = data if image_msg.get("format") == "jpeg" and data.startswith(_JPEG_MAGIC) else None
    return SourceFrame(seq, int(parts["stamp"]), name, image, camera, jpeg)


def _read_timestamps(table: Path) -> dict[str, int]:
    with open(table) as f:
        return {row["name"]: int(row["stamp_ns"]) for row in csv.DictReader(f)}


def _read_folder(folder: Path, rate_hz: float) -> Iterator[SourceFrame]:
    """A folder with images/ and a COLMAP model (sparse/0/ or the folder itself)."""
    images = folder / "images" if (folder / "images").is_dir() else folder
    cameras = read_colmap(folder)
    table = images / "timestamps.csv"
    stamps = _read_timestamps(table) if table.is_file() else {}
    for seq, camera in enumerate(cameras):
        file = images / camera.name
        try:
            data = file.read_bytes()
        except OSError:
            data = b""
        image = _decode_rgb(data) if data else None
        if image is None:
            raise SceneFormatError(file, "image missing or unreadable (named by the COLMAP model)")
        stamp = stamps.get(camera.name, int(round(seq * 1e9 / rate_hz)))
        jpeg = data if data.startswith(_JPEG_MAGIC) else None  # a PNG is re-encoded when recorded
        yield SourceFrame(seq, stamp, camera.name, image, camera, jpeg)


def read_replay(
    path: str | Path,
    folder_rate_hz: float = 1.0,
    on_cut: Callable[[str], None] | None = None,
    bag: Mapping[str, Any] | None = None,
) -> Iterator[SourceFrame]:
    """Frames of an MCAP replay log, a folder of images + COLMAP model, or a ROS 2 bag, in order.

    A ROS 2 bag (a rosbag2 folder, its ``.db3``, or a ``.mcap`` with profile ``ros2``) is read
    by ``rosbag.read_bag`` with ``bag`` (the flat ``bag_*`` source params); its
    WARN line on frames dropped for want of a pose goes to ``on_cut`` like a cut log's.

    Frames carry the stored JPEG bytes (``jpeg``), so recording a replay copies its images
    exactly. A folder's stamps come from ``images/timestamps.csv`` (columns name, stamp_ns)
    when present, else from ``folder_rate_hz``. Unreadable input raises ``SceneFormatError``
    (a missing path at once, a corrupt log while iterating). A cut log (no footer: a recording
    that did not finish) gives its whole frames before the cut, then logs one WARN naming the
    file and the frames replayed, the same line given to ``on_cut``.
    """
    path = Path(path)
    from .rosbag import is_rosbag2, read_bag  # rosbags is imported only when a bag is read

    if is_rosbag2(path) or path.name == "metadata.yaml":
        return read_bag(path, bag, on_cut)
    if path.is_dir():
        return _read_folder(path, folder_rate_hz)
    if not path.is_file():
        raise SceneFormatError(path, "does not exist")
    return _read_mcap(path, on_cut)


def paced(frames: Iterable[SourceFrame], rate_hz: float | None = None, fast: bool = False) -> Iterator[SourceFrame]:
    """Yield frames at their recorded pace (stamp differences), at ``rate_hz``, or at once (``fast``).

    Sleeps between frames; the rule is ``Pacer``'s, which a polled source asks instead.
    A non-positive ``rate_hz`` raises ``OlsplatInputError`` here, before any frame.
    """
    pacer = Pacer(rate_hz, fast)

    def frames_in_time() -> Iterator[SourceFrame]:
        for frame in frames:
            wait = pacer.due(frame.stamp_ns) - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            pacer.sent()
            yield frame

    return frames_in_time()


def write_timestamps(path: str | Path, names: list[str], stamps: list[int]) -> None:
    """``timestamps.csv`` for an image folder: columns name, stamp_ns (ns since the Unix epoch)."""
    if len(names) != len(stamps):
        raise ValueError(f"{len(names)} names but {len(stamps)} stamps")
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["name", "stamp_ns"])
        writer.writerows(zip(names, stamps, strict=True))
