"""MAVLink decoding with pymavlink: real bytes over loop://, a pseudo-terminal and a corrupted recording."""

from __future__ import annotations

import os

import numpy as np
import pytest
import serial

from olsplat_nodes.telemetry import POSE_MESSAGES, MavlinkDecoder, MavlinkReader
from tests.helpers import wait_for

from .samples import corrupt, encoder, mixed_frames, pack


def msgbufs(messages) -> list[bytes]:
    return [bytes(m.get_msgbuf()) for m in messages]


def decode_in_chunks(data: bytes, seed: int, max_chunk: int = 64, keep=None) -> tuple[list, MavlinkDecoder]:
    rng = np.random.default_rng(seed)
    decoder = MavlinkDecoder(keep=keep)
    out, i = [], 0
    while i < len(data):
        n = int(rng.integers(1, max_chunk + 1))
        out += decoder.feed(data[i : i + n])
        i += n
    return out + decoder.flush(), decoder


def test_v1_and_v2_frames_decode_with_their_fields():
    mav = encoder()
    v2 = pack(mav, mav.attitude_encode(1234, 0.1, -0.2, 3.0, 0, 0, 0))
    v1 = pack(mav, mav.local_position_ned_encode(1240, 1.5, -2.5, -30.0, 0, 0, 0), v1=True)
    assert v2[0] == 0xFD and v1[0] == 0xFE
    decoder = MavlinkDecoder()
    attitude, local = decoder.feed(v2 + v1)
    assert attitude.get_type() == "ATTITUDE" and attitude.time_boot_ms == 1234
    assert attitude.roll == pytest.approx(0.1) and attitude.yaw == pytest.approx(3.0)
    assert local.get_type() == "LOCAL_POSITION_NED" and (local.x, local.y, local.z) == pytest.approx((1.5, -2.5, -30.0))
    assert decoder.stats["messages"] == decoder.stats["kept"] == 2
    assert decoder.stats["garbage_bytes"] == decoder.stats["resyncs"] == 0


def test_only_kept_types_are_returned_but_all_are_verified():
    frames = mixed_frames(60)
    out, decoder = decode_in_chunks(b"".join(frames), seed=1, keep=POSE_MESSAGES)
    assert {m.get_type() for m in out} == set(POSE_MESSAGES)
    assert decoder.stats["messages"] == 60 and decoder.stats["kept"] == 50  # 10 heartbeats dropped


def test_byte_by_byte_and_bulk_feeding_agree():
    data = corrupt(mixed_frames(80, seed=3), seed=3).data
    bulk = MavlinkDecoder(keep=None)
    expected = msgbufs(bulk.feed(data) + bulk.flush())
    single = MavlinkDecoder(keep=None)
    out = []
    for b in data:
        out += single.feed(bytes([b]))
    assert msgbufs(out + single.flush()) == expected
    assert single.stats == bulk.stats


@pytest.mark.parametrize("seed", range(6))
def test_corrupted_recording_keeps_every_intact_message(seed):
    recording = corrupt(mixed_frames(400, seed=seed), seed=seed)
    out, decoder = decode_in_chunks(recording.data, seed=seed, keep=None)  # never raises
    stats = decoder.stats
    assert msgbufs(out) == recording.intact
    rejected = stats["bad_crc"] + stats["bad_frames"] + stats["unknown_frames"]
    assert rejected >= recording.damaged_with_marker > 0
    assert stats["bad_crc"] > 0 and stats["resyncs"] > 0
    # Every byte is in a decoded frame or counted as garbage.
    assert sum(map(len, recording.intact)) + stats["garbage_bytes"] == len(recording.data)
    assert decoder.pending_bytes == 0


def test_pure_noise_never_raises_and_is_all_garbage():
    data = np.random.default_rng(7).integers(0, 256, 50_000, dtype=np.uint8).tobytes()
    out, decoder = decode_in_chunks(data, seed=7, max_chunk=512, keep=None)
    assert out == []
    assert decoder.stats["garbage_bytes"] == len(data)


def test_truncated_frame_does_not_swallow_the_next_one():
    """pymavlink alone drops the bytes the truncated frame claims; the decoder rescans them."""
    mav = encoder()
    first = pack(mav, mav.global_position_int_encode(10, 1, 2, 3, 4, 5, 6, 7, 8))
    second = pack(mav, mav.attitude_encode(20, 0.1, 0.2, 0.3, 0, 0, 0))
    data = first[:12] + second + second
    decoder = MavlinkDecoder()
    assert msgbufs(decoder.feed(data)) == [second, second]
    assert decoder.stats["bad_crc"] + decoder.stats["bad_frames"] >= 1


def test_message_outside_the_dialect_is_unverifiable_and_rescanned():
    """AHRS2 is an ArduPilot message: 'all' verifies it, 'common' cannot (no CRC seed)."""
    mav = encoder()
    ahrs2 = pack(mav, mav.ahrs2_encode(0.1, 0.2, 0.3, 100.0, 1, 2))
    attitude = pack(mav, mav.attitude_encode(20, 0.1, 0.2, 0.3, 0, 0, 0))
    everything = MavlinkDecoder(keep=None, dialect="all")
    assert [m.get_type() for m in everything.feed(ahrs2 + attitude)] == ["AHRS2", "ATTITUDE"]
    common = MavlinkDecoder(keep=None, dialect="common")
    assert [m.get_type() for m in common.feed(ahrs2 + attitude)] == ["ATTITUDE"]
    assert common.stats["unknown_frames"] >= 1 and common.stats["garbage_bytes"] == len(ahrs2)


def test_unknown_dialect_is_a_value_error():
    with pytest.raises(ValueError, match="dialect='nonsense'"):
        MavlinkDecoder(dialect="nonsense")


def read_until(reader: MavlinkReader, count: int, timeout_s: float = 3.0) -> list:
    got = []
    wait_for(lambda: len(got) >= count, timeout_s, step=lambda: got.extend(reader.read(0.05)))
    return got


def test_loop_url_carries_real_mavlink_bytes():
    frames = mixed_frames(120, seed=11)
    recording = corrupt(frames, seed=11)
    clock_values = iter(range(10**9, 2 * 10**9, 1000))
    with MavlinkReader("loop://", 115200, keep=None, clock=lambda: next(clock_values)) as reader:
        assert reader.open()
        got = []
        for i in range(0, len(recording.data), 1024):  # the loop's buffer holds 4096 bytes
            reader.port.write(recording.data[i : i + 1024])
            got += reader.read(0.05)
        got += read_until(reader, len(recording.intact) - len(got))
        assert reader.stats["connected"] == 1
    assert msgbufs(r.message for r in got) == recording.intact
    stamps = [r.host_ns for r in got]
    assert stamps == sorted(stamps) and stamps[0] >= 10**9
    assert reader.port is None  # closed by the context manager


def test_pseudo_terminal_carries_real_mavlink_bytes():
    frames = mixed_frames(60, seed=12)
    master, slave = os.openpty()
    try:
        with MavlinkReader(os.ttyname(slave), 57600) as reader:
            assert reader.open()  # raw mode is set before any byte is written
            data = b"\x00\xff\x11\x13\r\n" + b"".join(frames)  # bytes a cooked tty would alter
            for i in range(0, len(data), 256):
                os.write(master, data[i : i + 256])
            got = read_until(reader, 50)
        assert [bytes(r.message.get_msgbuf()) for r in got] == [f for f in frames if MavlinkDecoder().feed(f)]
        assert reader.stats["garbage_bytes"] == 6
    finally:
        os.close(master)
        os.close(slave)


def test_port_that_goes_away_is_reopened(tmp_path):
    """A device name that points to one pty, then (after an unplug) to another, like a udev link."""
    link = tmp_path / "ttyFC"
    mav = encoder()
    first = pack(mav, mav.attitude_encode(10, 0.1, 0.2, 0.3, 0, 0, 0))
    second = pack(mav, mav.attitude_encode(20, 0.1, 0.2, 0.3, 0, 0, 0))
    master1, slave1 = os.openpty()
    master2, slave2 = os.openpty()
    try:
        link.symlink_to(os.ttyname(slave1))
        with MavlinkReader(str(link), 57600, reopen_interval_s=0.0) as reader:
            assert reader.open()
            os.write(master1, first)
            assert [r.message.time_boot_ms for r in read_until(reader, 1)] == [10]
            os.close(master1)  # unplugged
            master1 = None
            assert wait_for(lambda: reader.read(0.05) == [] and reader.stats["port_errors"] >= 1)
            assert reader.stats["connected"] == 0 and reader.last_error
            link.unlink()
            link.symlink_to(os.ttyname(slave2))  # replugged
            assert wait_for(reader.open)
            os.write(master2, second)
            assert [r.message.time_boot_ms for r in read_until(reader, 1)] == [20]
            assert reader.stats["opens"] == 2
    finally:
        for fd in (master1, slave1, master2, slave2):
            if fd is not None:
                os.close(fd)


def test_absent_device_is_counted_not_raised(tmp_path):
    with MavlinkReader(str(tmp_path / "no-such-tty"), 57600, reopen_interval_s=0.0) as reader:
        assert reader.read(0.0) == [] and reader.read(0.0) == []
        assert reader.stats["port_errors"] == 2 and reader.stats["connected"] == 0
        assert "no-such-tty" in reader.last_error


def test_bad_url_is_a_configuration_error():
    with pytest.raises(ValueError):
        MavlinkReader("nonsense-scheme://x").open()
    with pytest.raises(ValueError, match="url=''"):
        MavlinkReader("")


def test_serial_module_is_pyserial():
    assert serial.__version__ == "3.5"
