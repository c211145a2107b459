"""CameraInfo in a bag: distortion kept exactly with bag_undistort false; with it on, a point
projected through the distortion (cv2.projectPoints) lands at its pinhole pixel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from olsplat_nodes.scene.camera import k_from_opencv
from olsplat_nodes.sources.rosbag import read_bag

from .bags import T0, camera_info, compressed, jpeg_bytes, patches, raw_image, rigid, tf_message, transform, write_bag

W, H = 160, 120
K = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
MODELS = {
    "plumb_bob": [-0.25, 0.08, 0.001, -0.0005, 0.01],
    "rational_polynomial": [-0.2, 0.05, 0.0005, 0.0002, 0.0, 0.1, -0.02, 0.01],
    "equidistant": [0.05, -0.01, 0.002, -0.0005],
}
POINTS = np.array([[-0.55, -0.4, 1.0], [0.6, 0.35, 1.0], [-0.5, 0.45, 1.0], [0.1, -0.05, 1.0]])  # camera frame


def distorted_pixels(model: str) -> np.ndarray:
    """[N, 2] where the distorted camera sees POINTS (OpenCV pixel coordinates)."""
    D = np.array(MODELS[model])
    zero = np.zeros(3)
    if model == "equidistant":
        pixels, _ = cv2.fisheye.projectPoints(POINTS.reshape(-1, 1, 3), zero, zero, K, D)
    else:
        pixels, _ = cv2.projectPoints(POINTS, zero, zero, K, D)
    return pixels.reshape(-1, 2)


def spots(centres: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8: a Gaussian spot (sigma 1.2 px) at each centre on black."""
    v, u = np.mgrid[0:H, 0:W]
    image = np.zeros((H, W))
    for cu, cv in centres:
        image += 250 * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * 1.2**2))
    return np.repeat(np.clip(image, 0, 255).round().astype(np.uint8)[..., None], 3, 2)


def centroid(image: np.ndarray, near: np.ndarray, radius: int = 6) -> np.ndarray:
    u0, v0 = np.round(near).astype(int)
    patch = image[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1, 0].astype(float)
    v, u = np.mgrid[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1]
    return np.array([(patch * u).sum(), (patch * v).sum()]) / patch.sum()


def distorted_bag(tmp_path, model: str, image_message):
    messages = [
        ("/tf_static", T0, tf_message(transform(T0, "map", "camera_optical_frame", rigid(0.2, (1, 2, 3))))),
        ("/camera/camera_info", T0, camera_info(T0, W, H, K=K, D=MODELS[model], model=model)),
        ("/camera/image", T0, image_message),
    ]
    return write_bag(tmp_path / model, messages)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_undistorted_frames_put_points_at_their_pinhole_pixels(tmp_path, model):
    image = spots(distorted_pixels(model))
    (frame,) = read_bag(distorted_bag(tmp_path, model, raw_image(T0, "rgb8", image)))
    assert frame.camera.dist.size == 0 and frame.camera.model == "PINHOLE" and frame.jpeg is None
    np.testing.assert_array_equal(frame.camera.K, k_from_opencv(K))  # our pixel centres are at +0.5
    pinhole = (POINTS @ K.T)[:, :2] / POINTS[:, 2:]  # OpenCV's convention: array indices, as centroid
    assert np.abs(distorted_pixels(model) - pinhole).max() > 5  # the distortion is not negligible
    found = np.array([centroid(frame.image, p) for p in pinhole])
    np.testing.assert_allclose(found, pinhole, atol=0.15)


@pytest.mark.parametrize(("model", "colmap"), [("plumb_bob", "OPENCV"), ("rational_polynomial", "FULL_OPENCV")])
def test_distortion_is_kept_exactly_when_asked(tmp_path, model, colmap):
    data = jpeg_bytes(patches(H, W))
    bag = distorted_bag(tmp_path, model, compressed(T0, data))
    (frame,) = read_bag(bag, {"bag_undistort": False})
    np.testing.assert_array_equal(frame.camera.dist, MODELS[model])
    assert frame.camera.model == colmap and frame.jpeg == data


def test_fisheye_distortion_cannot_be_kept(tmp_path):
    bag = distorted_bag(tmp_path, "equidistant", compressed(T0, jpeg_bytes(patches(H, W))))
    with pytest.raises(ValueError, match=r"/camera/camera_info message 0: equidistant \(fisheye\) distortion cannot"):
        list(read_bag(bag, {"bag_undistort": False}))
