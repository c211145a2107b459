"""Helpers shared by the test folders (``from tests.helpers import wait_for, every, free_port``):
polling waits with deadlines instead of sleeps, and free TCP ports for real sockets."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any, TypeVar

import pytest

T = TypeVar("T")


def wait_for(
    condition: Callable[[], T],
    timeout_s: float = 3.0,
    what: str = "the condition",
    *,
    step: Callable[[], Any] | None = None,
    interval_s: float = 0.01,
) -> T:
    """Call ``step`` (if any), then ``condition``, until ``condition`` returns something truthy,
    and return that value. Between tries sleep ``interval_s`` (0: poll as fast as ``step`` and
    ``condition`` return, for conditions that block by themselves). After ``timeout_s`` the test
    fails, naming ``what`` and the last value; the condition is always tried at least once, and
    once more at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        if step is not None:
            step()
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what} (last value: {value!r:.200})")
        time.sleep(max(0.0, min(interval_s, deadline - time.monotonic())))


def every(period_s: float, action: Callable[[], Any]) -> Callable[[], None]:
    """A ``step`` for ``wait_for`` that runs ``action`` at most once per ``period_s`` (the first
    call runs it at once): e.g. re-send a message every 0.2 s while polling fast."""
    last = [-float("inf")]

    def step() -> None:
        if time.monotonic() - last[0] >= period_s:
            last[0] = time.monotonic()
            action()

    return step


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that nothing listens on right now (the kernel picks it; the probe
    socket is closed again). Another process could take it before the caller binds it: use it
    where an endpoint must be known in advance (a launch file, a client of a server not started
    yet, an endpoint nobody should answer); bind ``tcp://127.0.0.1:*`` where possible."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]
