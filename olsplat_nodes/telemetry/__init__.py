"""Flight-controller telemetry: MAVLink over serial -> world-from-camera poses matched to frames.

Frames and rules are in ``pose.py`` (NED/FRD in, ENU world and OpenCV camera out) and
``matching.py`` (clock offset, interpolation, rejection); README.md beside this file sums up.
"""

from .config import TelemetryConfig
from .matching import BootClock, PoseBuffer, PoseMatch, bracket, interpolate_attitude, interpolate_position, slerp
from .mavlink import POSE_MESSAGES, MavlinkDecoder, MavlinkReader, Received, load_dialect
from .pose import CameraMount, euler_to_quat, euler_to_rotmat, geodetic_to_ned, mount_rotation, world_from_camera
from .source import FlightControllerPoses

__all__ = [
    "POSE_MESSAGES",
    "BootClock",
    "CameraMount",
    "FlightControllerPoses",
    "MavlinkDecoder",
    "MavlinkReader",
    "PoseBuffer",
    "PoseMatch",
    "Received",
    "TelemetryConfig",
    "bracket",
    "euler_to_quat",
    "euler_to_rotmat",
    "geodetic_to_ned",
    "interpolate_attitude",
    "interpolate_position",
    "load_dialect",
    "mount_rotation",
    "slerp",
    "world_from_camera",
]
