"""Streams: a PUB that never blocks, and a SUB that decodes, filters by exact topic, counts what
it misses from ``seq`` and drops bad messages (counted and logged, never raised)."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Iterable
from typing import Any

import zmq
from zmq.utils.monitor import parse_monitor_message

from olsplat_msgs import DEFAULT_MAX_BYTES, WireError, decode, encode

from ._sockets import Closable, DropLog, as_list, attach, deadline_after, log, make_socket, remaining_ms

_MAX_LATE_SKIPS = 1000


class Publisher(Closable):
    """PUB socket. ``send(topic, msg)`` encodes and hands the frames to libzmq without blocking:
    at the high-water mark (``hwm`` messages per subscriber) PUB drops, which is what a sensor
    stream wants (latest wins); subscribers see the loss as gaps in ``seq``. The node sets
    ``seq``/``stamp_ns`` on the message; this class changes nothing on it."""

    def __init__(self, context: zmq.Context, endpoint: str | Iterable[str], bind: bool = True, hwm: int = 4):
        self.socket = make_socket(context, zmq.PUB, sndhwm=hwm)
        try:
            self.endpoints = attach(self.socket, as_list(endpoint), bind)
        except BaseException:
            self.socket.close(linger=0)
            raise
        self.stats = {"published": 0, "dropped": 0}

    @property
    def endpoint(self) -> str:
        """The first endpoint as resolved (a bound ``tcp://host:*`` shows its port)."""
        return self.endpoints[0]

    def send(self, topic: str, msg: Any) -> bool:
        """Publish ``msg`` on ``topic``; False if libzmq refused it (counted in ``dropped``)."""
        frames = encode(msg, topic)
        try:
            # copy=False: large array frames go to libzmq without another copy (bytes are immutable)
            self.socket.send_multipart(frames, flags=zmq.NOBLOCK, copy=False)
        except zmq.Again:
            self.stats["dropped"] += 1
            return False
        self.stats["published"] += 1
        return True


class Subscriber(Closable):
    """SUB socket on one or more endpoints, receiving only ``topics`` (exact names; ``None`` = all).

    ``stats`` (flat ints, ready to merge into diagnostics ``values``):
      received      messages delivered by recv/drain
      bad_messages  frames that failed to decode (garbage, truncated, wrong version, too large, ...)
      gaps          messages missing by ``seq``, summed over streams; a stream is one
                    (topic, message type name, frame_id); per stream in ``gaps_by_stream``
      duplicates    a stream repeated its last ``seq`` (e.g. a repeated EndOfStream)
      seq_resets    a stream's ``seq`` went backwards (its publisher restarted); not a gap
      other_topics  well-formed messages on a topic that only shares a prefix with ours
      reconnects    connections re-made after libzmq dropped them (e.g. a frame over max_bytes)
    The first message of a stream never counts as a gap: a subscriber always misses the first
    messages after connecting (ZeroMQ's slow joiner).
    """

    def __init__(
        self,
        context: zmq.Context,
        endpoints: str | Iterable[str],
        topics: str | Iterable[str] | None,
        hwm: int = 4,
        bind: bool = False,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
    ):
        self.max_bytes = int(max_bytes)
        self.topics = None if topics is None else frozenset(as_list(topics))
        self.socket = make_socket(context, zmq.SUB, rcvhwm=hwm, max_bytes=self.max_bytes)
        for topic in self.topics if self.topics is not None else ("",):
            self.socket.setsockopt(zmq.SUBSCRIBE, topic.encode("utf-8"))
        # libzmq ends (and never retries) a connection on which a frame exceeded MAXMSGSIZE: watch
        # our connected endpoints and connect again, so one oversized message cannot cut a stream
        self._monitor = None if bind else self.socket.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        try:
            self.endpoints = attach(self.socket, as_list(endpoints), bind)
        except BaseException:
            self.close()
            raise
        self._poller = zmq.Poller()
        self._poller.register(self.socket, zmq.POLLIN)
        if self._monitor is not None:
            self._poller.register(self._monitor, zmq.POLLIN)
        self.stats = {
            "received": 0,
            "bad_messages": 0,
            "gaps": 0,
            "duplicates": 0,
            "seq_resets": 0,
            "other_topics": 0,
            "reconnects": 0,
        }
        self.gaps_by_stream: Counter[tuple[str, str, str]] = Counter()
        self.bad_by_error: Counter[str] = Counter()  # WireError class name -> count
        self._last_seq: dict[tuple[str, str, str], int] = {}
        self._drop_log = DropLog(f"subscriber on {', '.join(self.endpoints)}")

    @property
    def endpoint(self) -> str:
        return self.endpoints[0]

    def _reconnect_dropped(self) -> None:
        if self._monitor is None:  # a bound subscriber has nothing to reconnect
            return
        while True:
            try:
                event = parse_monitor_message(self._monitor.recv_multipart(flags=zmq.NOBLOCK))
            except zmq.Again:
                return
            endpoint = event["endpoint"].decode("utf-8", "replace")
            for target in [endpoint] if endpoint in self.endpoints else self.endpoints:
                try:
                    self.socket.disconnect(target)
                except zmq.ZMQError:  # already gone
                    pass
                self.socket.connect(target)
                self.stats["reconnects"] += 1
            log.info(
                "subscriber: connection to %s dropped (oversized frame or peer restart); connecting again", endpoint
            )

    def _accept(self, frames: list) -> tuple[str, Any] | None:
        try:
            topic, msg = decode(frames, max_bytes=self.max_bytes)
        except WireError as exc:
            self.stats["bad_messages"] += 1
            self.bad_by_error[type(exc).__name__] += 1
            self._drop_log(f"{type(exc).__name__}: {exc}")
            return None
        if self.topics is not None and topic not in self.topics:
            self.stats["other_topics"] += 1
            return None
        self.stats["received"] += 1
        key = (topic, type(msg).__name__, msg.frame_id)
        last = self._last_seq.get(key)
        if last is not None:
            if msg.seq > last + 1:
                self.stats["gaps"] += msg.seq - last - 1
                self.gaps_by_stream[key] += msg.seq - last - 1
            elif msg.seq == last:
                self.stats["duplicates"] += 1
            elif msg.seq < last:
                self.stats["seq_resets"] += 1
        self._last_seq[key] = msg.seq
        return topic, msg

    def recv(self, timeout_ms: float | None) -> tuple[str, Any] | None:
        """The next good message as ``(topic, msg)``, or None after ``timeout_ms`` (None = wait
        forever). Bad messages on the way are counted, logged and skipped."""
        deadline = deadline_after(timeout_ms)
        late = 0
        while True:
            ready = dict(self._poller.poll(remaining_ms(deadline)))
            if self.socket not in ready:
                # Reconnect only once nothing is left to read: a poll that finds the SUB readable
                # makes libzmq prefetch the first frame of the next message, and disconnecting the
                # pipe that holds the rest of it aborts the process ("Assertion failed: !_more
                # (src/fq.cpp:80)"), e.g. when messages were queued ahead of the oversized frame
                # that cut the connection. Waiting also delivers those messages instead of dropping them.
                if self._monitor in ready:
                    self._reconnect_dropped()
                if not ready or time.monotonic() >= deadline:
                    return None
                continue
            result = self._accept(self.socket.recv_multipart(flags=zmq.NOBLOCK, copy=False))
            if result is not None:
                return result
            # past the deadline, keep skipping bad messages that are already queued (a good one may
            # follow), but not forever: a garbage flood must not hold the caller
            late += time.monotonic() >= deadline
            if late > _MAX_LATE_SKIPS:
                return None

    def drain(self, timeout_ms: float | None = 0, max_messages: int = 10_000) -> list[tuple[str, Any]]:
        """Everything queued now, oldest first: waits up to ``timeout_ms`` for the first good
        message, then takes what is already there without waiting (at most ``max_messages``)."""
        first = self.recv(timeout_ms)
        if first is None:
            return []
        out = [first]
        while len(out) < max_messages:
            item = self.recv(0)
            if item is None:
                break
            out.append(item)
        return out

    def close(self) -> None:
        if self.socket.closed:
            return
        if self._monitor is not None:
            self.socket.disable_monitor()
            self._monitor.close(linger=0)
        self.socket.close(linger=0)
