"""Pixel-centre conventions at the boundary with OpenCV and ROS (``scene/camera.py``)."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.scene.camera import k_from_opencv, k_to_opencv


def test_opencv_intrinsics_are_half_a_pixel_off_and_round_trip_exactly():
    """ROS CameraInfo and OpenCV put the top-left pixel's centre at (0, 0), we at (0.5, 0.5)."""
    k_cv = np.array([[726.1, 0.0, 499.5], [0.0, 726.1, 374.5], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(k_from_opencv(k_cv), [[726.1, 0, 500.0], [0, 726.1, 375.0], [0, 0, 1]])
    rng = np.random.default_rng(0)
    for _ in range(1000):
        fx, fy, cx, cy = rng.uniform(50, 5000), rng.uniform(50, 5000), rng.uniform(0.5, 4000), rng.uniform(0.5, 3000)
        k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        np.testing.assert_array_equal(k_from_opencv(k_to_opencv(k)), k)
