"""Real MAVLink bytes made with pymavlink's encoder, a synthetic flight and a corrupted recording."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from olsplat_nodes.telemetry import load_dialect

DIALECT = load_dialect("all")


def encoder(system: int = 1, component: int = 1):
    return DIALECT.MAVLink(None, srcSystem=system, srcComponent=component)


def pack(mav, message, v1: bool = False) -> bytes:
    frame = bytes(message.pack(mav, force_mavlink1=v1))
    mav.seq = (mav.seq + 1) % 256  # what MAVLink.send does after packing
    return frame


def mixed_frames(n: int, seed: int = 0) -> list[bytes]:
    """n frames of kept and other types, MAVLink 1 and 2, with random field values."""
    rng = np.random.default_rng(seed)
    mav = encoder()
    frames = []
    for i in range(n):
        boot_ms = 1000 + 20 * i
        kind = i % 6
        if kind == 0:
            msg = mav.attitude_encode(boot_ms, *rng.uniform(-3, 3, 6))
        elif kind == 1:
            msg = mav.local_position_ned_encode(boot_ms, *rng.uniform(-100, 100, 6))
        elif kind == 2:
            msg = mav.global_position_int_encode(
                boot_ms, *rng.integers(-900_000_000, 900_000_000, 2), *rng.integers(0, 500_000, 2), 10, -20, 30, 4500
            )
        elif kind == 3:
            msg = mav.system_time_encode(1_700_000_000_000_000 + 20_000 * i, boot_ms)
        elif kind == 4:
            msg = mav.heartbeat_encode(2, 3, 81, 4, 4)  # not kept, still verified
        else:
            msg = mav.attitude_quaternion_encode(boot_ms, *(rng.normal(size=4) / 2), 0.1, 0.2, 0.3, [0, 0, 0, 0])
        frames.append(pack(mav, msg, v1=bool(rng.integers(2))))
    return frames


@dataclass
class Recording:
    data: bytes
    intact: list[bytes]  # frames that appear unmodified, in order
    damaged_with_marker: int  # damaged frames whose start marker survived (each must be rejected)
    garbage_runs: int


def corrupt(frames: list[bytes], seed: int = 0, tail_intact: int = 12) -> Recording:
    """Bit flips, truncations and garbage runs (with false start markers) between frames.

    The last ``tail_intact`` frames are left intact so that every false start before them
    is complete (and rejected) by the end of the recording.
    """
    rng = np.random.default_rng(seed)
    out, intact, damaged, runs = bytearray(), [], 0, 0
    for i, frame in enumerate(frames):
        op = (
            "intact"
            if i >= len(frames) - tail_intact
            else rng.choice(["intact", "intact", "flip", "truncate", "garbage"])
        )
        if op == "garbage":
            run = rng.integers(0, 256, rng.integers(1, 120), dtype=np.uint8)
            run[rng.random(len(run)) < 0.1] = rng.choice([0xFD, 0xFE])  # false start markers
            out += run.tobytes()
            runs += 1
            op = "intact"
        if op == "intact":
            out += frame
            intact.append(frame)
        elif op == "flip":
            bad = bytearray(frame)
            for bit in rng.choice(len(bad) * 8, rng.integers(1, 4), replace=False):
                bad[bit // 8] ^= 1 << (bit % 8)
            out += bad
            damaged += bad[0] in (0xFD, 0xFE)
        else:  # truncated: the link dropped the end of the frame
            out += frame[: rng.integers(1, len(frame))]
            damaged += 1
    return Recording(bytes(out), intact, damaged, runs)


@dataclass
class Flight:
    """A vehicle flying a straight line at constant speed while yawing at a constant rate.

    Linear interpolation of the position and slerp of the attitude are exact for it.
    """

    start_ned: tuple = (5.0, -3.0, -40.0)
    velocity_ned: tuple = (2.0, 1.0, -0.5)  # m/s
    yaw0: float = 0.3  # rad
    yaw_rate: float = 0.4  # rad/s
    roll: float = 0.05
    pitch: float = -0.08

    def position(self, t_s):
        return np.asarray(self.start_ned) + np.multiply.outer(t_s, self.velocity_ned)

    def attitude(self, t_s):
        return self.roll, self.pitch, self.yaw0 + self.yaw_rate * t_s


def flight_messages(
    flight: Flight, duration_s: float, attitude_hz: float = 50.0, position_hz: float = 10.0, boot_ms0: int = 5000
):
    """(time_boot_ms, frame bytes) of ATTITUDE and LOCAL_POSITION_NED, in time order."""
    mav = encoder()
    out = []
    for k in range(int(duration_s * attitude_hz) + 1):
        ms = round(k * 1000 / attitude_hz)
        roll, pitch, yaw = flight.attitude(ms / 1000)
        yaw = (yaw + np.pi) % (2 * np.pi) - np.pi  # MAVLink sends yaw in [-pi, pi]
        out.append(
            (boot_ms0 + ms, 0, pack(mav, mav.attitude_encode(boot_ms0 + ms, roll, pitch, yaw, 0, 0, flight.yaw_rate)))
        )
    for k in range(int(duration_s * position_hz) + 1):
        ms = round(k * 1000 / position_hz)
        x, y, z = flight.position(ms / 1000)
        out.append(
            (boot_ms0 + ms, 1, pack(mav, mav.local_position_ned_encode(boot_ms0 + ms, x, y, z, *flight.velocity_ned)))
        )
    out.sort(key=lambda item: item[:2])
    return [(ms, frame) for ms, _, frame in out]
