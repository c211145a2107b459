"""Small nodes for the launcher tests, run for real in child processes and threads
(``exec: tests.launcher.nodes_for_tests:Ticker``). Each one is driven by files in the run
directory, so a test waits on conditions, never on sleeps."""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq

from olsplat_nodes.nodes.base import Node
from olsplat_nodes.transport._sockets import attach

log = logging.getLogger(__name__)


class Ticker(Node):
    """Logs ``NAME tick i`` ``ticks`` times, then returns ``exit_code``. With ``crash_once``
    (a path), the first run creates that file and fails (``crash_how``: "exit" returns 3,
    "raise" raises), later runs go on normally. With ``wait_for`` (a path) it starts ticking
    only once that file exists (another node is up)."""

    @dataclass(frozen=True)
    class Params:
        ticks: int = 3
        period_s: float = 0.01
        exit_code: int = 0
        crash_once: str = ""
        crash_how: str = "exit"
        topic: str = "ticks"
        note: str = ""
        wait_for: str = ""
        extra: tuple[Any, ...] = ()  # unused: a list parameter whose items may be anything

    def run(self, stop: threading.Event) -> int:
        p = self.params
        log.info("%s starting: topic=%s note=%s", self.name, p.topic, p.note)
        if p.crash_once and not os.path.exists(p.crash_once):
            Path(p.crash_once).touch()
            if p.crash_how == "raise":
                raise RuntimeError(f"{self.name} crashes on purpose")
            log.info("%s crashing on purpose", self.name)
            return 3
        while p.wait_for and not os.path.exists(p.wait_for):
            if stop.wait(0.02):
                return 0
        for i in range(p.ticks):
            if stop.wait(p.period_s):
                return 0
            log.info("%s tick %d", self.name, i)
        return int(p.exit_code)


class Waiter(Node):
    """Writes its pid to ``pid_file``, then runs until ``release_file`` exists (returns 0) or
    it is stopped (returns 0). With ``ignore_stop`` it keeps running after stop (to be killed)."""

    @dataclass(frozen=True)
    class Params:
        pid_file: str = ""
        release_file: str = ""
        ignore_stop: bool = False

    def run(self, stop: threading.Event) -> int:
        p = self.params
        log.info("%s waiting (pid %d)", self.name, os.getpid())  # before the pid file: a test waits on it
        if p.pid_file:
            tmp = Path(p.pid_file + ".tmp")
            tmp.write_text(str(os.getpid()))
            tmp.replace(p.pid_file)  # atomic: a reader never sees an empty file
        while p.ignore_stop or not stop.is_set():
            if p.release_file and os.path.exists(p.release_file):
                log.info("%s released", self.name)
                return 0
            time.sleep(0.02)
        log.info("%s stopped", self.name)
        return 0


class Talker(Node):
    """PUB bound to ``endpoint``; sends ``TOPIC i`` every ``period_s`` until stopped."""

    @dataclass(frozen=True)
    class Params:
        endpoint: str = "ipc://{run_dir}/talk.sock"
        topic_out: str = "chatter"
        period_s: float = 0.02

    def run(self, stop: threading.Event) -> int:
        sock = self.context.socket(zmq.PUB)
        sock.linger = 0
        try:
            attach(sock, [self.params.endpoint], bind=True)  # as the real nodes bind
            log.info("%s publishing %s on %s", self.name, self.params.topic_out, self.params.endpoint)
            i = 0
            while not stop.wait(self.params.period_s):
                sock.send_string(f"{self.params.topic_out} {i}")
                i += 1
        finally:
            sock.close()
        return 0


class Listener(Node):
    """SUB connected to ``endpoint``; returns 0 after ``count`` messages on ``topic_in``, 2 if
    none arrive within ``timeout_s``."""

    @dataclass(frozen=True)
    class Params:
        endpoint: str = "ipc://{run_dir}/talk.sock"
        topic_in: str = "chatter"
        count: int = 3
        timeout_s: float = 10.0

    def run(self, stop: threading.Event) -> int:
        sock = self.context.socket(zmq.SUB)
        sock.linger = 0
        try:
            sock.connect(self.params.endpoint)
            sock.subscribe(self.params.topic_in + " ")
            log.info("%s listening to %s on %s", self.name, self.params.topic_in, self.params.endpoint)
            got = 0
            deadline = time.monotonic() + self.params.timeout_s
            while got < self.params.count and not stop.is_set():
                if time.monotonic() > deadline:
                    log.error("%s: nothing heard within %s s", self.name, self.params.timeout_s)
                    return 2
                if sock.poll(50):
                    log.info("%s heard %s", self.name, sock.recv_string())
                    got += 1
        finally:
            sock.close()
        return 0


def process_created() -> float:
    """This process's creation (its fork), wall-clock seconds: /proc/self/stat's start time in
    clock ticks since boot, against the boot clock now (10 ms resolution). Unlike a time taken in
    ``run``, it leaves out the interpreter's start and imports, which a busy machine stretches."""
    fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()  # from field 3 (state) on
    started = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22, starttime
    return time.time() - (time.clock_gettime(time.CLOCK_BOOTTIME) - started)


class Crasher(Node):
    """Appends "created crashed" to ``starts_file`` (one line per start: ``process_created()`` and
    ``time.time()`` just before the crash), then raises an unexpected exception: a crash, every time."""

    @dataclass(frozen=True)
    class Params:
        starts_file: str = ""

    def run(self, stop: threading.Event) -> int:
        with open(self.params.starts_file, "a") as file:
            file.write(f"{process_created()} {time.time()}\n")
        raise RuntimeError(f"{self.name} crashes on purpose")


class Beater(Node):
    """Sends a heartbeat (``Diagnostics`` to ``diagnostics``, the node's ``stats.values()``) every
    ``period_s`` until stopped; with ``crash_once`` (a path) the first run creates that file and
    exits with 3 after one beat."""

    @dataclass(frozen=True)
    class Params:
        diagnostics: str = ""
        period_s: float = 0.05
        crash_once: str = ""

    def run(self, stop: threading.Event) -> int:
        from olsplat_nodes.transport.diagnostics import Diagnostics

        diag = Diagnostics(self.context, self.params.diagnostics, self.name, period_s=0.0)
        try:
            while not stop.wait(self.params.period_s):
                diag.beat_now(0, "beating", self.stats.values())
                if self.params.crash_once and not os.path.exists(self.params.crash_once):
                    Path(self.params.crash_once).touch()
                    return 3
        finally:
            diag.close()
        return 0
