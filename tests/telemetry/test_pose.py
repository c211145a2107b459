"""Autopilot attitude + position + mount -> world_from_camera: hand-computed cases and references."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.rotmat import Matrix3

from olsplat_nodes.scene import Camera, intrinsics, look_at
from olsplat_nodes.scene.rotations import quat_to_rotmat
from olsplat_nodes.telemetry import (
    CameraMount,
    euler_to_quat,
    euler_to_rotmat,
    geodetic_to_ned,
    mount_rotation,
    world_from_camera,
)

S = np.sqrt(0.5)


def test_level_flight_nose_north_nadir_camera():
    """Image right = east, image down = south (nose at the top), optical axis = down."""
    pose = world_from_camera([10.0, 20.0, -30.0], euler_to_rotmat(0.0, 0.0, 0.0))
    expected = np.array([[1, 0, 0, 20], [0, -1, 0, 10], [0, 0, -1, 30], [0, 0, 0, 1]], float)
    np.testing.assert_allclose(pose, expected, atol=1e-12)


def test_yaw_90_nose_east():
    """Nose east: image right = south, image down = west."""
    pose = world_from_camera([0.0, 0.0, -5.0], euler_to_rotmat(0.0, 0.0, np.pi / 2))
    np.testing.assert_allclose(pose[:3, :3], [[0, -1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [0, 0, 5], atol=1e-12)


def test_mount_pitched_down_45_degrees():
    """Level, nose north, camera 45 degrees below the horizon: it looks north-and-down."""
    mount = CameraMount.from_angles(0.0, -45.0, 0.0)
    pose = world_from_camera([0.0, 0.0, 0.0], euler_to_rotmat(0.0, 0.0, 0.0), mount)
    np.testing.assert_allclose(pose[:3, 2], [0, S, -S], atol=1e-12)  # optical axis
    np.testing.assert_allclose(pose[:3, 0], [1, 0, 0], atol=1e-12)  # image right = east
    np.testing.assert_allclose(pose[:3, 1], [0, -S, -S], atol=1e-12)  # image down


def test_forward_camera_with_zero_angles():
    pose = world_from_camera([0.0, 0.0, 0.0], euler_to_rotmat(0.0, 0.0, 0.0), CameraMount.from_angles(0, 0, 0))
    np.testing.assert_allclose(
        pose[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12
    )  # looks north, image down = down


def test_lever_arm_turns_with_the_vehicle():
    """Camera 0.2 m ahead of and 0.1 m below the reported point, vehicle yawed 90 degrees (nose east)."""
    mount = CameraMount.from_angles(lever_arm_m=(0.2, 0.0, 0.1))
    pose = world_from_camera([1.0, 2.0, -10.0], euler_to_rotmat(0.0, 0.0, np.pi / 2), mount)
    np.testing.assert_allclose(pose[:3, 3], [2.0 + 0.2, 1.0, 10.0 - 0.1], atol=1e-12)
    # Pitched up 90 degrees (nose up), the forward arm points up.
    pose = world_from_camera(
        [0.0, 0.0, 0.0], euler_to_rotmat(0.0, np.pi / 2, 0.0), CameraMount(lever_arm_m=(0.2, 0.0, 0.0))
    )
    np.testing.assert_allclose(pose[:3, 3], [0, 0, 0.2], atol=1e-12)


def test_mount_matrix_equals_angles():
    nadir = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # OpenCV axes in body FRD: right, back, down
    np.testing.assert_allclose(mount_rotation(), nadir, atol=1e-12)
    np.testing.assert_allclose(CameraMount(nadir).body_from_camera, CameraMount().body_from_camera, atol=1e-12)


def test_euler_matches_pymavlink_rotmat_and_quaternion():
    """pymavlink's own Euler -> DCM (rotmat.Matrix3.from_euler) is the reference."""
    rng = np.random.default_rng(0)
    for roll, pitch, yaw in rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], (20, 3)):
        m = Matrix3()
        m.from_euler(roll, pitch, yaw)
        reference = [[m.a.x, m.a.y, m.a.z], [m.b.x, m.b.y, m.b.z], [m.c.x, m.c.y, m.c.z]]
        np.testing.assert_allclose(euler_to_rotmat(roll, pitch, yaw), reference, atol=1e-12)
        np.testing.assert_allclose(quat_to_rotmat(euler_to_quat(roll, pitch, yaw)), reference, atol=1e-12)


@pytest.mark.parametrize("yaw_deg, mount_pitch_deg", [(0, -90), (30, -60), (-120, -45), (200, -10), (75, -89)])
def test_against_look_at(yaw_deg, mount_pitch_deg):
    """A level vehicle with an unrolled camera is ``look_at`` along the optical axis, world z up."""
    yaw, theta = np.radians(yaw_deg), np.radians(mount_pitch_deg)
    position = np.array([3.0, -4.0, -25.0])
    pose = world_from_camera(
        position, euler_to_rotmat(0.0, 0.0, yaw), CameraMount.from_angles(0.0, mount_pitch_deg, 0.0)
    )
    eye = np.array([position[1], position[0], -position[2]])
    axis = np.array([np.cos(theta) * np.sin(yaw), np.cos(theta) * np.cos(yaw), np.sin(theta)])  # ENU
    nose = np.array([np.sin(yaw), np.cos(yaw), 0.0])
    up = nose if mount_pitch_deg == -90 else np.array([0.0, 0.0, 1.0])  # nadir: the nose is at the top
    np.testing.assert_allclose(pose, look_at(eye, eye + axis, up), atol=1e-9)
    Camera("fc", 64, 48, intrinsics(50, 50, 32, 24), pose)  # a valid rigid pose for scene.Camera


def test_nadir_camera_projects_a_point_ahead_to_the_top_of_the_image():
    """The end-to-end meaning: a ground point north of a north-facing drone appears above the centre."""
    pose = world_from_camera([0.0, 0.0, -20.0], euler_to_rotmat(0.0, 0.0, 0.0))
    camera = Camera("fc", 100, 100, intrinsics(50, 50, 50, 50), pose)
    ahead_east = np.array([3.0, 5.0, 0.0, 1.0])  # ENU: east 3, north 5, on the ground
    x, y, z = (camera.camera_from_world @ ahead_east)[:3]
    assert z == pytest.approx(20.0)
    u, v = 50 + 50 * x / z, 50 + 50 * y / z
    assert u > 50 and v < 50  # right of and above the centre


def test_vectorised_over_samples():
    rng = np.random.default_rng(1)
    angles = rng.uniform(-1, 1, (7, 3))
    positions = rng.normal(size=(7, 3))
    mount = CameraMount.from_angles(5, -70, 3, lever_arm_m=(0.1, -0.05, 0.2))
    batch = world_from_camera(positions, euler_to_rotmat(*angles.T), mount)
    for i in range(7):
        np.testing.assert_allclose(
            batch[i], world_from_camera(positions[i], euler_to_rotmat(*angles[i]), mount), atol=1e-12
        )


def test_geodetic_to_ned_small_offsets():
    """Meridian and prime-vertical radii of WGS-84 (plus the height) give the metres per degree."""
    a, e2 = 6378137.0, 6.69437999014e-3
    for lat in (0.0, 45.0, -33.4):
        phi = np.radians(lat)
        meridian = a * (1 - e2) / (1 - e2 * np.sin(phi) ** 2) ** 1.5 + 100.0
        prime = a / np.sqrt(1 - e2 * np.sin(phi) ** 2) + 100.0
        d = 1e-4  # degrees: about 11 m
        ref = (lat, 7.0, 100.0)
        north = geodetic_to_ned(lat + d, 7.0, 100.0, ref)
        east = geodetic_to_ned(lat, 7.0 + d, 100.0, ref)
        up = geodetic_to_ned(lat, 7.0, 110.0, ref)
        assert north[0] == pytest.approx(meridian * np.radians(d), rel=1e-7) and abs(north[1]) < 1e-6
        assert east[1] == pytest.approx(prime * np.cos(phi) * np.radians(d), rel=1e-7)
        np.testing.assert_allclose(up, [0, 0, -10.0], atol=1e-6)
    np.testing.assert_allclose(
        geodetic_to_ned([45.0, 45.0], [7.0, 7.0], [100.0, 100.0], (45.0, 7.0, 100.0)), np.zeros((2, 3)), atol=1e-6
    )


def test_bad_mounts_are_value_errors():
    with pytest.raises(ValueError, match="proper rotation"):
        CameraMount(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="3x3"):
        CameraMount(np.eye(2))
    with pytest.raises(ValueError, match="lever_arm_m"):
        CameraMount(lever_arm_m=(0.0, 1.0))
