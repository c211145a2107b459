"""Autopilot state + camera mount -> ``world_from_camera`` (pure functions, no I/O).

Frames (stated once, used everywhere in this package):
- **NED**: the autopilot's local frame, metres, +x north, +y east, +z down. LOCAL_POSITION_NED
  is already in it (origin: the autopilot's EKF origin); GLOBAL_POSITION_INT is converted into
  it around a reference point (``geodetic_to_ned``, from ``scene/geodesy.py``).
- **Body FRD**: +x forward (nose), +y right, +z down. MAVLink ATTITUDE gives roll, pitch, yaw
  (radians) of the body w.r.t. NED as Z-Y-X Tait-Bryan angles:
  ``ned_from_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
- **World**: ENU, metres, +x east, +y north, +z up, same origin as the NED frame. ENU because
  the rest of olsplat is z-up (the simulator's town is east/north/up, ``look_at`` defaults to
  up = +z) and ROS REP-103 uses ENU for world frames; NED would put every map upside down.
- **Camera**: OpenCV axes, +x right, +y down, +z forward (optical axis), as ``scene.Camera``.

Camera mount: ``body_from_camera`` [3, 3] has the OpenCV camera axes as columns, written in
body FRD; ``lever_arm_m`` [3] is the camera centre in body FRD, metres, from the point whose
position the autopilot reports. Mount angles (``mount_rotation``) describe a "camera body"
frame (x along the optical axis, y image right, z image down) w.r.t. the vehicle body with the
same Z-Y-X convention as the vehicle attitude: (0, 0, 0) looks along the nose with the image
upright, pitch -90 looks straight down (nadir) with the nose at the top of the image.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# the WGS-84 maths live in the core (scene/geodesy.py); their old names stay importable from here
from ..scene.geodesy import ENU_FROM_NED, WGS84_A, WGS84_E2, WGS84_F, geodetic_to_ned  # noqa: F401

# Columns: OpenCV camera axes (right, down, optical axis) written in the camera-body frame
# (x optical axis, y right, z down).
CAMBODY_FROM_OPENCV = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def euler_to_rotmat(roll, pitch, yaw) -> np.ndarray:
    """Z-Y-X Tait-Bryan angles (radians, any matching shapes [...]) -> [..., 3, 3].

    The result maps body FRD vectors to NED: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (MAVLink
    ATTITUDE, aerospace convention).
    """
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (roll, pitch, yaw)))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def euler_to_quat(roll, pitch, yaw) -> np.ndarray:
    """Z-Y-X Tait-Bryan angles (radians, [...]) -> [..., 4] unit quaternion wxyz of ``euler_to_rotmat``."""
    half = [np.asarray(a, np.float64) / 2.0 for a in (roll, pitch, yaw)]
    (cr, cp, cy), (sr, sp, sy) = [np.cos(a) for a in half], [np.sin(a) for a in half]
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        -1,
    )


def mount_rotation(roll_deg: float = 0.0, pitch_deg: float = -90.0, yaw_deg: float = 0.0) -> np.ndarray:
    """[3, 3] ``body_from_camera`` (OpenCV camera axes) from mount angles in degrees.

    The default (0, -90, 0) is a nadir camera with the vehicle's nose at the top of the image.
    """
    angles = np.radians([roll_deg, pitch_deg, yaw_deg])
    return euler_to_rotmat(*angles) @ CAMBODY_FROM_OPENCV


def _check_rotation(matrix, what: str) -> np.ndarray:
    m = np.asarray(matrix, np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all():
        raise ValueError(f"{what} must be a finite 3x3 matrix, got {np.asarray(matrix).tolist()}")
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise ValueError(f"{what} must be a proper rotation (orthonormal, det +1), got {m.tolist()}")
    return m


@dataclass(frozen=True)
class CameraMount:
    """Where the camera sits on the vehicle (see the module docstring for the frames)."""

    body_from_camera: np.ndarray = field(default_factory=mount_rotation)  # [3, 3]; default nadir
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] body FRD, metres

    def __post_init__(self) -> None:
        object.__setattr__(self, "body_from_camera", _check_rotation(self.body_from_camera, "body_from_camera"))
        arm = np.asarray(self.lever_arm_m, np.float64).reshape(-1)
        if arm.shape != (3,) or not np.isfinite(arm).all():
            raise ValueError(f"lever_arm_m must be 3 finite numbers (metres, body FRD), got {self.lever_arm_m!r}")
        object.__setattr__(self, "lever_arm_m", arm)

    @classmethod
    def from_angles(
        cls, roll_deg: float = 0.0, pitch_deg: float = -90.0, yaw_deg: float = 0.0, lever_arm_m=(0.0, 0.0, 0.0)
    ) -> CameraMount:
        """Mount from camera-body angles in degrees (default: nadir) and a lever arm."""
        return cls(mount_rotation(roll_deg, pitch_deg, yaw_deg), lever_arm_m)


def world_from_camera(position_ned, ned_from_body, mount: CameraMount | None = None) -> np.ndarray:
    """Vehicle position and attitude + camera mount -> [..., 4, 4] world (ENU) from camera (OpenCV).

    position_ned   # [..., 3] metres, NED, of the point the autopilot reports
    ned_from_body  # [..., 3, 3] attitude (``euler_to_rotmat`` of ATTITUDE, or a quaternion's matrix)
    mount          # None: nadir camera at the reported point
    """
    mount = CameraMount() if mount is None else mount
    position = np.asarray(position_ned, np.float64)
    attitude = np.asarray(ned_from_body, np.float64)
    camera_ned = position + attitude @ mount.lever_arm_m
    out = np.zeros((*np.broadcast_shapes(position.shape[:-1], attitude.shape[:-2]), 4, 4))
    out[..., :3, :3] = ENU_FROM_NED @ attitude @ mount.body_from_camera
    out[..., :3, 3] = camera_ned @ ENU_FROM_NED.T
    out[..., 3, 3] = 1.0
    return out
