"""ULog files written here, byte by byte, after the format's specification (PX4 docs, "ULog File
Format"): a 16-byte header, the flag bits, one format message per topic, then add-logged and data
messages, each message ``<HB`` (payload size, type). ``test_ulog.py`` checks that pyulog reads them
back and that pyulog's own writer reproduces them.

Topic layouts follow PX4 v1.14's (fields sorted by size, with ``_padding`` at the end).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

_CODES = {"uint64_t": "Q", "int64_t": "q", "uint32_t": "I", "int32_t": "i", "double": "d", "float": "f"}
_CODES |= {"uint8_t": "B", "int8_t": "b", "bool": "?", "uint16_t": "H"}

CAMERA_CAPTURE = [
    ("uint64_t", "timestamp"),
    ("uint64_t", "timestamp_utc"),
    ("double", "lat"),
    ("double", "lon"),
    ("uint32_t", "seq"),
    ("float", "alt"),
    ("float", "ground_distance"),
    ("float[4]", "q"),
    ("int8_t", "result"),
    ("uint8_t[3]", "_padding0"),
]
VEHICLE_ATTITUDE = [
    ("uint64_t", "timestamp"),
    ("uint64_t", "timestamp_sample"),
    ("float[4]", "q"),
    ("float[4]", "delta_q_reset"),
    ("uint8_t", "quat_reset_counter"),
    ("uint8_t[7]", "_padding0"),
]
VEHICLE_GLOBAL_POSITION = [
    ("uint64_t", "timestamp"),
    ("uint64_t", "timestamp_sample"),
    ("double", "lat"),
    ("double", "lon"),
    ("float", "alt"),
    ("float", "alt_ellipsoid"),
    ("float", "eph"),
    ("float", "epv"),
    ("uint8_t", "lat_lon_reset_counter"),
    ("uint8_t", "alt_reset_counter"),
    ("bool", "lat_lon_valid"),
    ("bool", "alt_valid"),
    ("uint8_t[4]", "_padding0"),
]
VEHICLE_LOCAL_POSITION = [
    ("uint64_t", "timestamp"),
    ("uint64_t", "timestamp_sample"),
    ("double", "ref_lat"),
    ("double", "ref_lon"),
    ("float", "x"),
    ("float", "y"),
    ("float", "z"),
    ("float", "ref_alt"),
    ("bool", "xy_valid"),
    ("bool", "z_valid"),
    ("bool", "xy_global"),
    ("bool", "z_global"),
]
LAYOUTS = {
    "camera_capture": CAMERA_CAPTURE,
    "vehicle_attitude": VEHICLE_ATTITUDE,
    "vehicle_global_position": VEHICLE_GLOBAL_POSITION,
    "vehicle_local_position": VEHICLE_LOCAL_POSITION,
}


def _message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _field(type_str: str) -> tuple[str, int]:
    """("float[4]") -> ("f", 4); ("double") -> ("d", 0)."""
    base, _, count = type_str.partition("[")
    return _CODES[base], int(count[:-1]) if count else 0


def _logged(layout: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The fields a data message carries: PX4 does not write the padding at the end of a message."""
    end = len(layout)
    while end and layout[end - 1][1].startswith("_padding"):
        end -= 1
    return layout[:end]


def ulog_bytes(topics: dict[str, dict[str, np.ndarray]]) -> bytes:
    """A ULog file: ``{topic: {field: [rows] or [rows, k] values}}``; layouts from ``LAYOUTS``,
    absent fields written as zeros, trailing padding not written; data messages in timestamp order, as PX4 logs."""
    out = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)  # magic, version 1, start timestamp
    out += _message("B", bytes(8) + bytes(8) + bytes(24))  # compat, incompat flags, no appended data
    for name in topics:
        out += _message("F", (name + ":" + "".join(f"{t} {f};" for t, f in LAYOUTS[name])).encode())
    rows = []
    for msg_id, (name, columns) in enumerate(topics.items()):
        out += _message("A", struct.pack("<BH", 0, msg_id) + name.encode())
        n = len(columns["timestamp"])
        for i in range(n):
            values, codes = [], "<H"
            for type_str, field in _logged(LAYOUTS[name]):
                code, count = _field(type_str)
                column = np.asarray(columns.get(field, np.zeros((n, count) if count else n)))
                codes += code * max(count, 1)
                cast = float if code in "fd" else bool if code == "?" else int
                values += [cast(v) for v in np.atleast_1d(column[i])]
            rows.append((int(columns["timestamp"][i]), _message("D", struct.pack(codes, msg_id, *values))))
    rows.sort(key=lambda row: row[0])
    return out + b"".join(data for _, data in rows)


def write_ulog(path: Path, topics: dict[str, dict[str, np.ndarray]]) -> Path:
    path.write_bytes(ulog_bytes(topics))
    return path


# A flight with a known truth: a straight line north-east (travel heading 45 degrees) at 50 m,
# the vehicle yawing at 15 deg/s from 100 degrees, rolling +-20 degrees, pitched 5 degrees down.
START = (47.3977, 8.5456, 488.0)  # lat_deg, lon_deg, alt_m AMSL of the track's NED origin
BOOT_S = 10.0  # the autopilot's clock at t = 0 (µs stamps are (t + BOOT_S) * 1e6)
UTC_BOOT_US = 1_714_557_600_000_000  # 2024-05-01 10:00:00 UTC at boot
TRIGGERS_S = (1.37, 3.41, 5.38, 7.43, 9.36, 11.42)


def truth(t_s):
    """t [...] seconds -> (NED [..., 3] metres, roll, pitch, yaw [...] radians)."""
    t = np.asarray(t_s, np.float64)
    ned = np.stack([3.0 * t, 3.0 * t, np.full_like(t, -50.0)], -1)
    roll = np.radians(20.0) * np.sin(2 * np.pi * t / 5.0)
    return ned, roll, np.full_like(t, np.radians(-5.0)), np.radians(100.0 + 15.0 * t)


def geodetic(ned) -> np.ndarray:
    import pymap3d

    ned = np.asarray(ned, np.float64)
    return np.stack(pymap3d.ned2geodetic(ned[..., 0], ned[..., 1], ned[..., 2], *START), -1)


def stamps_us(t_s) -> np.ndarray:
    return np.round((np.asarray(t_s, np.float64) + BOOT_S) * 1e6).astype(np.int64)


def flight_topics(
    triggers_s=TRIGGERS_S, *, attitude=True, position="global", stale_s=0.3, results=None, capture_q=True
) -> dict:
    """The ULog topics of the truth flight: vehicle_attitude at 50 Hz, positions at 5 Hz
    (``position`` "global", "local" or None) over 0..13 s; camera_capture rows at ``triggers_s``
    whose own q and lat/lon/alt are the truth ``stale_s`` earlier (zero q when not ``capture_q``)."""
    from olsplat_nodes.telemetry import euler_to_quat

    triggers = np.asarray(triggers_s, np.float64)
    ned, roll, pitch, yaw = truth(triggers - stale_s)
    n = len(triggers)
    topics = {
        "camera_capture": {
            "timestamp": stamps_us(triggers),
            "timestamp_utc": UTC_BOOT_US + stamps_us(triggers),
            "seq": np.arange(n),
            **dict(zip(("lat", "lon", "alt"), geodetic(ned).T, strict=True)),
            "ground_distance": np.full(n, 50.0),
            "q": euler_to_quat(roll, pitch, yaw) if capture_q else np.zeros((n, 4)),
            "result": np.ones(n) if results is None else np.asarray(results),
        }
    }
    if attitude:
        t = np.arange(0.0, 13.0, 0.02)
        _, roll, pitch, yaw = truth(t)
        topics["vehicle_attitude"] = {
            "timestamp": stamps_us(t) + 2000,  # published 2 ms after the sample
            "timestamp_sample": stamps_us(t),
            "q": euler_to_quat(roll, pitch, yaw),
        }
    t = np.arange(0.0, 13.0, 0.2)
    ned = truth(t)[0]
    if position == "global":
        lla = geodetic(ned)
        topics["vehicle_global_position"] = {
            "timestamp": stamps_us(t) + 5000,
            "timestamp_sample": stamps_us(t),
            **dict(zip(("lat", "lon", "alt"), lla.T, strict=True)),
            "lat_lon_valid": np.ones(len(t)),
            "alt_valid": np.ones(len(t)),
        }
    elif position == "local":
        topics["vehicle_local_position"] = {
            "timestamp": stamps_us(t),
            **dict(zip(("x", "y", "z"), ned.T, strict=True)),
            "ref_lat": np.full(len(t), START[0]),
            "ref_lon": np.full(len(t), START[1]),
            "ref_alt": np.full(len(t), START[2]),
            **{k: np.ones(len(t)) for k in ("xy_valid", "z_valid", "xy_global", "z_global")},
        }
    return topics
