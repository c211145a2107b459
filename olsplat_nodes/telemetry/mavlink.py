"""MAVLink v1/v2 from a byte stream (pymavlink's parser) and from a serial port (pyserial).

``MavlinkDecoder`` feeds bytes to pymavlink's ``MAVLink.parse_char`` (robust mode), which frames
messages and verifies their CRC (with the per-message CRC_EXTRA seed). On top of it the decoder
adds one rule, so that an intact message is never lost behind a corrupted one: when a frame is
rejected (bad CRC, bad length, bad flags) or its message id is not in the dialect (its CRC cannot
be verified, so it is as likely to be noise), the parser is rewound to the byte after that
frame's start marker and scanning goes on from there. pymavlink alone would drop the whole
claimed length, and with it the start of the next message whenever a truncated frame or a
false start marker in a garbage run claims more bytes than it has.

Accounting: every byte fed ends up in a decoded frame, in ``garbage_bytes``, or still pending
(``pending_bytes``, a frame not complete yet); ``flush`` ends a recorded stream by treating what
is pending as garbage and decoding what follows it.

``MavlinkReader`` opens ``serial.serial_for_url(url, baudrate)`` (a device such as
``/dev/ttyACM0``, ``loop://``, a pseudo-terminal name, ``socket://``, ``rfc2217://``), reads
what has arrived, stamps each chunk with the host clock at its reception and survives a port
that is absent or goes away: the error is logged and counted, the port is reopened later.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import serial

log = logging.getLogger(__name__)

# The messages olsplat uses: attitude, position (local or global), and time for clock sync.
POSE_MESSAGES = ("ATTITUDE", "ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYSTEM_TIME")


def load_dialect(name: str = "all"):
    """pymavlink's generated MAVLink 2 module (it also decodes MAVLink 1 frames).

    "all" knows the messages of every dialect (ArduPilot's and PX4's included), so that their
    checksums can be verified; "common" is the smaller standard set.
    """
    try:
        dialect = importlib.import_module(f"pymavlink.dialects.v20.{name}")
    except ImportError as exc:
        if not isinstance(exc, ModuleNotFoundError) or exc.name != f"pymavlink.dialects.v20.{name}":
            raise ImportError(
                "pymavlink is needed for flight-controller telemetry: pip install pymavlink==2.4.50"
            ) from exc
        raise ValueError(
            f"unknown MAVLink dialect, got dialect={name!r} (e.g. 'all', 'common', 'ardupilotmega')"
        ) from None
    if dialect.MAVLINK_IGNORE_CRC:
        log.warning("MAV_IGNORE_CRC is set in the environment: pymavlink does not verify checksums")
    return dialect


class MavlinkDecoder:
    """Bytes -> verified MAVLink messages (pymavlink message objects) of the kept types."""

    def __init__(self, keep: Iterable[str] | None = POSE_MESSAGES, dialect: str = "all"):
        self.keep = None if keep is None else frozenset(keep)  # None: keep every verified message
        self._dialect = load_dialect(dialect)
        self._mav = self._dialect.MAVLink(None)
        self._mav.robust_parsing = True  # report bad data as MAVLink_bad_data instead of raising
        self._in_sync = True
        self.stats = {
            "bytes": 0,  # bytes fed
            "messages": 0,  # frames with a verified checksum (kept or not)
            "kept": 0,
            "garbage_bytes": 0,  # bytes in no verified frame
            "bad_crc": 0,  # frames rejected for their checksum
            "bad_frames": 0,  # frames rejected for another reason (length, flags)
            "unknown_frames": 0,  # frames with an id outside the dialect: unverifiable, rescanned
            "resyncs": 0,  # times sync was lost (garbage or a rejected frame after a good frame)
        }

    @property
    def pending_bytes(self) -> int:
        return self._mav.buf_len()

    def feed(self, data: bytes) -> list:
        """Decode what ``data`` completes; never raises on malformed input."""
        self.stats["bytes"] += len(data)
        out = []
        # Small slices keep pymavlink's buffer short, so that a rewind copies little.
        for i in range(0, len(data), 512):
            out += self._drain(bytes(data[i : i + 512]))
        return out

    def flush(self) -> list:
        """End of stream: the pending incomplete frame is garbage; decode what followed it."""
        out = []
        while self._mav.buf_len() > 0:
            self._rewind_past_start()
            out += self._drain(b"")
        return out

    def _drain(self, data: bytes) -> list:
        out = []
        message = self._mav.parse_char(data)
        while message is not None:
            if self._accept(message):
                out.append(message)
            message = self._mav.parse_char(b"")
        return out

    def _accept(self, message) -> bool:
        name = message.get_type()
        if name == "BAD_DATA" and message.reason == "Bad prefix":
            self._lose_sync()
            self.stats["garbage_bytes"] += len(message.data)
            return False
        if name == "BAD_DATA" or name.startswith("UNKNOWN_"):
            self._lose_sync()
            key = (
                "unknown_frames"
                if name.startswith("UNKNOWN_")
                else "bad_crc"
                if "CRC" in message.reason
                else "bad_frames"
            )
            self.stats[key] += 1
            self._rewind(bytes(message.get_msgbuf()))
            return False
        self._in_sync = True
        self.stats["messages"] += 1
        if self.keep is not None and name not in self.keep:
            return False
        self.stats["kept"] += 1
        return True

    def _lose_sync(self) -> None:
        if self._in_sync:
            self.stats["resyncs"] += 1
        self._in_sync = False

    def _rewind(self, frame: bytes) -> None:
        """Scan a rejected frame again from the byte after its start marker."""
        self.stats["garbage_bytes"] += 1
        self._set_buffer(frame[1:] + bytes(self._mav.buf[self._mav.buf_index :]))

    def _rewind_past_start(self) -> None:
        self._lose_sync()
        self.stats["garbage_bytes"] += 1
        self._set_buffer(bytes(self._mav.buf[self._mav.buf_index + 1 :]))

    def _set_buffer(self, data: bytes) -> None:
        # pymavlink keeps its input in buf[buf_index:] and the length of the frame it waits for
        # in expected_length; the reset value is the one it uses after every frame.
        self._mav.buf = bytearray(data)
        self._mav.buf_index = 0
        self._mav.expected_length = self._dialect.HEADER_LEN_V1 + 2


@dataclass(frozen=True)
class Received:
    """A kept message and the host time at which the chunk holding it was read."""

    host_ns: int  # from the reader's clock
    message: object  # pymavlink MAVLink_message (fields as attributes, get_type() gives the name)


class MavlinkReader:
    """Reads MAVLink from a pyserial URL; reconnects after errors instead of raising.

    ``clock`` stamps receptions (nanoseconds); it must be the clock the camera frames use.
    A URL with an unknown scheme raises ValueError (a configuration error); a port that cannot
    be opened or fails while reading is logged, counted and retried every
    ``reopen_interval_s``.
    """

    def __init__(
        self,
        url: str,
        baudrate: int = 57600,
        *,
        keep: Iterable[str] | None = POSE_MESSAGES,
        dialect: str = "all",
        clock: Callable[[], int] = time.monotonic_ns,
        reopen_interval_s: float = 1.0,
    ):
        if not url:
            raise ValueError(f"a serial port or pyserial URL is needed, got url={url!r}")
        self.url, self.baudrate = url, int(baudrate)
        self.clock = clock
        self.reopen_interval_s = reopen_interval_s
        self.decoder = MavlinkDecoder(keep, dialect)
        self.port: serial.SerialBase | None = None
        self.last_error = ""
        self._next_open = 0.0
        self.port_stats = {"opens": 0, "port_errors": 0}

    @property
    def stats(self) -> dict[str, int]:
        return {**self.decoder.stats, **self.port_stats, "connected": int(self.port is not None)}

    def open(self) -> bool:
        """Open the port if it is closed and a retry is due; True when it is open."""
        if self.port is not None:
            return True
        if time.monotonic() < self._next_open:
            return False
        try:
            self.port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.05)
        except serial.SerialException as exc:  # absent device, busy port: try again later
            self._fail(exc)
            return False
        self.port_stats["opens"] += 1
        self.last_error = ""
        log.info("telemetry port %s open at %d baud", self.url, self.baudrate)
        return True

    def read(self, timeout_s: float = 0.05) -> list[Received]:
        """Messages completed by what has arrived, waiting up to ``timeout_s`` for the first byte."""
        if not self.open():
            return []
        port = self.port
        assert port is not None  # open() returned True
        try:
            if port.timeout != timeout_s:
                port.timeout = timeout_s
            data = port.read(1)  # blocks until a byte arrives or the timeout
            if data and port.in_waiting:
                data += port.read(port.in_waiting)
        except (serial.SerialException, OSError) as exc:  # unplugged mid-flight
            self._fail(exc)
            return []
        host_ns = self.clock()
        return [Received(host_ns, m) for m in self.decoder.feed(data)]

    def _fail(self, exc: Exception) -> None:
        if self.port is not None:
            try:
                self.port.close()
            except (serial.SerialException, OSError):
                pass
            self.port = None
        self.port_stats["port_errors"] += 1
        message = f"telemetry port {self.url}: {exc}"
        if message != self.last_error:
            log.warning("%s (retrying every %.1f s)", message, self.reopen_interval_s)
        self.last_error = message
        self._next_open = time.monotonic() + self.reopen_interval_s

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
            self.port = None

    def __enter__(self) -> MavlinkReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
