"""FlightControllerPoses end to end: encoded telemetry -> serial -> samples -> poses for frame stamps."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.telemetry import MavlinkDecoder, TelemetryConfig, euler_to_rotmat, geodetic_to_ned, world_from_camera
from olsplat_nodes.telemetry.source import FlightControllerPoses
from tests.helpers import wait_for

from .samples import Flight, encoder, flight_messages, pack

MS = 1_000_000
OFFSET_NS = 123_456_000_000  # host clock - autopilot boot clock


def feed(source: FlightControllerPoses, messages, delays_ms) -> None:
    decoder = MavlinkDecoder()
    for (boot_ms, frame), delay in zip(messages, delays_ms, strict=False):  # extra delays unused
        for message in decoder.feed(frame):
            source.add_message(message, boot_ms * MS + OFFSET_NS + int(delay * MS))


def expected_pose(flight: Flight, t_s: float, mount) -> np.ndarray:
    return world_from_camera(flight.position(t_s), euler_to_rotmat(*flight.attitude(t_s)), mount)


def test_poses_for_frames_follow_the_flight():
    flight = Flight()
    config = TelemetryConfig(mount_rpy_deg=(0, -70, 5), lever_arm_m=(0.15, 0.0, 0.1))
    source = FlightControllerPoses(config)
    messages = flight_messages(flight, 3.0, boot_ms0=5000)
    rng = np.random.default_rng(0)
    delays = rng.uniform(0.0, 15.0, len(messages))
    delays[::25] = 0.0  # some messages arrive without delay: the offset estimate is exact
    feed(source, messages, delays)
    assert source.boot_clock.offset_ns == OFFSET_NS
    checked = 0
    for t_s in np.arange(0.013, 2.99, 1 / 30):  # 30 Hz camera, stamps between samples
        stamp = OFFSET_NS + 5000 * MS + int(round(t_s * 1e9))
        match = source.lookup(stamp, now_ns=stamp)
        assert match.status == "ok", match.reason
        np.testing.assert_allclose(match.world_from_camera, expected_pose(flight, t_s, config.mount()), atol=1e-5)
        checked += 1
    assert source.stats["matched"] == checked > 80
    assert source.stats["attitude_samples"] == 151 and source.stats["position_samples"] == 31


def test_frames_outside_the_telemetry_wait_then_get_rejected():
    flight = Flight()
    source = FlightControllerPoses(TelemetryConfig(max_wait_s=0.5))
    messages = flight_messages(flight, 1.0, boot_ms0=5000)
    before = OFFSET_NS + 4000 * MS
    assert source.lookup(before, now_ns=before).reason == "clock:no_offset"  # nothing received yet
    feed(source, messages, [0.0] * len(messages))
    assert source.lookup(before, now_ns=before).reason == "attitude:no_sample_before"
    after = OFFSET_NS + 6500 * MS
    assert source.lookup(after, now_ns=after).status == "wait"
    assert source.lookup(after, now_ns=after + 600 * MS).reason == "attitude:no_sample_after"
    assert source.stats["rejected"] == 2 and source.stats["matched"] == 0


def test_global_position_is_converted_around_the_reference():
    reference = (47.3977419, 8.5455938, 488.0)
    source = FlightControllerPoses(TelemetryConfig(position="global", reference=reference))
    mav = encoder()
    decoder = MavlinkDecoder()
    north_east = [(47.3977419 + 1e-4 * k, 8.5455938 + 2e-4 * k, 488.0 + 5 * k) for k in range(3)]
    for k, (lat, lon, alt) in enumerate(north_east):
        ms = 1000 + 100 * k
        frames = pack(
            mav,
            mav.global_position_int_encode(ms, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), 0, 0, 0, 0, 0),
        )
        frames += pack(mav, mav.attitude_encode(ms, 0.0, 0.0, 0.0, 0, 0, 0))
        for message in decoder.feed(frames):
            source.add_message(message, ms * MS)
    match = source.lookup(1150 * MS, now_ns=1150 * MS)
    assert match.status == "ok"
    ned = (geodetic_to_ned(*north_east[1], reference) + geodetic_to_ned(*north_east[2], reference)) / 2
    np.testing.assert_allclose(match.world_from_camera[:3, 3], [ned[1], ned[0], -ned[2]], atol=1e-3)
    assert ned[0] > 10 and ned[1] > 20 and ned[2] < -5  # moved north, east and up


def test_first_fix_becomes_the_origin_and_no_fix_is_ignored():
    source = FlightControllerPoses(TelemetryConfig(position="global"))
    mav = encoder()
    decoder = MavlinkDecoder()
    data = pack(mav, mav.global_position_int_encode(900, 0, 0, 0, 0, 0, 0, 0, 0))  # before the first fix
    data += pack(mav, mav.global_position_int_encode(1000, 473977419, 85455938, 488000, 0, 0, 0, 0, 0))
    for message in decoder.feed(data):
        source.add_message(message, 0)
    assert source.reference == pytest.approx((47.3977419, 8.5455938, 488.0))
    assert source.stats["invalid_samples"] == 1 and source.stats["position_samples"] == 1


def test_reboot_clears_the_samples():
    flight = Flight()
    source = FlightControllerPoses(TelemetryConfig())
    feed(source, flight_messages(flight, 1.0, boot_ms0=60_000), [0.0] * 70)
    assert len(source.buffer) > 0
    feed(source, flight_messages(flight, 0.1, boot_ms0=200), [0.0] * 10)
    assert source.stats["reboots"] == 1
    assert source.stats["stale_samples"] == 0  # the old samples were cleared, not compared with


def test_attitude_quaternion_source():
    source = FlightControllerPoses(TelemetryConfig(attitude="ATTITUDE_QUATERNION"))
    mav = encoder()
    decoder = MavlinkDecoder()
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)  # yaw 90 degrees
    data = b"".join(
        pack(mav, m)
        for ms in (1000, 1100)
        for m in (
            mav.attitude_quaternion_encode(ms, c, 0.0, 0.0, s, 0, 0, 0, [0, 0, 0, 0]),
            mav.attitude_encode(ms, 0.0, 0.0, 0.0, 0, 0, 0),  # ignored in this mode
            mav.local_position_ned_encode(ms, 0.0, 0.0, -5.0, 0, 0, 0),
        )
    )
    for message in decoder.feed(data):
        source.add_message(message, message.time_boot_ms * MS)
    match = source.lookup(1050 * MS, now_ns=1050 * MS)
    np.testing.assert_allclose(match.world_from_camera[:3, :3], [[0, -1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-9)


def test_serial_loop_end_to_end():
    flight = Flight()
    host_now = [0]
    with FlightControllerPoses(TelemetryConfig(url="loop://", baudrate=921600), clock=lambda: host_now[0]) as source:
        assert source.reader.open()
        added = 0
        for boot_ms, frame in flight_messages(flight, 1.0, boot_ms0=5000):
            host_now[0] = boot_ms * MS + OFFSET_NS
            source.reader.port.write(frame)
            added += wait_for(lambda: source.poll(0.05), timeout_s=2.0)
        assert added == 51 + 11
        stamp = OFFSET_NS + 5500 * MS
        match = source.lookup(stamp, now_ns=stamp)
        assert match.status == "ok"
        np.testing.assert_allclose(match.world_from_camera, expected_pose(flight, 0.5, source.mount), atol=1e-5)
        assert source.stats["connected"] == 1 and source.stats["garbage_bytes"] == 0
    assert source.reader.port is None


def test_config_from_launch_params():
    config = TelemetryConfig.from_params(
        {"url": "/dev/ttyACM0", "mount_rpy_deg": [0, -90, 0], "lever_arm_m": [0.1, 0, 0.05], "position": "global"}
    )
    assert config.lever_arm_m == (0.1, 0.0, 0.05)
    matrix = TelemetryConfig(mount_matrix=[0, -1, 0, 1, 0, 0, 0, 0, 1]).mount()
    np.testing.assert_allclose(matrix.body_from_camera, TelemetryConfig().mount().body_from_camera, atol=1e-12)
    with pytest.raises(ValueError, match="unknown telemetry parameters \\['baud'\\]"):
        TelemetryConfig.from_params({"baud": 57600})
    with pytest.raises(ValueError, match="position='gps'"):
        TelemetryConfig(position="gps")
    with pytest.raises(ValueError, match="proper rotation"):
        TelemetryConfig(mount_matrix=[1, 0, 0, 0, 1, 0, 0, 0, -1])
