"""Shared socket plumbing: options, bind/connect with the endpoint in the error, and a
rate-limited drop log (a flood of garbage must not become a flood of log lines)."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Self

import zmq

log = logging.getLogger("olsplat.transport")


def as_list(endpoints: str | Iterable[str]) -> list[str]:
    """One endpoint or several, as a list (a bare string is one endpoint, not its characters)."""
    items = [endpoints] if isinstance(endpoints, str) else list(endpoints)
    if not items or not all(isinstance(e, str) and e for e in items):
        raise ValueError(f"expected one or more non-empty strings (endpoints or topics), got {endpoints!r}")
    return items


def make_socket(
    context: zmq.Context,
    kind: int,
    *,
    max_bytes: int | None = None,
    sndhwm: int | None = None,
    rcvhwm: int | None = None,
) -> zmq.Socket:
    """A socket with linger 0 (closing never hangs on unsent messages: the graph is lossy by design),
    the given high-water marks, and MAXMSGSIZE so that libzmq refuses an oversized frame instead of
    allocating it."""
    sock = context.socket(kind)
    sock.linger = 0
    if max_bytes is not None:
        sock.maxmsgsize = int(max_bytes)
    if sndhwm is not None:
        sock.sndhwm = int(sndhwm)
    if rcvhwm is not None:
        sock.rcvhwm = int(rcvhwm)
    return sock


INPROC_REBIND_WAIT_S = 5.0  # how long a bind waits for a closed socket's inproc:// name to be freed


def attach(
    sock: zmq.Socket, endpoints: list[str], bind: bool, inproc_wait_s: float = INPROC_REBIND_WAIT_S
) -> list[str]:
    """Bind or connect to every endpoint; returns the endpoints as libzmq resolved them (a bound
    ``tcp://127.0.0.1:*`` becomes the chosen port). Creates the directory of an ``ipc://`` path.

    An ``inproc://`` name stays taken after its socket's ``close`` returns, until libzmq's reaper
    thread has destroyed the socket (sub-millisecond idle, longer under load). A node restarted in
    the launcher's composed mode binds its name again at once, so a bind that finds the name in
    use retries for up to ``inproc_wait_s`` before it reports the conflict."""
    resolved = []
    for endpoint in endpoints:
        try:
            if bind:
                if endpoint.startswith("ipc://"):
                    Path(endpoint[len("ipc://") :]).parent.mkdir(parents=True, exist_ok=True)
                _bind(sock, endpoint, inproc_wait_s)
                resolved.append(sock.get_string(zmq.LAST_ENDPOINT))
            else:
                sock.connect(endpoint)
                resolved.append(endpoint)
        except zmq.ZMQError as exc:
            exc.add_note(f"while {'binding' if bind else 'connecting'} {endpoint}")
            raise
    return resolved


def _bind(sock: zmq.Socket, endpoint: str, inproc_wait_s: float) -> None:
    deadline = time.monotonic() + inproc_wait_s
    while True:
        try:
            sock.bind(endpoint)
            return
        except zmq.ZMQError as exc:
            in_use = exc.errno == zmq.EADDRINUSE and endpoint.startswith("inproc://")
            if not in_use or time.monotonic() >= deadline:
                raise
            time.sleep(0.001)


class Closable:
    """Base of the transport's socket classes: ``close()`` (idempotent), and a context manager
    that closes on exit. Subclasses keep their zmq socket in ``self.socket`` and extend ``close``
    when they own more (a monitor socket, CURVE keys)."""

    socket: zmq.Socket

    def close(self) -> None:
        self.socket.close(linger=0)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DropLog:
    """Logs a warning for a dropped message at most once per ``interval_s``, then says how many
    similar drops it did not log in between."""

    def __init__(self, what: str, interval_s: float = 5.0):
        self.what = what
        self.interval_s = interval_s
        self._last = -float("inf")
        self._suppressed = 0

    def __call__(self, reason: str) -> None:
        now = time.monotonic()
        if now - self._last < self.interval_s:
            self._suppressed += 1
            return
        extra = f" ({self._suppressed} more since the last report)" if self._suppressed else ""
        log.warning("%s: dropped a message: %s%s", self.what, reason, extra)
        self._last, self._suppressed = now, 0


def deadline_after(timeout_ms: float | None) -> float:
    """Monotonic deadline; ``None`` waits forever."""
    return float("inf") if timeout_ms is None else time.monotonic() + max(0.0, timeout_ms) / 1000.0


def remaining_ms(deadline: float) -> int | None:
    """Milliseconds left for ``zmq.Socket.poll`` (``None`` = forever, never negative)."""
    if deadline == float("inf"):
        return None
    return max(0, int((deadline - time.monotonic()) * 1000.0 + 0.999))
