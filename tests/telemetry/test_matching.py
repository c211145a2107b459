"""Timestamp matching: bracketing, interpolation, slerp, rejection counts and the boot clock."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.scene.rotations import quat_to_rotmat
from olsplat_nodes.telemetry import (
    BootClock,
    PoseBuffer,
    bracket,
    euler_to_quat,
    interpolate_attitude,
    interpolate_position,
    slerp,
)

MS = 1_000_000
TOL = 100 * MS


def yaw_of(quat) -> float:
    r = quat_to_rotmat(quat)
    return float(np.arctan2(r[1, 0], r[0, 0]))


def test_bracket_cases():
    stamps = np.array([0, 50, 100, 400]) * MS
    assert bracket([], 10, TOL)[:2] == ("wait", "no_samples")
    assert bracket(stamps, 25 * MS, TOL) == ("ok", "", 0, 1, 0.5)
    assert bracket(stamps, 50 * MS, TOL) == ("ok", "", 1, 1, 0.0)  # exact hit
    assert bracket(stamps, -1, TOL)[:2] == ("rejected", "no_sample_before")
    assert bracket(stamps, 401 * MS, TOL)[:2] == ("wait", "no_sample_after")
    assert bracket(stamps, 250 * MS, TOL)[:2] == ("rejected", "gap")  # 150 ms on both sides
    assert bracket(stamps, 320 * MS, TOL)[:2] == ("rejected", "gap")  # 80 ms after, 220 ms before
    assert bracket(stamps, 190 * MS, 100 * MS)[:2] == ("rejected", "gap")
    assert bracket([0, 200 * MS], 100 * MS, TOL)[0] == "ok"  # 100 ms on each side: within


def test_linear_position_interpolation():
    stamps = np.array([1000, 1100]) * MS
    positions = [[0.0, 0.0, -10.0], [2.0, -4.0, -12.0]]
    status, _, p = interpolate_position(stamps, positions, 1025 * MS, TOL)
    assert status == "ok"
    np.testing.assert_allclose(p, [0.5, -1.0, -10.5])


def test_slerp_yaw_and_wraparound():
    q0, q1 = euler_to_quat(0, 0, 0), euler_to_quat(0, 0, np.pi / 2)
    assert yaw_of(slerp(q0, q1, 0.5)) == pytest.approx(np.pi / 4)
    assert yaw_of(slerp(q0, q1, 0.25)) == pytest.approx(np.pi / 8)
    # 179 deg -> -179 deg passes through 180, not through 0.
    mid = slerp(euler_to_quat(0, 0, np.radians(179)), euler_to_quat(0, 0, np.radians(-179)), 0.5)
    assert abs(yaw_of(mid)) == pytest.approx(np.pi)
    # q and -q: the same rotation, no detour.
    np.testing.assert_allclose(quat_to_rotmat(slerp(q1, -q1, 0.3)), quat_to_rotmat(q1), atol=1e-12)


def test_slerp_constant_angular_rate():
    rng = np.random.default_rng(0)
    for _ in range(10):
        q0, q1 = (q / np.linalg.norm(q) for q in rng.normal(size=(2, 4)))
        total = 2 * np.arccos(min(1.0, abs(q0 @ q1)))
        for s in (0.1, 0.5, 0.9):
            q = slerp(q0, q1, s)
            assert np.linalg.norm(q) == pytest.approx(1.0)
            assert 2 * np.arccos(min(1.0, abs(q0 @ q))) == pytest.approx(s * total, abs=1e-9)


def test_attitude_interpolation_within_tolerance():
    stamps = np.array([0, 40, 80]) * MS
    quats = [euler_to_quat(0.0, 0.0, y) for y in (0.0, 0.2, 0.4)]
    status, _, q = interpolate_attitude(stamps, quats, 60 * MS, TOL)
    assert status == "ok" and yaw_of(q) == pytest.approx(0.3)


def test_buffer_matches_waits_and_rejects_with_counts():
    buf = PoseBuffer(tolerance_s=0.1, maxlen=100)
    for k in range(0, 11):  # attitude at 50 Hz over 0..200 ms
        buf.add_attitude(20 * k * MS, euler_to_quat(0.0, 0.0, 0.01 * k))
    for k in range(0, 3):  # position at 10 Hz: 0, 100, 200 ms
        buf.add_position(100 * k * MS, [k, 0.0, 0.0])
    ok = buf.lookup(150 * MS)
    assert (
        ok.status == "ok"
        and ok.position_ned == pytest.approx([1.5, 0, 0])
        and yaw_of(ok.quat_ned_from_body) == pytest.approx(0.075)
    )
    assert buf.lookup(250 * MS).status == "wait"  # a later sample may still come: not counted
    assert buf.stats["rejected"] == 0
    late = buf.lookup(250 * MS, final=True)
    assert late.status == "rejected" and late.reason == "attitude:no_sample_after"
    early = buf.lookup(-5 * MS)
    assert early.status == "rejected" and early.reason == "attitude:no_sample_before"
    buf.add_position(500 * MS, [5.0, 0, 0])  # a 300 ms gap in position (telemetry dropout)
    for k in range(11, 26):
        buf.add_attitude(20 * k * MS, euler_to_quat(0.0, 0.0, 0.01 * k))
    gap = buf.lookup(350 * MS)
    assert gap.status == "rejected" and gap.reason == "position:gap"
    assert buf.stats == {
        "matched": 1,
        "rejected": 3,
        "stale_samples": 0,
        "rejected_attitude_no_sample_after": 1,
        "rejected_attitude_no_sample_before": 1,
        "rejected_position_gap": 1,
    }


def test_buffer_is_bounded_and_drops_stale_samples():
    buf = PoseBuffer(tolerance_s=0.1, maxlen=5)
    for k in range(20):
        buf.add_attitude(k * 10 * MS, euler_to_quat(0, 0, 0))
        buf.add_position(k * 10 * MS, [0, 0, 0])
    assert len(buf) == 5
    assert buf.lookup(100 * MS).reason == "attitude:no_sample_before"  # evicted
    assert buf.lookup(175 * MS).status == "ok"
    assert not buf.add_position(190 * MS, [1, 1, 1]) and not buf.add_position(10 * MS, [1, 1, 1])
    assert buf.stats["stale_samples"] == 2


def test_buffer_rejects_bad_configuration():
    with pytest.raises(ValueError, match="tolerance_s=0"):
        PoseBuffer(tolerance_s=0)
    with pytest.raises(ValueError, match="maxlen=1"):
        PoseBuffer(maxlen=1)


def test_boot_clock_takes_the_least_delayed_message():
    clock = BootClock(window_s=10.0)
    true_offset = 7_000_000_000
    assert clock.offset_ns is None and clock.to_autopilot_ns(123) is None
    delays = [12, 3, 40, 0.5, 9, 25] * 10  # ms
    for k, delay in enumerate(delays):
        boot_ms = 1000 + 20 * k
        clock.observe(boot_ms, boot_ms * MS + true_offset + int(delay * MS))
    assert clock.offset_ns == true_offset + MS // 2
    assert clock.to_autopilot_ns(true_offset + 5000 * MS + MS // 2) == 5000 * MS


def test_boot_clock_window_follows_drift():
    clock = BootClock(window_s=1.0)
    offset = 0
    for k in range(500):  # 10 s at 50 Hz; the autopilot's crystal runs 100 ppm slow
        boot_ms = 20 * k
        offset = int(boot_ms * MS * 1e-4)
        clock.observe(boot_ms, boot_ms * MS + offset + (k % 3) * MS)
    assert abs(clock.offset_ns - offset) <= 100_000  # within 0.1 ms (the drift over the 1 s window)


def test_boot_clock_reboot_resets():
    clock = BootClock()
    assert not clock.observe(600_000, 10**12)
    assert clock.observe(500, 10**12 + 5 * 10**9)  # boot time back to 0.5 s: rebooted
    assert clock.stats["reboots"] == 1
    assert clock.offset_ns == 10**12 + 5 * 10**9 - 500 * MS
    assert not clock.observe(480, 10**12 + 5 * 10**9)  # small steps back between message types are normal


def test_boot_clock_from_system_time():
    clock = BootClock(mode="system_time")
    clock.observe(1000, 123)  # host receive times do not matter in this mode
    assert clock.offset_ns is None
    clock.observe_system_time(0, 1000)  # no GPS time yet
    assert clock.offset_ns is None
    clock.observe_system_time(1_700_000_000_000_000, 2000)
    assert clock.offset_ns == 1_700_000_000_000_000_000 - 2000 * MS
    with pytest.raises(ValueError, match="mode='gps'"):
        BootClock(mode="gps")
