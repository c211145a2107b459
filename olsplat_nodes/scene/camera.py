"""The camera of one view: intrinsics, distortion and pose.

Conventions (stated once, used everywhere):
- Camera axes are OpenCV's: +x right, +y down, +z forward (into the scene).
- ``world_from_camera`` [4, 4] maps camera coordinates to world coordinates (a "camera to
  world" pose); its translation is the camera centre in the world.
- Pixel (u, v) = (column, row); the centre of the top-left pixel is (0.5, 0.5), so
  u = fx * x / z + cx with cx = width / 2 for a centred principal point (COLMAP's convention).
- ``dist`` holds OpenCV distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]). The
  rasterizer renders the ideal pinhole image with ``K``; frames from a distorted camera are
  undistorted to that image (cv2.undistort) before they meet rendered data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Camera:
    name: str
    width: int  # image width in pixels, that is, number of columns
    height: int  # image height in pixels, that is, number of rows
    K: np.ndarray  # [3, 3] float64 pinhole intrinsics
    world_from_camera: np.ndarray  # [4, 4] float64 rigid transform
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))  # OpenCV coefficients
    model: str = "PINHOLE"  # COLMAP model name the intrinsics came from / are written as

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.world_from_camera = np.asarray(self.world_from_camera, dtype=np.float64).reshape(4, 4)
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        if not (np.isfinite(self.K).all() and self.K[0, 0] > 0 and self.K[1, 1] > 0):
            raise ValueError(
                f"camera {self.name!r}: focal lengths must be positive and finite, got K={self.K.tolist()}"
            )
        rotation = self.world_from_camera[:3, :3]
        if not np.isfinite(self.world_from_camera).all() or not np.allclose(
            rotation.T @ rotation, np.eye(3), atol=1e-4
        ):
            raise ValueError(f"camera {self.name!r}: world_from_camera is not a rigid transform")

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        return self.world_from_camera[:3, 3].copy()

    def scaled(self, factor: float) -> Camera:
        """The same view as an image ``factor`` times the size (0.5: half the width and height,
        each rounded, at least 1 px): focal lengths and principal point scaled by the exact ratio
        of the sizes, so each pixel edge of this image maps onto the new one's (pixel centres
        stay at +0.5); pose and distortion (normalised coordinates) unchanged."""
        width, height = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        K = self.K.copy()
        K[0] *= width / self.width
        K[1] *= height / self.height
        return Camera(self.name, width, height, K, self.world_from_camera.copy(), self.dist.copy(), self.model)

    @property
    def camera_from_world(self) -> np.ndarray:
        """[4, 4] world-to-camera transform (the inverse rigid transform)."""
        rotation = self.world_from_camera[:3, :3]
        out = np.eye(4)
        out[:3, :3] = rotation.T
        out[:3, 3] = -rotation.T @ self.world_from_camera[:3, 3]
        return out


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """[3, 3] pinhole matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def k_from_opencv(k_opencv) -> np.ndarray:
    """[3, 3] K in OpenCV's and ROS CameraInfo's convention (the top-left pixel's centre is
    (0, 0)) -> ours (COLMAP's: (0.5, 0.5)): the principal point moves by half a pixel. Exact in
    floating point for any principal point of at least half a pixel, so a round trip is exact."""
    k = np.array(k_opencv, np.float64, copy=True).reshape(3, 3)
    k[:2, 2] += 0.5
    return k


def k_to_opencv(k) -> np.ndarray:
    """[3, 3] our K -> OpenCV's convention (``k_from_opencv``'s inverse)."""
    k = np.array(k, np.float64, copy=True).reshape(3, 3)
    k[:2, 2] -= 0.5
    return k


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] world_from_camera (OpenCV axes) for a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear upwards in the image (image -y).
    """
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
        right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose
