"""What every node shares: a name, typed parameters, a zmq context, and one loop.

A node is started either in its own process (``python -m olsplat_nodes.nodes EXEC --name N
--params-json JSON``; SIGTERM/SIGINT set ``stop``) or as a thread of a composed launch that
shares one context. ``run(stop)`` is the same for every node: ``setup`` (open the core state
and the sockets), then ``spin`` until ``stop`` is set or ``spin`` returns an exit code, then
``teardown`` and every socket closed, also after an exception. It returns the exit code: 0
when the node has finished its job (a finite replay fully processed), ``EXIT_INTERRUPTED``
when stopped, non-zero on failure; the supervisor restarts a crash, not a failure on bad input
or configuration (an ``OlsplatInputError`` from ``setup``: the process exits with
``errors.EXIT_BAD_INPUT`` / ``EXIT_CONFIG`` and its one-line reason).
"""

from __future__ import annotations

import collections
import importlib
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
import zmq

from ..errors import EXIT_INTERRUPTED, OlsplatInputError
from ..params import field_defaults, parse_params
from . import NODES

log = logging.getLogger(__name__)


def process_age_s() -> float:
    """Seconds since this process started (Linux: /proc/self/stat's start time against
    /proc/uptime, 10 ms steps); NaN where that cannot be read."""
    import os

    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22 of proc(5): starttime
        return float(Path("/proc/uptime").read_text().split()[0]) - started
    except (OSError, ValueError, IndexError):
        return float("nan")


@dataclass(frozen=True)
class NoParams:
    """The parameters of a node that takes none."""


class _Closable(Protocol):
    def close(self) -> None: ...


class Node:
    """Base class. Subclasses declare ``Params``, a frozen dataclass of every parameter they
    read (typed, with defaults; ``{run_dir}``, ``{namespace}`` and ``{name}`` in string defaults
    are filled in by the launcher), and implement ``spin`` (and usually ``setup``). A parameter
    with an unknown name or a wrong type is an error before anything starts: a typo in a launch
    file must not silently fall back to a default."""

    Params: ClassVar[type] = NoParams

    def __init__(self, name: str, params: dict[str, Any] | None = None, context: zmq.Context | None = None):
        self.name = name
        where = f"node {name!r} ({type(self).__name__})"
        self.params: Any = parse_params(self.Params, dict(params or {}), where)
        self.validate(self.params, where)
        self.context = context or zmq.Context.instance()
        self.stats = NodeStats()
        self.seqs = SequenceCounter()
        self._sockets: list[_Closable] = []

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """Every parameter's name and default (the launcher resolves placeholders in these)."""
        return field_defaults(cls.Params)

    @classmethod
    def check_params(cls, params: dict[str, Any], where: str) -> None:
        """Everything about ``params`` that can be known before the node starts (names, types,
        ranges); ParameterError starting with ``where``. The launcher calls it for every node
        before it starts any."""
        cls.validate(parse_params(cls.Params, params, where), where)

    @classmethod
    def validate(cls, params: Any, where: str) -> None:
        """Checks across fields of a parsed ``Params``, for subclasses; none by default."""

    # --- the loop -------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> int:
        self.stop = stop
        try:
            began = time.monotonic()
            self.setup()
            # what start-up costs, in every node's log (``olsplat bench graph`` reports it):
            # from the process's start (imports included) and of the node's own setup
            log.info(
                "%s ready: %.1f s after its process started, setup %.1f s",
                self.name,
                process_age_s(),
                time.monotonic() - began,
            )
            while not stop.is_set():
                code = self.spin()
                if code is not None:
                    self.stats.finished = code == 0  # its last heartbeat (teardown) says it is done
                    return code
            return EXIT_INTERRUPTED
        finally:
            try:
                self.teardown()
            finally:
                for socket in reversed(self._sockets):
                    socket.close()
                self._sockets.clear()

    def setup(self) -> None:
        """Open the node's state and sockets (``self.own`` each socket so that it is closed)."""

    def spin(self) -> int | None:
        """One turn of the loop (it should block at most ~0.2 s, so that ``stop`` is seen);
        return an exit code to end the node."""
        raise NotImplementedError

    def teardown(self) -> None:
        """Last words before the sockets close (a final heartbeat, say)."""

    # --- helpers --------------------------------------------------------------------------
    def own(self, socket):
        """Register ``socket`` to be closed when the node ends; returns it."""
        self._sockets.append(socket)
        return socket

    def publish(self, publisher, topic: str, message) -> None:
        """Send ``message`` on ``topic`` with the next sequence number of its type; counted."""
        publisher.send(topic, self.seqs.stamp(message))
        self.stats.count("published")

    def limit_threads(self, threads: int) -> None:
        """Run this node's numba kernels on ``threads`` worker threads (0 = one per core). The
        graph's processes share a small CPU: several pools of one thread per core each would
        only fight over it. numba's setting is per calling thread, so each node of a composed
        launch keeps its own."""
        if threads > 0:
            import numba

            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]

    def unexpected(self, message, topic: str) -> None:
        """A well-formed message of a type this input does not take: counted, logged, dropped."""
        self.stats.count("bad_messages")
        log.warning("%s: unexpected %s on %s: dropped", self.name, type(message).__name__, topic)


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


RESTARTS_ENV, LAST_EXIT_ENV = "OLSPLAT_RESTARTS", "OLSPLAT_LAST_EXIT"


def launch_history() -> tuple[int, str]:
    """(restarts, how the previous run ended) as the launcher passed them in the environment;
    (0, "") for a first start or a node started by hand."""
    import os

    text = os.environ.get(RESTARTS_ENV, "0")
    return (int(text) if text.isdigit() else 0), os.environ.get(LAST_EXIT_ENV, "")


class NodeStats:
    """Counters every node reports in its DiagnosticStatus heartbeats.

    ``rate_hz`` is messages handled per second over the last ``window_s``; ``latency_ms`` is
    the mean wall time from a message's acquisition stamp to the end of its handling over the
    same window (it includes queueing upstream), ``busy_ms`` the mean handling time alone;
    ``restarts`` how often the launcher has restarted the node, ``last_exit`` (after a restart)
    how its previous run ended."""

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        # how often the launcher has restarted this node and why its previous run ended: put in
        # the child's environment by the supervisor (``RESTARTS_ENV``, ``LAST_EXIT_ENV``), set
        # on ``stats`` directly for a node running as a thread of a composed launch
        self.restarts, self.last_exit = launch_history()
        self.finished = False  # the node ended its job (exit 0): heartbeats say ``finished: 1``
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
        now = time.monotonic()
        latency = max(time.time() - stamp_ns / 1e9, 0.0) if stamp_ns else busy_s
        self.events.append((now, latency, busy_s))
        self.counts["handled"] += 1
        while self.events and self.events[0][0] < now - self.window_s:
            self.events.popleft()

    def values(self, **extra) -> dict:
        now = time.monotonic()
        recent = [e for e in self.events if e[0] >= now - self.window_s]
        span = min(self.window_s, max(now - recent[0][0], 1e-3)) if recent else self.window_s
        out: dict[str, Any] = dict(self.counts)
        out["rate_hz"] = round(len(recent) / span, 3) if len(recent) > 1 else 0.0
        out["latency_ms"] = round(1e3 * float(np.mean([e[1] for e in recent])), 1) if recent else 0.0
        out["busy_ms"] = round(1e3 * float(np.mean([e[2] for e in recent])), 1) if recent else 0.0
        out["restarts"] = self.restarts
        if self.finished:
            out["finished"] = 1
        if self.last_exit:
            out["last_exit"] = self.last_exit
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
