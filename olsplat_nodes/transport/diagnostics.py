"""Heartbeats: every node's ``Diagnostics`` PUB connects to the one collector (a SUB that binds,
owned by the query server), which keeps the latest status per node and marks silent nodes STALE."""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping
from typing import Any

import zmq

from olsplat_msgs import DiagnosticStatus, encode

from ._sockets import Closable, attach, make_socket
from .pubsub import Subscriber

log = logging.getLogger(__name__)
DIAGNOSTICS_TOPIC = "diagnostics"
LEVEL_NAMES = {
    DiagnosticStatus.OK: "OK",
    DiagnosticStatus.WARN: "WARN",
    DiagnosticStatus.ERROR: "ERROR",
    DiagnosticStatus.STALE: "STALE",
}


class Diagnostics(Closable):
    """A node's heartbeat publisher. ``beat`` sends at most one status per ``period_s`` (call it
    from the node's loop as often as convenient); ``beat_now`` always sends (state changes,
    shutdown). Levels: ``DiagnosticStatus.OK/WARN/ERROR`` (0/1/2; STALE is the collector's)."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        node_name: str,
        period_s: float = 1.0,
        *,
        topic: str = DIAGNOSTICS_TOPIC,
        hwm: int = 10,
    ):
        self.node_name, self.period_s, self.topic = node_name, float(period_s), topic
        self.socket = make_socket(context, zmq.PUB, sndhwm=hwm)
        try:
            attach(self.socket, [endpoint], bind=False)
        except BaseException:
            self.socket.close(linger=0)
            raise
        self.endpoint = endpoint
        self.seq = 0
        self._last_sent = -float("inf")

    def beat(self, level: int, message: str = "", values: Mapping[str, Any] | None = None) -> bool:
        """Send unless a beat went out less than ``period_s`` ago; True if sent."""
        if time.monotonic() - self._last_sent < self.period_s:
            return False
        return self.beat_now(level, message, values)

    def beat_now(self, level: int, message: str = "", values: Mapping[str, Any] | None = None) -> bool:
        """Send now; True if libzmq took it (PUB drops at the high-water mark)."""
        status = DiagnosticStatus(
            stamp_ns=time.time_ns(),
            seq=self.seq,
            frame_id=self.node_name,
            node=self.node_name,
            level=int(level),
            message=message,
            values=dict(values or {}),
        )
        frames = encode(status, self.topic)
        self.seq += 1
        self._last_sent = time.monotonic()
        try:
            self.socket.send_multipart(frames, flags=zmq.NOBLOCK)
        except zmq.Again:
            return False
        return True


class DiagnosticsCollector(Closable):
    """The collector: a SUB bound to ``endpoint`` (every node's ``Diagnostics`` connects to it).
    ``poll`` takes in what arrived; ``nodes()`` gives the latest status of each node as a dict with
    ``age_s`` (seconds since it arrived), level forced to STALE when older than ``stale_after_s``
    (three missed beats at the default 1 s period) unless its last status said it had finished
    its job (``values["finished"]``: a replay's ingest after the final map) — the shape
    ``StatusReply.nodes`` carries."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        stale_after_s: float = 3.0,
        *,
        topic: str = DIAGNOSTICS_TOPIC,
        hwm: int = 1000,
        max_bytes: int = 1 << 20,
    ):
        self.stale_after_s = float(stale_after_s)
        self.subscriber = Subscriber(context, endpoint, [topic], hwm=hwm, bind=True, max_bytes=max_bytes)
        self.endpoint = self.subscriber.endpoint
        self._latest: dict[str, tuple[DiagnosticStatus, float]] = {}
        self.unexpected = 0  # well-formed messages of another type on the diagnostics topic

    @property
    def stats(self) -> dict[str, int]:
        """The subscriber's counters plus ``unexpected`` (other message types, dropped)."""
        return {**self.subscriber.stats, "unexpected": self.unexpected}

    def poll(self, timeout_ms: float | None = 0) -> int:
        """Take every status queued now (waiting up to ``timeout_ms`` for the first); returns how many."""
        received = self.subscriber.drain(timeout_ms)
        now = time.monotonic()
        for topic, status in received:
            if not isinstance(status, DiagnosticStatus):
                self.unexpected += 1
                log.warning("unexpected %s on %s: dropped", type(status).__name__, topic)
                continue
            self._latest[status.node] = (status, now)
        return len(received)

    def nodes(self) -> list[dict[str, Any]]:
        """Latest status per node, sorted by node name, as plain dicts plus ``age_s``."""
        now = time.monotonic()
        out = []
        for node in sorted(self._latest):
            status, arrived = self._latest[node]
            entry = dataclasses.asdict(status)
            entry["age_s"] = now - arrived
            # a node that finished its job (its last beat says ``finished``) is silent, not stale
            if entry["age_s"] > self.stale_after_s and not entry["values"].get("finished"):
                entry["level"] = DiagnosticStatus.STALE
            out.append(entry)
        return out

    def close(self) -> None:
        self.subscriber.close()
