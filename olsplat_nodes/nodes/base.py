"""What every node shares: a name, a flat parameter dict, a zmq context, and ``run(stop)``.

A node is started either in its own process (``python -m olsplat_nodes.nodes EXEC --name N
--params-json JSON``; SIGTERM/SIGINT set ``stop``) or as a thread of a composed launch that
shares one context. ``run`` returns the exit code: 0 when the node has finished its job (a
finite replay fully processed), non-zero on failure; the supervisor restarts on failure.
"""

from __future__ import annotations

import importlib
import threading
from typing import Any

import numpy as np
import zmq

from ..errors import OlsplatInputError
from . import NODES


class Node:
    """Base class. Subclasses declare ``DEFAULTS`` (every parameter they read, with its default)
    and implement ``run``. Unknown parameters are an error: a typo in a launch file must not
    silently fall back to a default."""

    DEFAULTS: dict[str, Any] = {}

    def __init__(self, name: str, params: dict[str, Any] | None = None, context: zmq.Context | None = None):
        self.name = name
        params = dict(params or {})
        unknown = sorted(set(params) - set(self.DEFAULTS))
        if unknown:
            raise OlsplatInputError(
                f"node {name!r} ({type(self).__name__}): unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(self.DEFAULTS))}"
            )
        self.params = {**self.DEFAULTS, **params}
        self.context = context or zmq.Context.instance()

    def run(self, stop: threading.Event) -> int:  # pragma: no cover - abstract
        raise NotImplementedError


def node_class(exec_name: str) -> type[Node]:
    """The class of an executable name (``ingest``) or of a ``module:Class`` path."""
    target = NODES.get(exec_name, exec_name)
    module_name, _, class_name = target.partition(":")
    if not class_name:
        raise OlsplatInputError(f"unknown node executable {exec_name!r}; known: {', '.join(NODES)} (or module:Class)")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as exc:
        raise OlsplatInputError(f"node executable {exec_name!r}: cannot load {target} ({exc})") from exc
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise OlsplatInputError(f"node executable {exec_name!r}: {target} is not a Node class")
    return cls


class NodeStats:
    """Counters every node reports in its DiagnosticStatus heartbeats.

    ``rate_hz`` is messages handled per second over the last ``window_s``; ``latency_ms`` is
    the mean wall time from a message's acquisition stamp to the end of its handling over the
    same window (it includes queueing upstream), ``busy_ms`` the mean handling time alone."""

    def __init__(self, window_s: float = 10.0):
        import collections

        self.window_s = window_s
        self.events: collections.deque = collections.deque()  # (monotonic end, latency s, busy s)
        self.counts: dict[str, int] = {
            "received": 0,
            "handled": 0,
            "published": 0,
            "dropped": 0,
            "bad_messages": 0,
            "errors": 0,
        }

    def count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n

    def handled(self, stamp_ns: int, busy_s: float) -> None:
        import time

        now = time.monotonic()
        latency = max(time.time() - stamp_ns / 1e9, 0.0) if stamp_ns else busy_s
        self.events.append((now, latency, busy_s))
        self.counts["handled"] += 1
        while self.events and self.events[0][0] < now - self.window_s:
            self.events.popleft()

    def values(self, **extra) -> dict:
        import time

        now = time.monotonic()
        recent = [e for e in self.events if e[0] >= now - self.window_s]
        span = min(self.window_s, max(now - recent[0][0], 1e-3)) if recent else self.window_s
        out = dict(self.counts)
        out["rate_hz"] = round(len(recent) / span, 3) if len(recent) > 1 else 0.0
        out["latency_ms"] = round(1e3 * float(np.mean([e[1] for e in recent])), 1) if recent else 0.0
        out["busy_ms"] = round(1e3 * float(np.mean([e[2] for e in recent])), 1) if recent else 0.0
        out.update(extra)
        return out

    def with_sockets(self, *socket_stats: dict, **extra) -> dict:
        """``values(**extra)`` plus the counters of the node's receiving sockets (``Subscriber.stats``:
        received, gaps, reconnects, ...; summed over several sockets). ``bad_messages`` adds up the
        node's own count (messages that decoded but could not be used: wrong type, inconsistent
        content) and the sockets' (messages that did not decode): a plain dict merge would let the
        sockets' count replace the node's."""
        merged: dict = {}
        for stats in socket_stats:
            for key, value in stats.items():
                merged[key] = merged.get(key, 0) + value
        merged["bad_messages"] = self.counts.get("bad_messages", 0) + merged.get("bad_messages", 0)
        return self.values(**{**merged, **extra})


class SequenceCounter:
    """Per message type sequence numbers (1, 2, ...): subscribers count the gaps of each
    (topic, schema, frame_id) stream as drops, so every type needs its own gap-free count."""

    def __init__(self):
        self.last: dict[str, int] = {}

    def stamp(self, message):
        """Set ``message.seq`` to the next number of its type; returns the message."""
        kind = type(message).__name__
        self.last[kind] = self.last.get(kind, 0) + 1
        message.seq = self.last[kind]
        return message
