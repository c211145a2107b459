"""ROS 2 camera messages: images -> [H, W, 3] uint8 RGB (+ their JPEG bytes), CameraInfo -> intrinsics.

Our own decoder rather than ``rosbags-image``, which ignores ``step`` (padded rows come out
sheared). ``sensor_msgs/msg/Image`` fields, as in its .msg: ``height`` rows, ``width`` columns,
``step`` the row length in bytes (>= width * channels * bytes per channel; the rest is padding),
``is_bigendian`` the byte order of 16-bit data, ``data`` step * height bytes.

- rgb8, bgr8, rgba8, bgra8, mono8, and their 16-bit forms (rgb16, bgr16, rgba16, bgra16, mono16,
  also 8UC1/8UC3/16UC1 as mono/bgr): 16 bits keep their high byte, alpha is dropped, mono
  becomes grey RGB.
- Bayer mosaics ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` (and 16): the
  ROS name is the 2x2 pattern from the top-left pixel, OpenCV's ``COLOR_BayerRGGB2RGB`` etc.
  (cv2's long names read the same way).
- ``sensor_msgs/msg/CompressedImage``: decoded by content (``format`` may be ``jpeg``, ``png``,
  ``rgb8; jpeg compressed bgr8``...); data starting with the JPEG magic is kept as ``jpeg``.
  ``compressedDepth`` (16-bit depth PNG with a header) is refused.

Every problem raises ``ValueError`` with a one-line reason; the bag reader adds the path,
topic and message index.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "DISTORTION_MODELS",
    "JPEG_MAGIC",
    "RAW_ENCODINGS",
    "Intrinsics",
    "camera_intrinsics",
    "decode_compressed",
    "decode_image_message",
    "decode_raw",
]

JPEG_MAGIC = b"\xff\xd8\xff"  # start of image + the first marker

# encoding -> (bytes per channel, channels, channel order: "rgb", "bgr", "mono" or a cv2 Bayer code)
RAW_ENCODINGS: dict[str, tuple[int, int, str | int]] = {
    "rgb8": (1, 3, "rgb"),
    "bgr8": (1, 3, "bgr"),
    "rgba8": (1, 4, "rgb"),
    "bgra8": (1, 4, "bgr"),
    "mono8": (1, 1, "mono"),
    "8UC1": (1, 1, "mono"),
    "8UC3": (1, 3, "bgr"),  # OpenCV's own type: cv_bridge treats it as bgr
    "rgb16": (2, 3, "rgb"),
    "bgr16": (2, 3, "bgr"),
    "rgba16": (2, 4, "rgb"),
    "bgra16": (2, 4, "bgr"),
    "mono16": (2, 1, "mono"),
    "16UC1": (2, 1, "mono"),
    **{
        f"bayer_{pattern}{bits}": (bits // 8, 1, getattr(cv2, f"COLOR_Bayer{pattern.upper()}2RGB"))
        for pattern in ("rggb", "bggr", "gbrg", "grbg")
        for bits in (8, 16)
    },
}


def decode_raw(encoding: str, height: int, width: int, step: int, is_bigendian: bool, data) -> np.ndarray:
    """A ``sensor_msgs/msg/Image``'s pixels -> [height, width, 3] uint8 RGB (rules in the module docstring)."""
    if encoding not in RAW_ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r} (supported: {', '.join(RAW_ENCODINGS)})")
    itemsize, channels, order = RAW_ENCODINGS[encoding]
    if height <= 0 or width <= 0:
        raise ValueError(f"empty image ({width}x{height})")
    row = width * channels * itemsize
    buffer = np.frombuffer(memoryview(data).cast("B"), np.uint8)
    if step < row or step % itemsize:
        raise ValueError(f"step {step} is too short for {width} {encoding} pixels ({row} bytes) or not whole pixels")
    if buffer.size < step * height:
        raise ValueError(
            f"data has {buffer.size} bytes, {encoding} {width}x{height} with step {step} needs {step * height}"
        )
    dtype = np.dtype(np.uint8) if itemsize == 1 else np.dtype(">u2" if is_bigendian else "<u2")
    rows = buffer[: step * height].view(dtype).reshape(height, step // itemsize)
    pixels = rows[:, : width * channels].reshape(height, width, channels)  # padding dropped
    if itemsize == 2:
        pixels = (pixels.astype(np.uint16) >> 8).astype(np.uint8)  # native order, high byte
    if isinstance(order, int):  # a Bayer mosaic
        return cv2.cvtColor(np.ascontiguousarray(pixels[..., 0]), order)
    if order == "mono":
        return np.repeat(pixels, 3, axis=2)
    rgb = pixels[..., :3] if order == "rgb" else pixels[..., 2::-1]
    return np.ascontiguousarray(rgb)


def decode_compressed(fmt: str, data) -> tuple[np.ndarray, bytes | None]:
    """A ``sensor_msgs/msg/CompressedImage`` -> ([H, W, 3] uint8 RGB, the JPEG bytes or None)."""
    if "compresseddepth" in fmt.lower().replace(" ", ""):
        raise ValueError(f"compressed depth images are not camera frames (format {fmt!r})")
    raw = bytes(memoryview(data).cast("B"))
    image = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"the {fmt or 'compressed'} image ({len(raw)} bytes) does not decode")
    return np.ascontiguousarray(image[..., ::-1]), raw if raw.startswith(JPEG_MAGIC) else None


def decode_image_message(msg) -> tuple[np.ndarray, bytes | None]:
    """An Image or CompressedImage message (rosbags dataclass) -> (RGB [H, W, 3] uint8, JPEG bytes or None)."""
    if msg.__msgtype__ == "sensor_msgs/msg/CompressedImage":
        return decode_compressed(msg.format, msg.data)
    return (
        decode_raw(msg.encoding, int(msg.height), int(msg.width), int(msg.step), bool(msg.is_bigendian), msg.data),
        None,
    )


@dataclass(frozen=True)
class Intrinsics:
    """What a ``sensor_msgs/msg/CameraInfo`` says of the raw image, in olsplat's terms."""

    width: int  # columns
    height: int  # rows
    K: np.ndarray  # [3, 3] pixels
    dist: np.ndarray  # [N] OpenCV coefficients (pinhole: k1 k2 p1 p2 [k3 [k4 k5 k6]]; fisheye: k1..k4); [] = none
    fisheye: bool  # ROS "equidistant" (cv2.fisheye's model)
    model: str  # COLMAP name when the distortion is kept: PINHOLE, OPENCV, FULL_OPENCV


DISTORTION_MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}  # ROS name -> coefficients


def camera_intrinsics(info, rectified: bool = False) -> Intrinsics:
    """A CameraInfo message -> ``Intrinsics``; ``ValueError`` (one line) for what we cannot use.

    ``rectified``: the image is an ``image_rect*`` topic (already undistorted): the projection
    ``P``'s left 3x3 is its K and there is no distortion. Refused: an all-zero K (uncalibrated),
    binning above 1, a region of interest smaller than the image, a distortion model other than
    plumb_bob, rational_polynomial and equidistant (an empty or unknown name is accepted only
    with all-zero coefficients), more non-zero coefficients than the model has.
    """
    width, height = int(info.width), int(info.height)
    K = np.asarray(info.k, np.float64).reshape(3, 3)
    if not K.any():
        raise ValueError("K is all zero (an uncalibrated camera)")
    if max(int(info.binning_x), int(info.binning_y)) > 1:
        raise ValueError(f"binning {info.binning_x}x{info.binning_y} is not supported (calibrate the binned image)")
    roi = info.roi
    if (roi.x_offset or roi.y_offset or roi.width or roi.height) and (
        roi.x_offset,
        roi.y_offset,
        roi.width,
        roi.height,
    ) != (0, 0, width, height):
        raise ValueError(
            f"a region of interest ({roi.width}x{roi.height} at {roi.x_offset},{roi.y_offset}) is not supported"
        )
    if rectified:
        return Intrinsics(
            width, height, np.asarray(info.p, np.float64).reshape(3, 4)[:, :3], np.zeros(0), False, "PINHOLE"
        )
    dist = np.asarray(info.d, np.float64).reshape(-1)
    if not dist.any():
        return Intrinsics(width, height, K, np.zeros(0), False, "PINHOLE")
    model = info.distortion_model
    if model not in DISTORTION_MODELS:
        raise ValueError(f"unknown distortion model {model!r} (known: {', '.join(DISTORTION_MODELS)})")
    count = DISTORTION_MODELS[model]
    if dist[count:].any():
        raise ValueError(f"{model} has {count} coefficients, got {len(dist)} with non-zero ones beyond")
    dist = np.pad(dist[:count], (0, count - min(count, len(dist))))
    named = {"plumb_bob": "OPENCV", "rational_polynomial": "FULL_OPENCV", "equidistant": "OPENCV_FISHEYE"}
    return Intrinsics(width, height, K, dist, model == "equidistant", named[model])
