"""Camera poses from a bag: a REP-105 tf chain at 50 Hz against the analytic motion, /tf out of
order with duplicate stamps, repeated /tf_static, Odometry or PoseStamped with a mount."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.sources.rosbag import read_bag

from .bags import (
    LINK_FROM_OPTICAL,
    T0,
    S,
    camera_info,
    compressed,
    jpeg_bytes,
    odometry,
    patches,
    pose_stamped,
    rigid,
    tf_message,
    transform,
    write_bag,
)

JPEG = jpeg_bytes(patches(60, 80))
BASE_FROM_LINK = rigid(0.1, (0.2, 0.0, -0.1), pitch_rad=1.2)  # a camera tilted down on the body


def map_from_odom(t: float) -> np.ndarray:
    return rigid(0.02 * t, (0.5 * t, 0.1 * t, 0.0))


def odom_from_base(t: float) -> np.ndarray:
    return rigid(0.4 * t, (3.0 * t, 2.0 * np.sin(t), 40.0 + 0.5 * t))


def ns(t: float) -> int:
    return T0 + int(round(t * S))


def camera_messages(times, frame_id="camera_optical_frame"):
    out = [("/camera/camera_info", ns(times[0]), camera_info(ns(times[0]), 80, 60, frame_id=frame_id))]
    return out + [("/camera/image/compressed", ns(t), compressed(ns(t), JPEG, frame_id=frame_id)) for t in times]


def static_mount():
    return tf_message(
        transform(T0, "base_link", "camera_link", BASE_FROM_LINK),
        transform(T0, "camera_link", "camera_optical_frame", LINK_FROM_OPTICAL),
    )


def assert_poses(frames, times, expected, dt=0.02):
    """Poses against ``expected(t)``; positions within the linear interpolation bound of
    2 sin(t) between samples ``dt`` seconds apart (|f''| dt^2 / 8)."""
    assert [f.stamp_ns for f in frames] == [ns(t) for t in times]
    for frame, t in zip(frames, times, strict=True):
        pose, want = frame.camera.world_from_camera, expected(t)
        np.testing.assert_allclose(pose[:3, :3], want[:3, :3], atol=1e-9)  # constant-rate yaws: slerp is exact
        np.testing.assert_allclose(pose[:3, 3], want[:3, 3], atol=2.0 * dt**2 / 8 + 1e-9)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_rep105_chain_at_50_hz_gives_the_analytic_pose_between_samples(tmp_path, storage):
    messages = [("/tf_static", T0, static_mount())]
    for k in range(151):  # 3 s at 50 Hz
        t = k * 0.02
        messages.append(("/tf", ns(t), tf_message(
            transform(ns(t), "map", "odom", map_from_odom(t)), transform(ns(t), "odom", "base_link", odom_from_base(t))
        )))  # fmt: skip
    times = [0.337 + 0.25 * k for k in range(8)]  # between samples
    bag = write_bag(tmp_path / "chain", messages + camera_messages(times), storage=storage)
    frames = list(read_bag(bag))
    assert_poses(frames, times, lambda t: map_from_odom(t) @ odom_from_base(t) @ BASE_FROM_LINK @ LINK_FROM_OPTICAL)


def test_tf_out_of_order_with_duplicate_stamps_keeps_the_last_logged(tmp_path):
    rng = np.random.default_rng(1)
    samples = [k * 0.1 for k in range(21)]
    messages = []
    for k, t in enumerate(rng.permutation(samples)):  # logged out of stamp order, each stamp twice
        wrong = rigid(2.0, (99.0, 0.0, 0.0))
        messages.append(("/tf", T0 + 2 * k, tf_message(transform(ns(t), "map", "camera_link", wrong))))
        right = rigid(0.3 * t, (t, 0, 5))
        messages.append(("/tf", T0 + 2 * k + 1, tf_message(transform(ns(t), "map", "camera_link", right))))
    messages.append(
        ("/tf_static", ns(1.0), tf_message(transform(0, "camera_link", "camera_optical_frame", LINK_FROM_OPTICAL)))
    )
    times = [0.25, 0.5, 1.05, 1.9]
    frames = list(read_bag(write_bag(tmp_path / "shuffled", messages + camera_messages(times))))
    np.testing.assert_allclose(
        [f.camera.world_from_camera for f in frames], [rigid(0.3 * t, (t, 0, 5)) @ LINK_FROM_OPTICAL for t in times],
        atol=1e-9,
    )  # fmt: skip


def test_repeated_tf_static_merges_by_child_the_later_winning(tmp_path):
    wrong = tf_message(
        transform(T0, "base_link", "camera_link", BASE_FROM_LINK),
        transform(T0, "camera_link", "camera_optical_frame", rigid(1.0)),
    )
    right = tf_message(transform(T0, "camera_link", "camera_optical_frame", LINK_FROM_OPTICAL))
    messages = [("/tf_static", T0, wrong), ("/tf_static", T0 + 1, right)]
    messages += [("/tf", ns(t), tf_message(transform(ns(t), "map", "base_link", odom_from_base(t)))) for t in (0, 1, 2)]
    (frame,) = read_bag(write_bag(tmp_path / "static", messages + camera_messages([1.0])))
    np.testing.assert_allclose(
        frame.camera.world_from_camera, odom_from_base(1.0) @ BASE_FROM_LINK @ LINK_FROM_OPTICAL, atol=1e-9
    )


def odometry_messages(rate_hz=20.0):
    return [("/odom", ns(k / rate_hz), odometry(ns(k / rate_hz), odom_from_base(k / rate_hz))) for k in range(61)]


def test_odometry_and_a_mount(tmp_path):
    mount = BASE_FROM_LINK @ LINK_FROM_OPTICAL
    times = [0.33, 1.01, 2.77]
    bag = write_bag(tmp_path / "odom", odometry_messages() + camera_messages(times))  # no tf at all
    frames = list(read_bag(bag, {"bag_mount": mount.reshape(-1).tolist()}))
    assert_poses(frames, times, lambda t: odom_from_base(t) @ mount, dt=0.05)


def test_odometry_and_the_static_tf_from_its_child_frame(tmp_path):
    times = [0.5, 1.5]
    messages = [("/tf_static", T0, static_mount()), *odometry_messages(), *camera_messages(times)]
    frames = list(read_bag(write_bag(tmp_path / "odom_tf", messages)))  # no /tf: the only pose topic is used
    assert_poses(frames, times, lambda t: odom_from_base(t) @ BASE_FROM_LINK @ LINK_FROM_OPTICAL, dt=0.05)


def test_a_named_pose_topic_wins_over_tf_and_link_axes(tmp_path):
    times = [0.4, 0.8]
    messages = [
        ("/mavros/local_position/pose", ns(k * 0.1), pose_stamped(ns(k * 0.1), odom_from_base(k * 0.1)))
        for k in range(20)
    ]
    messages += [("/tf", ns(t), tf_message(transform(ns(t), "map", "camera_link", rigid(1.0)))) for t in (0, 1)]
    messages += camera_messages(times, frame_id="camera_link")
    bag = write_bag(tmp_path / "mavros", messages)
    frames = list(
        read_bag(
            bag, {"bag_pose_topic": "/mavros/local_position/pose", "bag_mount": BASE_FROM_LINK.reshape(-1).tolist()}
        )
    )
    assert_poses(frames, times, lambda t: odom_from_base(t) @ BASE_FROM_LINK, dt=0.1)
    frames = list(
        read_bag(bag, {"bag_camera_axes": "link", "bag_tolerance_s": 1.0})
    )  # the tf chain to camera_link, FLU axes turned to optical
    assert_poses(frames, times, lambda t: rigid(1.0) @ LINK_FROM_OPTICAL)
