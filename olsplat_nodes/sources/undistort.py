"""Undistort a frame to the ideal pinhole image of its own K (``scene/camera.py``'s promise).

The rasterizer renders a pinhole image with ``K``; a frame from a distorted camera is remapped
once to that image, keeping K and the size, so that what meets rendered data has no distortion.
The remap tables are built once per (K, distortion, size, fisheye) and cached: a bag's camera
does not change between frames, and building them is far dearer than the remap.

- OpenCV pinhole distortion (k1, k2, p1, p2[, k3[, k4, k5, k6]]; ROS ``plumb_bob`` and
  ``rational_polynomial``): ``cv2.initUndistortRectifyMap``.
- Fisheye / equidistant (k1, k2, k3, k4; ROS ``equidistant``): ``cv2.fisheye.initUndistortRectifyMap``.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

__all__ = ["undistort_image"]


@lru_cache(maxsize=8)
def _maps(k_bytes: bytes, d_bytes: bytes, width: int, height: int, fisheye: bool) -> tuple[np.ndarray, np.ndarray]:
    K = np.frombuffer(k_bytes, np.float64).reshape(3, 3)
    D = np.frombuffer(d_bytes, np.float64)
    if fisheye:
        return cv2.fisheye.initUndistortRectifyMap(K, D[:4], np.eye(3), K, (width, height), cv2.CV_16SC2)
    return cv2.initUndistortRectifyMap(K, D, None, K, (width, height), cv2.CV_16SC2)


def undistort_image(image: np.ndarray, K: np.ndarray, dist: np.ndarray, fisheye: bool = False) -> np.ndarray:
    """[H, W, C] image from a camera with intrinsics K [3, 3] (pixels) and distortion ``dist``
    -> the same-size pinhole image of K (bilinear; pixels that map outside the frame are black)."""
    height, width = image.shape[:2]
    K = np.ascontiguousarray(K, np.float64).reshape(3, 3)
    dist = np.ascontiguousarray(dist, np.float64).reshape(-1)
    map1, map2 = _maps(K.tobytes(), dist.tobytes(), width, height, bool(fisheye))
    return cv2.remap(image, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
