"""The query link: a ROUTER server and a DEALER client with timeouts.

Framing (msgs/README.md, "The query link"): every message carries the REQ-style empty delimiter
before the topic, so the server sees ``[identity]["" ][topic][header][arrays...]`` from both REQ
and DEALER clients and answers in the same envelope. Requests and replies use topic ``query``.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from typing import Any

import msgpack
import zmq

from olsplat_msgs import (
    DEFAULT_MAX_BYTES,
    QueryReply,
    QueryRequest,
    SplatsReply,
    SplatsRequest,
    StatusRequest,
    ViewsRequest,
    WireError,
    decode,
    encode,
)

from ._sockets import Closable, DropLog, attach, deadline_after, log, make_socket, remaining_ms
from .curve import ClientKeys, ServerKeys

QUERY_TOPIC = "query"
_MAX_LATE_SKIPS = 1000


class NoReply(TimeoutError):
    """The server did not answer within the timeout (it may be down, busy, or refusing our key)."""

    def __init__(self, endpoint: str, timeout: float):
        self.endpoint = endpoint
        self.timeout = timeout
        super().__init__(f"no reply from {endpoint} within {timeout:g} s")


def _salvage_request_id(body: list) -> str:
    """The request_id of an undecodable request if its header is readable enough, else ""; lets
    the client match the bad_request answer to what it sent."""
    try:
        header = msgpack.unpackb(body[1], raw=False, strict_map_key=False)
        request_id = header["fields"]["request_id"]
    except Exception:  # anything unreadable simply has no id
        return ""
    return request_id[:200] if isinstance(request_id, str) else ""


def _client_of(frames: list) -> str:
    """Who sent a request, for the rate limit: the CURVE public key (a client that reconnects
    keeps it), else the connection (the ROUTER's routing identity of it).

    Not the peer's address: without CURVE every client of one machine, or behind one NAT, has
    the same address, and one flooding client would spend the budget of all the others (three
    loopback clients flooding left an honest fourth 6 answers in 57 when the budget was per
    address). A client that reconnects to get a fresh budget pays a TCP handshake each time."""
    first = frames[0]
    try:
        key = first.get("User-Id")
    except (zmq.ZMQError, AttributeError, KeyError):
        key = None
    return f"User-Id:{key}" if key else f"connection:{bytes(first).hex()}"


class RateLimiter:
    """Token buckets per client: ``rate`` requests per second on average, ``burst`` at once.
    Memory stays bounded: at most ``max_clients`` buckets (the longest-idle ones go first)."""

    def __init__(self, rate: float, burst: int, max_clients: int = 10_000):
        self.rate, self.burst, self.max_clients = float(rate), float(burst), max_clients
        self.buckets: dict[str, tuple[float, float]] = {}  # client -> (tokens, last refill time)

    def allow(self, client: str, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        tokens, last = self.buckets.pop(client, (self.burst, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate)
        allowed = tokens >= 1.0
        self.buckets[client] = (tokens - 1.0 if allowed else tokens, now)  # re-inserted: newest last
        while len(self.buckets) > self.max_clients:
            del self.buckets[next(iter(self.buckets))]
        return allowed


class QueryServer(Closable):
    """ROUTER socket bound to ``endpoint``. ``poll`` returns the next well-formed request; a
    malformed one (or a message that is not one of ``accept``) is counted, logged and answered
    with ``QueryReply(status="bad_request")`` right there. With ``keys`` the link is CURVE
    encrypted and only clients on the allow-list get through.

    With ``queries_per_s`` a client (its CURVE key, else its connection) sending QueryRequests
    faster than that (beyond ``burst`` at once) is answered ``status="busy"`` at once, without
    the query being run; StatusRequests are never limited.

    ``stats``: requests (returned by poll), bad_requests, busy (refused by the rate limit),
    replies, dropped_replies (peer gone or its queue full), auth_failures (handshakes refused by
    CURVE, seen by a socket monitor)."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        keys: ServerKeys | None = None,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
        accept: tuple[type, ...] = (QueryRequest, StatusRequest, SplatsRequest, ViewsRequest),
        hwm: int = 100,
        queries_per_s: float | None = None,
        burst: int = 10,
    ):
        self.context, self.keys, self.max_bytes, self.accept = context, keys, int(max_bytes), tuple(accept)
        self.limiter = RateLimiter(queries_per_s, burst) if queries_per_s else None
        self.socket = make_socket(context, zmq.ROUTER, max_bytes=self.max_bytes, sndhwm=hwm, rcvhwm=hwm)
        self._monitor = self.socket.get_monitor_socket(
            zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
        )
        self._keys_applied = False
        try:
            if keys is not None:
                keys.apply(self.socket, context)
                self._keys_applied = True
            self.endpoint = attach(self.socket, [endpoint], bind=True)[0]
        except BaseException:
            self.close()
            raise
        self.stats = {
            "requests": 0,
            "bad_requests": 0,
            "busy": 0,
            "replies": 0,
            "dropped_replies": 0,
            "auth_failures": 0,
        }
        self._drop_log = DropLog(f"query server on {self.endpoint}")

    def _count_monitor_events(self) -> None:
        while True:
            try:
                frames = self._monitor.recv_multipart(flags=zmq.NOBLOCK)
            except zmq.Again:
                return
            if len(frames) == 2 and len(frames[0]) >= 2:
                self.stats["auth_failures"] += 1

    def _bad(self, identity: bytes, reason: str, request_id: str = "") -> None:
        self.stats["bad_requests"] += 1
        self._drop_log(reason)
        self.reply(identity, QueryReply(request_id=request_id, status="bad_request", message=reason))

    def _accept(self, frames: list) -> tuple[bytes, Any] | None:
        identity = bytes(frames[0])
        if len(frames) < 2 or len(frames[1]) != 0:
            self._bad(identity, "missing the empty delimiter frame before the topic (a DEALER client must send it)")
            return None
        body = frames[2:]
        try:
            _topic, msg = decode(body, max_bytes=self.max_bytes)
        except WireError as exc:
            self._bad(identity, f"{type(exc).__name__}: {exc}", _salvage_request_id(body))
            return None
        if not isinstance(msg, self.accept):
            names = " or ".join(cls.__name__ for cls in self.accept)
            self._bad(identity, f"expected {names}, got {type(msg).__name__}", getattr(msg, "request_id", ""))
            return None
        # the costly requests (a query's work, a map of up to 20 MB) count against the rate limit
        costly = isinstance(msg, (QueryRequest, SplatsRequest))
        if self.limiter is not None and costly and not self.limiter.allow(_client_of(frames)):
            self.stats["busy"] += 1
            self._drop_log("a client over the query rate limit")
            message = f"over the rate limit of {self.limiter.rate:g} queries per second per client: retry later"
            refusal: type = SplatsReply if isinstance(msg, SplatsRequest) else QueryReply
            self.reply(identity, refusal(request_id=getattr(msg, "request_id", ""), status="busy", message=message))
            return None
        self.stats["requests"] += 1
        return identity, msg

    def poll(self, timeout_ms: float | None) -> tuple[bytes, Any] | None:
        """The next well-formed request as ``(identity, msg)``, or None after ``timeout_ms``
        (None = forever). Answer it with ``reply(identity, ...)``."""
        deadline = deadline_after(timeout_ms)
        late = 0
        while True:
            ready = self.socket.poll(remaining_ms(deadline), zmq.POLLIN)
            self._count_monitor_events()
            if not ready:
                return None
            result = self._accept(self.socket.recv_multipart(flags=zmq.NOBLOCK, copy=False))
            if result is not None:
                return result
            late += time.monotonic() >= deadline
            if late > _MAX_LATE_SKIPS:
                return None

    def reply(self, identity: bytes, msg: Any) -> bool:
        """Send ``msg`` to the client ``identity``; False if it could not be queued (client gone
        or not reading: ROUTER drops rather than blocks)."""
        try:
            self.socket.send_multipart([identity, b"", *encode(msg, QUERY_TOPIC)], flags=zmq.NOBLOCK, copy=False)
        except zmq.Again:
            self.stats["dropped_replies"] += 1
            return False
        self.stats["replies"] += 1
        return True

    def close(self) -> None:
        if self.socket.closed:
            return
        try:
            self.socket.disable_monitor()
        except zmq.ZMQError:
            pass
        self._monitor.close(linger=0)
        self.socket.close(linger=0)
        if self._keys_applied and self.keys is not None:
            self._keys_applied = False
            self.keys.release(self.context)


class QueryClient(Closable):
    """DEALER client of one query server. ``request(msg)`` sends and waits up to ``timeout_s`` for
    the matching reply; on timeout the socket is closed and a fresh one connected (lazy pirate:
    a late answer can never be mistaken for the next one), and ``NoReply`` is raised after
    ``retries`` more attempts. A request without a ``request_id`` gets a random one.

    ``stats``: requests, replies, timeouts, bad_replies (undecodable), stale_replies (an id we
    no longer wait for), resets."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        timeout_s: float = 5.0,
        keys: ClientKeys | None = None,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
        retries: int = 0,
    ):
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s!r}")
        self.context, self.endpoint, self.timeout_s, self.keys = context, endpoint, float(timeout_s), keys
        self.max_bytes, self.retries = int(max_bytes), int(retries)
        self.stats = {"requests": 0, "replies": 0, "timeouts": 0, "bad_replies": 0, "stale_replies": 0, "resets": 0}
        self._drop_log = DropLog(f"query client of {endpoint}")
        self.socket = self._connect()

    def _connect(self) -> zmq.Socket:
        sock = make_socket(self.context, zmq.DEALER, max_bytes=self.max_bytes)
        try:
            if self.keys is not None:
                self.keys.apply(sock)
            attach(sock, [self.endpoint], bind=False)
        except BaseException:
            sock.close(linger=0)
            raise
        return sock

    def _reset(self) -> None:
        self.socket.close(linger=0)
        self.socket = self._connect()
        self.stats["resets"] += 1

    def _wait(self, request_id: str, deadline: float) -> Any | None:
        while True:
            if not self.socket.poll(remaining_ms(deadline), zmq.POLLIN):
                return None
            frames = self.socket.recv_multipart(flags=zmq.NOBLOCK, copy=False)
            try:
                if not frames or len(frames[0]) != 0:
                    raise WireError("reply without the empty delimiter frame")
                _topic, msg = decode(frames[1:], max_bytes=self.max_bytes)
            except WireError as exc:
                self.stats["bad_replies"] += 1
                self._drop_log(f"{type(exc).__name__}: {exc}")
                continue
            reply_id = getattr(msg, "request_id", "")
            if reply_id and reply_id != request_id:  # "" = the server could not read our id: it is ours
                self.stats["stale_replies"] += 1
                continue
            return msg

    def ask(self, msg: Any) -> Any | None:
        """``request(msg)``, or None when no reply came in time (a caller that shows a silent
        link as a state rather than handling an exception)."""
        try:
            return self.request(msg)
        except NoReply:
            return None

    def request(self, msg: Any) -> Any:
        """Send ``msg`` (a QueryRequest or StatusRequest), return the reply message."""
        if hasattr(msg, "request_id") and not msg.request_id:
            msg = dataclasses.replace(msg, request_id=uuid.uuid4().hex)  # the caller's message stays as it was
        frames = [b"", *encode(msg, QUERY_TOPIC)]
        request_id = getattr(msg, "request_id", "")
        self.stats["requests"] += 1
        for attempt in range(self.retries + 1):
            deadline = deadline_after(self.timeout_s * 1000.0)
            try:
                # DEALER queues while connecting; NOBLOCK only fails at the high-water mark
                self.socket.send_multipart(frames, flags=zmq.NOBLOCK, copy=False)
                reply = self._wait(request_id, deadline)
            except zmq.Again:
                reply = None
            if reply is not None:
                self.stats["replies"] += 1
                return reply
            self.stats["timeouts"] += 1
            log.info(
                "no reply from %s within %g s (attempt %d of %d)",
                self.endpoint,
                self.timeout_s,
                attempt + 1,
                self.retries + 1,
            )
            self._reset()
        raise NoReply(self.endpoint, self.timeout_s)
