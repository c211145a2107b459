"""Image encodings in a bag: raw Image with padded rows and both byte orders, Bayer mosaics of
known colour patches, PNG and JPEG CompressedImage; each topic read with bag_image_topic."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from olsplat_nodes.sources.ros_image import decode_raw
from olsplat_nodes.sources.rosbag import read_bag

from .bags import (
    T0,
    camera_info,
    compressed,
    jpeg_bytes,
    patches,
    png_bytes,
    raw_image,
    rigid,
    tf_message,
    transform,
    write_bag,
)

RGB = patches(60, 80, seed=3)  # [60, 80, 3], 10-pixel flat patches
GREY = RGB[..., 1]
ALPHA = np.full((60, 80, 1), 77, np.uint8)


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The [H, W] Bayer mosaic of an RGB image; ``pattern`` names the 2x2 cell from the top left."""
    channel = {"r": 0, "g": 1, "b": 2}
    out = np.zeros(rgb.shape[:2], rgb.dtype)
    for (dy, dx), letter in zip([(0, 0), (0, 1), (1, 0), (1, 1)], pattern, strict=True):
        out[dy::2, dx::2] = rgb[dy::2, dx::2, channel[letter]]
    return out


# topic -> (message at stamp T0, what the frame must show)
IMAGES = {
    "/rgb8": (raw_image(T0, "rgb8", RGB, step=80 * 3 + 13), RGB),
    "/bgr8": (raw_image(T0, "bgr8", RGB[..., ::-1], step=256), RGB),
    "/rgba8": (raw_image(T0, "rgba8", np.concatenate([RGB, ALPHA], 2)), RGB),
    "/bgra8": (raw_image(T0, "bgra8", np.concatenate([RGB[..., ::-1], ALPHA], 2), step=330), RGB),
    "/mono8": (raw_image(T0, "mono8", GREY, step=81), np.repeat(GREY[..., None], 3, 2)),
    "/mono16_be": (
        raw_image(T0, "mono16", GREY.astype(np.uint16) * 256 + 17, step=170, bigendian=True),
        np.repeat(GREY[..., None], 3, 2),
    ),
    "/mono16_le": (raw_image(T0, "mono16", GREY.astype(np.uint16) * 256 + 200), np.repeat(GREY[..., None], 3, 2)),
    "/rgb16_be": (raw_image(T0, "rgb16", RGB.astype(np.uint16) * 257, step=500, bigendian=True), RGB),
    "/png": (compressed(T0, png_bytes(RGB), fmt="png"), RGB),
}
BAYER = {
    f"/bayer_{p}": (raw_image(T0, f"bayer_{p}8", mosaic(RGB, p), step=96), RGB)
    for p in ("rggb", "bggr", "gbrg", "grbg")
}


@pytest.fixture(scope="module")
def image_bag(tmp_path_factory):
    messages = [("/tf_static", T0, tf_message(transform(T0, "map", "camera_optical_frame", rigid(0.5, (1, 2, 3)))))]
    messages.append(("/camera_info", T0, camera_info(T0, 80, 60)))
    jpeg = jpeg_bytes(RGB)
    messages.append(("/jpeg", T0, compressed(T0, jpeg, fmt="rgb8; jpeg compressed bgr8")))
    messages += [(topic, T0, message) for topic, (message, _) in {**IMAGES, **BAYER}.items()]
    return write_bag(tmp_path_factory.mktemp("bags") / "images", messages), jpeg


@pytest.mark.parametrize("topic", sorted(IMAGES))
def test_raw_and_png_images_decode_exactly(image_bag, topic):
    bag, _ = image_bag
    (frame,) = read_bag(bag, {"bag_image_topic": topic})
    np.testing.assert_array_equal(frame.image, IMAGES[topic][1])
    assert frame.jpeg is None and frame.image.dtype == np.uint8 and frame.image.flags.c_contiguous
    np.testing.assert_allclose(frame.camera.world_from_camera, rigid(0.5, (1, 2, 3)), atol=1e-12)


@pytest.mark.parametrize("topic", sorted(BAYER))
def test_bayer_mosaics_demosaic_to_their_colour_patches(image_bag, topic):
    bag, _ = image_bag
    (frame,) = read_bag(bag, {"bag_image_topic": topic})
    inside = np.zeros((60, 80), bool)  # 2 px away from every patch edge: demosaicing is exact there
    for y in range(0, 60, 10):
        for x in range(0, 80, 10):
            inside[y + 2 : y + 8, x + 2 : x + 8] = True
    np.testing.assert_array_equal(frame.image[inside], RGB[inside])


def test_jpeg_bytes_are_kept_whatever_the_format_string(image_bag):
    bag, jpeg = image_bag
    (frame,) = read_bag(bag, {"bag_image_topic": "/jpeg"})
    assert frame.jpeg == jpeg
    np.testing.assert_array_equal(frame.image, cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("yuv422", 2, 2, 4, False, b"\0" * 8), "unsupported image encoding 'yuv422'"),
        (("rgb8", 2, 2, 5, False, b"\0" * 10), "step 5 is too short for 2 rgb8 pixels (6 bytes)"),
        (("mono16", 2, 2, 5, False, b"\0" * 10), "or not whole pixels"),
        (("rgb8", 2, 2, 6, False, b"\0" * 11), "data has 11 bytes, rgb8 2x2 with step 6 needs 12"),
    ],
)
def test_raw_refusals_say_why(args, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        decode_raw(*args)
