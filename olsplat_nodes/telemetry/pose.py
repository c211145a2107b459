"""Autopilot state + camera mount -> ``world_from_camera`` (pure functions, no I/O).

Frames (stated once, used everywhere in this package):
- **NED**: the autopilot's local frame, metres, +x north, +y east, +z down. LOCAL_POSITION_NED
  is already in it (origin: the autopilot's EKF origin); GLOBAL_POSITION_INT is converted into
  it around a reference point (``geodetic_to_ned``).
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

# WGS-84 ellipsoid.
WGS84_A = 6378137.0  # semi-major axis, metres
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared

# Columns: NED axes written in ENU (x_enu = y_ned, y_enu = x_ned, z_enu = -z_ned).
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
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


def geodetic_to_ned(lat_deg, lon_deg, alt_m, reference) -> np.ndarray:
    """WGS-84 latitude/longitude (degrees) and altitude (metres) -> [..., 3] NED metres.

    ``reference`` is (lat_deg, lon_deg, alt_m) of the NED origin. Exact through ECEF, no
    flat-earth approximation. Altitudes may be above mean sea level (MAVLink ``alt``) as long
    as the reference uses the same datum: the geoid offset is constant over a flight area.
    """
    lat0, lon0, alt0 = (float(v) for v in reference)
    ecef = _ecef(lat_deg, lon_deg, alt_m)
    ecef0 = _ecef(lat0, lon0, alt0)
    phi, lam = np.radians(lat0), np.radians(lon0)
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    ned_from_ecef = np.array([[-sp * cl, -sp * sl, cp], [-sl, cl, 0.0], [-cp * cl, -cp * sl, -sp]])
    return (ecef - ecef0) @ ned_from_ecef.T


def _ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """[..., 3] Earth-centred Earth-fixed metres."""
    phi = np.radians(np.asarray(lat_deg, np.float64))
    lam = np.radians(np.asarray(lon_deg, np.float64))
    h = np.asarray(alt_m, np.float64)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(phi) ** 2)  # prime vertical radius
    return np.stack(
        [
            (n + h) * np.cos(phi) * np.cos(lam),
            (n + h) * np.cos(phi) * np.sin(lam),
            (n * (1.0 - WGS84_E2) + h) * np.sin(phi),
        ],
        -1,
    )


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
