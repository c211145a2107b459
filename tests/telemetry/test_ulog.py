"""PX4 flight logs: ULog files written here (ulog_files.py, checked against pyulog's reader and
writer), poses at the camera triggers against the analytic flight, photo matching, bad logs."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from pyulog import ULog

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.scene.rotations import quat_to_rotmat
from olsplat_nodes.telemetry import CameraMount, euler_to_rotmat, geodetic_to_ned, world_from_camera
from olsplat_nodes.telemetry.ulog import capture_poses, match_photos, read_flight_log

from .ulog_files import (
    START,
    TRIGGERS_S,
    UTC_BOOT_US,
    flight_topics,
    geodetic,
    stamps_us,
    truth,
    ulog_bytes,
    write_ulog,
)


def angle_between(a, b) -> float:
    """Radians between two rotation matrices."""
    return float(np.arccos(np.clip((np.trace(np.asarray(a).T @ b) - 1.0) / 2.0, -1.0, 1.0)))


def test_the_written_logs_are_ulog_as_pyulog_reads_and_writes_it(tmp_path):
    path = write_ulog(tmp_path / "flight.ulg", flight_topics())
    ulog = ULog(str(path), None, True)
    assert not ulog.file_corruption
    assert sorted(d.name for d in ulog.data_list) == ["camera_capture", "vehicle_attitude", "vehicle_global_position"]
    capture = ulog.get_dataset("camera_capture").data
    np.testing.assert_array_equal(capture["timestamp"], stamps_us(TRIGGERS_S))
    assert capture["q[0]"].dtype == np.float32 and "_padding0[0]" not in capture  # flattened, padding dropped
    ulog.write_ulog(str(tmp_path / "again.ulg"))  # pyulog's own writer gives back the same bytes
    assert (tmp_path / "again.ulg").read_bytes() == path.read_bytes()


@pytest.mark.parametrize("mount_rpy", [(0.0, -90.0, 0.0), (0.0, -60.0, 10.0)])
@pytest.mark.parametrize("position", ["global", "local"])
def test_poses_at_the_triggers_follow_the_logged_attitude(tmp_path, caplog, position, mount_rpy):
    path = write_ulog(tmp_path / "flight.ulg", flight_topics(position=position))
    with caplog.at_level(logging.WARNING):
        flight = read_flight_log(path)
    assert flight.problems == () and not caplog.records
    mount = CameraMount.from_angles(*mount_rpy)
    poses = capture_poses(flight)
    assert [p.seq for p in poses] == list(range(len(TRIGGERS_S)))
    assert {(p.attitude_source, p.position_source) for p in poses} == {
        ("vehicle_attitude", f"vehicle_{position}_position")
    }
    ned, roll, pitch, yaw = truth(np.array(TRIGGERS_S))
    for i, pose in enumerate(poses):
        got = pose.world_from_camera(START, mount)
        want = world_from_camera(ned[i], euler_to_rotmat(roll[i], pitch[i], yaw[i]), mount)
        assert angle_between(got[:3, :3], want[:3, :3]) < 1e-3  # slerp between 50 Hz samples
        np.testing.assert_allclose(got[:3, 3], want[:3, 3], atol=1e-3)  # linear motion, 5 Hz samples
        # PX4's own copy in camera_capture is 0.3 s old here: its attitude is visibly off
        stale = world_from_camera(ned[i], quat_to_rotmat(flight.captures.quats[i]), mount)
        assert angle_between(stale[:3, :3], want[:3, :3]) > 0.05


def test_a_nadir_camera_heads_with_the_nose_and_tilts_with_the_roll(tmp_path):
    poses = capture_poses(read_flight_log(write_ulog(tmp_path / "f.ulg", flight_topics())))
    _, roll, pitch, yaw = truth(np.array(TRIGGERS_S))
    for i, pose in enumerate(poses):
        world_from_camera_ = pose.world_from_camera(START, CameraMount())  # nadir, nose at the image top
        image_up = -world_from_camera_[:3, 1]  # ENU
        heading = np.degrees(np.arctan2(image_up[0], image_up[1])) % 360.0
        assert heading == pytest.approx(np.degrees(yaw[i]) % 360.0, abs=0.05)  # not the travel's 45 degrees
        assert abs(heading - 45.0) > 40.0
        tilt = np.degrees(np.arccos(-world_from_camera_[2, 2]))  # optical axis from straight down
        assert tilt == pytest.approx(np.degrees(np.arccos(np.cos(roll[i]) * np.cos(pitch[i]))), abs=0.05)


def test_gaps_fall_back_to_the_capture_then_refuse(tmp_path):
    topics = flight_topics(triggers_s=(1.37, 3.41, 12.99), capture_q=False)
    keep = (topics["vehicle_attitude"]["timestamp_sample"] < stamps_us(3.0)) | (
        topics["vehicle_attitude"]["timestamp_sample"] > stamps_us(3.9)
    )
    topics["vehicle_attitude"] = {k: v[keep] for k, v in topics["vehicle_attitude"].items()}
    poses = capture_poses(read_flight_log(write_ulog(tmp_path / "f.ulg", topics)), tolerance_s=0.3)
    assert poses[0].attitude_source == "vehicle_attitude" and poses[0].reason == ""
    assert poses[1].quat_ned_from_body is None and poses[1].reason == "attitude:gap"  # 0.9 s without a sample
    assert poses[1].geodetic is not None  # the position series is fine
    assert poses[2].reason == "attitude:no_sample_after, position:no_sample_after"  # 12.99 s: after the last
    assert poses[2].position_source == "camera_capture"  # PX4's copy stands in (its q is zero here)
    assert poses[2].world_from_camera(START, CameraMount()) is None
    topics = flight_topics(triggers_s=(3.41,), stale_s=0.0)
    topics["vehicle_attitude"] = {k: v[keep] for k, v in topics["vehicle_attitude"].items()}
    (pose,) = capture_poses(read_flight_log(write_ulog(tmp_path / "g.ulg", topics)), tolerance_s=0.3)
    assert pose.attitude_source == "camera_capture" and pose.reason == "attitude:gap"
    _, roll, pitch, yaw = truth(3.41)
    assert (
        angle_between(
            pose.world_from_camera(START, CameraMount())[:3, :3],
            world_from_camera(np.zeros(3), euler_to_rotmat(roll, pitch, yaw))[:3, :3],
        )
        < 1e-6
    )


def test_matching_by_order_when_the_counts_agree():
    match = match_photos([None] * 6, stamps_us(TRIGGERS_S))
    assert match.method == "order" and match.capture_of_photo.tolist() == list(range(6)) and match.unmatched == 0
    # a camera clock 2 h off with 1 s resolution: order still, the stamps agree with it
    photos_ns = [(int(u) // 1_000_000 + 7200) * 10**9 for u in UTC_BOOT_US + stamps_us(TRIGGERS_S)]
    assert match_photos(photos_ns, UTC_BOOT_US + stamps_us(TRIGGERS_S)).method == "order"


def test_matching_by_time_with_a_dropped_photo_and_a_stray_one():
    rng = np.random.default_rng(3)
    captures_us = UTC_BOOT_US + stamps_us(np.arange(20) * 2.0 + rng.uniform(0, 0.4, 20))
    offset_s = 3600.0 + 37.3  # the camera's clock: an hour's zone error and 37 s off
    photos_ns = [int(c * 1000 + offset_s * 1e9 + rng.uniform(-0.2, 0.2) * 1e9) for c in captures_us]
    del photos_ns[7]  # a trigger without a photo
    photos_ns.insert(12, photos_ns[11] + 1_000_000_000)  # a photo without a trigger, between two
    photos_ns[3] = None  # and one without a stamp
    want = [*range(7), *range(8, 13), -1, *range(13, 20)]
    want[3] = -1
    # as many photos as triggers, but the stamps say the pairs are not one-to-one
    match = match_photos(photos_ns, captures_us)
    assert match.method == "time" and match.capture_of_photo.tolist() == want
    assert match.offset_s == pytest.approx(offset_s, abs=0.2) and match.tolerance_s > 0.75
    assert (match.matched, match.unmatched) == (18, 2)
    del photos_ns[16], want[16]  # 19 photos for 20 triggers
    match = match_photos(photos_ns, captures_us)
    assert match.method == "time" and match.capture_of_photo.tolist() == want


def test_regular_triggers_take_the_offset_nearest_zero():
    """Photos 2..7 of 10 evenly spaced triggers fit offsets of 0.3 s +- any whole interval: the
    offset nearest zero wins."""
    captures_us = UTC_BOOT_US + np.arange(10) * 2_000_000
    photos_ns = [int(c * 1000 + 300_000_000) for c in captures_us[2:8]]
    match = match_photos(photos_ns, captures_us)
    assert match.capture_of_photo.tolist() == list(range(2, 8)) and match.offset_s == pytest.approx(0.3)


def test_bad_logs_are_one_line_naming_the_file(tmp_path, caplog):
    (tmp_path / "garbage.ulg").write_bytes(b"\x89PNG not a log" * 10)
    with pytest.raises(SceneFormatError, match=r"garbage\.ulg: not a readable ULog file \(Invalid file format"):
        read_flight_log(tmp_path / "garbage.ulg")
    with pytest.raises(SceneFormatError, match=r"absent\.ulg: no such ULog file"):
        read_flight_log(tmp_path / "absent.ulg")
    no_capture = {k: v for k, v in flight_topics().items() if k != "camera_capture"}
    with pytest.raises(SceneFormatError, match=r"nocam\.ulg: no camera_capture message"):
        read_flight_log(write_ulog(tmp_path / "nocam.ulg", no_capture))
    no_attitude = {k: v for k, v in flight_topics(capture_q=False).items() if k != "vehicle_attitude"}
    with pytest.raises(
        SceneFormatError, match=r"noatt\.ulg: no vehicle_attitude message and camera_capture\.q is empty"
    ):
        read_flight_log(write_ulog(tmp_path / "noatt.ulg", no_attitude))


def test_damage_is_one_warning_naming_the_file_and_what_was_read_is_used(tmp_path, caplog):
    data = ulog_bytes(flight_topics())
    cases = {
        "cut.ulg": (data[:-7], "cut short: a message runs past the end of the file"),
        "damaged.ulg": (data[: len(data) // 2] + bytes(12) + data[len(data) // 2 :], "damaged:"),
    }
    for name, (content, problem) in cases.items():
        (tmp_path / name).write_bytes(content)
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            flight = read_flight_log(tmp_path / name)
        assert [r.getMessage() for r in caplog.records] == [f"{tmp_path / name}: {flight.problems[0]}"]
        assert flight.problems[0].startswith(problem) and len(flight.captures.stamps_us) >= 3
    caplog.clear()
    no_attitude = {k: v for k, v in flight_topics(stale_s=0.0).items() if k != "vehicle_attitude"}
    with caplog.at_level(logging.WARNING):
        flight = read_flight_log(write_ulog(tmp_path / "noatt.ulg", no_attitude))
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'noatt.ulg'}: no vehicle_attitude message: attitudes from camera_capture.q (copied when PX4 "
        "handled each trigger)"
    ]
    assert {p.attitude_source for p in capture_poses(flight)} == {"camera_capture"}


def test_failed_captures_and_invalid_fixes_are_not_used(tmp_path):
    topics = flight_topics(results=[1, 0, 1, -1, 1, 1])
    topics["vehicle_global_position"]["lat_lon_valid"][:] = 0
    flight = read_flight_log(write_ulog(tmp_path / "f.ulg", topics))
    assert flight.captures.ok.tolist() == [True, False, True, True, True, True]  # -1: no feedback, not a failure
    assert flight.position is None and {p.position_source for p in capture_poses(flight)} == {"camera_capture"}
    lla = geodetic(truth(np.array(TRIGGERS_S) - 0.3)[0])
    np.testing.assert_allclose([p.geodetic for p in capture_poses(flight)], lla, atol=1e-6)
    assert geodetic_to_ned(*lla[0], START) == pytest.approx(truth(TRIGGERS_S[0] - 0.3)[0], abs=1e-3)
