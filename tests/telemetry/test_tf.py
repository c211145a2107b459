"""TfBuffer: static chains, interpolation between samples, lowest common ancestors, refusals."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.scene.rotations import quat_to_rotmat
from olsplat_nodes.telemetry.tf import (
    LINK_FROM_OPTICAL,
    TfBuffer,
    TfTimeError,
    TfTreeError,
    quat_from_ros,
    transform_matrix,
)

S = 1_000_000_000


def yaw(angle: float) -> np.ndarray:
    """wxyz of a rotation by ``angle`` radians about z."""
    return np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])


def test_optical_constant_is_the_rpy_every_driver_publishes():
    # camera_link -> camera_optical_frame: rpy (-pi/2, 0, -pi/2), ROS xyzw (-0.5, 0.5, -0.5, 0.5)
    np.testing.assert_allclose(
        quat_to_rotmat(quat_from_ros(-0.5, 0.5, -0.5, 0.5)), LINK_FROM_OPTICAL[:3, :3], atol=1e-12
    )
    # optical z (forward) is link x (forward); optical x (right) is link -y (left)
    np.testing.assert_allclose(LINK_FROM_OPTICAL[:3, :3] @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(LINK_FROM_OPTICAL[:3, :3] @ [1, 0, 0], [0, -1, 0])


def test_static_chain_composes_parent_from_child():
    tf = TfBuffer()
    tf.add_static("map", "base", [1, 2, 3], yaw(np.pi / 2))
    tf.add_static("base", "cam", [1, 0, 0], [1, 0, 0, 0])
    pose = tf.lookup("map", "cam", 123, 0)
    np.testing.assert_allclose(pose[:3, 3], [1, 3, 3], atol=1e-12)  # base's x axis points along map y
    np.testing.assert_allclose(tf.lookup("cam", "map", 0, 0), np.linalg.inv(pose), atol=1e-12)
    np.testing.assert_allclose(tf.lookup("cam", "cam", 0, 0), np.eye(4))


def test_repeated_static_merges_the_later_winning():
    tf = TfBuffer()
    tf.add_static("map", "a", [1, 0, 0], [1, 0, 0, 0])
    tf.add_static("map", "b", [0, 1, 0], [1, 0, 0, 0])
    tf.add_static("map", "a", [5, 0, 0], [1, 0, 0, 0])
    np.testing.assert_allclose(tf.lookup("map", "a", 0, 0)[:3, 3], [5, 0, 0])
    np.testing.assert_allclose(tf.lookup("a", "b", 0, 0)[:3, 3], [-5, 1, 0])


def test_midpoint_interpolates_translation_linearly_and_rotation_by_slerp():
    tf = TfBuffer()
    tf.add("map", "body", 2 * S, [2, 0, 0], yaw(1.0))  # out of order on purpose
    tf.add("map", "body", 1 * S, [0, 0, 0], yaw(0.0))
    pose = tf.lookup("map", "body", 1 * S + S // 4, S)
    np.testing.assert_allclose(pose, transform_matrix([0.5, 0, 0], yaw(0.25)), atol=1e-12)


def test_duplicate_stamps_keep_the_sample_added_last():
    tf = TfBuffer()
    tf.add("map", "body", 1 * S, [9, 9, 9], yaw(0.0))
    tf.add("map", "body", 2 * S, [2, 0, 0], yaw(0.0))
    tf.add("map", "body", 1 * S, [0, 0, 0], yaw(0.0))
    assert tf.samples("body").tolist() == [1 * S, 2 * S]
    np.testing.assert_allclose(tf.lookup("map", "body", 1 * S, 0)[:3, 3], [0, 0, 0])


def test_lowest_common_ancestor_when_the_target_is_not_an_ancestor():
    tf = TfBuffer()
    tf.add_static("map", "odom", [10, 0, 0], [1, 0, 0, 0])
    tf.add("odom", "base", 0, [0, 5, 0], yaw(np.pi))
    tf.add("odom", "base", S, [0, 5, 0], yaw(np.pi))
    tf.add_static("map", "tower", [0, 0, 20], [1, 0, 0, 0])
    pose = tf.lookup("tower", "base", S // 2, S)  # tower and base meet at map
    np.testing.assert_allclose(pose[:3, 3], [10, 5, -20], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], quat_to_rotmat(yaw(np.pi)), atol=1e-12)


@pytest.mark.parametrize(
    ("stamp", "reason"),
    [(0, "no_sample_before"), (5 * S, "no_sample_after"), (int(2.5 * S), "gap")],
)
def test_time_failures_name_the_edge(stamp, reason):
    tf = TfBuffer()
    tf.add_static("map", "odom", [0, 0, 0], [1, 0, 0, 0])
    for t in (1, 2, 4):
        tf.add("odom", "base", t * S, [t, 0, 0], [1, 0, 0, 0])
    with pytest.raises(TfTimeError) as caught:
        tf.lookup("map", "base", stamp, S // 2)
    assert str(caught.value) == f"{reason} odom->base" and caught.value.reason == reason


def test_tree_faults_are_refused():
    tf = TfBuffer()
    tf.add_static("map", "cam", [0, 0, 0], [1, 0, 0, 0])
    with pytest.raises(TfTreeError, match="'cam' has two parents, 'map' and 'odom'"):
        tf.add_static("odom", "cam", [0, 0, 0], [1, 0, 0, 0])
    with pytest.raises(TfTreeError, match="both static"):
        tf.add("map", "cam", 0, [0, 0, 0], [1, 0, 0, 0])
    tf.add_static("earth", "gps", [0, 0, 0], [1, 0, 0, 0])
    with pytest.raises(TfTreeError, match="'gps' under root 'earth'; known frames: cam, earth, gps, map"):
        tf.lookup("map", "gps", 0, 0)
    with pytest.raises(TfTreeError, match="no tf frame 'base'; known frames: cam, earth, gps, map"):
        tf.check_chain("map", "base")
    with pytest.raises(ValueError, match="invalid rotation quaternion"):
        quat_from_ros(0, 0, 0, 0)


def test_tree_lines_show_roots_and_edge_kinds():
    tf = TfBuffer()
    tf.add("map", "odom", 0, [0, 0, 0], [1, 0, 0, 0])
    tf.add_static("odom", "base", [0, 0, 0], [1, 0, 0, 0])
    assert tf.tree_lines() == ["map", "  odom (dynamic, 1 stamps)", "    base (static)"]
