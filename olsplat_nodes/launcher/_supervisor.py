"""The supervisor: start the nodes of a launch, restart them by policy, stop them all.

One loop in the calling thread polls every node 20 times a second. Signals only set flags (a
handler that took a lock could deadlock against the loop), so all decisions are made in one
place, in order.

Failures are classified: a node that exits with ``errors.NOT_RESTARTABLE`` (bad input or
configuration; it said why in one line) is not restarted, the launch stops and exits with that
code; a crash (a signal, an unexpected exception, any other code) is restarted after a delay that
doubles from ``restart_delay_s`` up to ``MAX_RESTART_DELAY_S``; a node that has used up its
``max_restarts`` ends the launch with ``EXIT_FAILED``. The launch never waits on a node that will
not run again. Child processes die with the launcher (``nodes._lifeline``), and a launch refuses
a run folder or a TCP port another graph holds (``_claims``).
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import TextIO

import zmq

from ..errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, NOT_RESTARTABLE  # the exit codes of Supervisor.run
from ._children import NodeLog, ProcessChild, ThreadChild, describe_exit
from ._claims import RunDirLock, check_ports
from ._config import LaunchConfig, NodeConfig
from ._memory import check_memory
from ._resolve import resolve_launch

_TICK_S = 0.05
MAX_RESTART_DELAY_S = 30.0  # the doubling restart delay stops growing here (or at restart_delay_s if larger)


@dataclass
class _Slot:
    """Supervision state of one node."""

    node: NodeConfig
    child: ProcessChild | ThreadChild
    state: str = "new"  # running | waiting (restart due at restart_at) | finished | failed | stopped
    starts: int = 0
    restarts: int = 0
    restart_at: float = 0.0
    last_exit: str = ""  # how the previous run ended, for the node's status after a restart


class Supervisor:
    """Runs a ``LaunchConfig`` until its ``exit_when`` nodes finish, a node it needs fails for
    good, or it is asked to stop.

    ``run()`` returns 0 (every ``exit_when`` node exited with code 0, or, with an empty
    ``exit_when``, every node ended and none had failed), 1 (an ``exit_when`` node failed and
    cannot be restarted, or a node gave up after ``max_restarts``), the node's
    ``EXIT_BAD_INPUT`` (65) / ``EXIT_CONFIG`` (78) when a node failed on its input or
    configuration, or 128 + the signal number when stopped by SIGINT (130) / SIGTERM (143).
    Before any node starts it takes the run folder's lock and checks the TCP ports
    (``OlsplatInputError`` when another graph holds either). Signal handlers are installed only
    when ``run`` is called from the main thread; from any other thread, call ``request_stop()``.

    Status lines (started, exited, restarting, giving up, stopping) go to ``stdout`` (default:
    ``sys.stdout``) and to ``run_dir/logs/launch.log``; node output goes to
    ``run_dir/logs/NAME.log``. A relative ``run_dir`` is taken from the current directory at
    construction. ``context`` (composed mode) is used instead of a fresh ``zmq.Context``
    and is then left open.
    """

    def __init__(self, config: LaunchConfig, stdout: TextIO | None = None, context: zmq.Context | None = None):
        self.config = config
        self.run_dir = config.run_dir.resolve()
        self.stdout = stdout
        self._context = context
        self._slots: list[_Slot] = []
        self._stop_code: int | None = None
        self._kill_now = False
        self._launch_log: TextIO | None = None

    def request_stop(self, exit_code: int = EXIT_INTERRUPTED) -> None:
        """Ask ``run`` to stop every node and return ``exit_code``. Safe from any thread and from
        a signal handler; a second request while stopping skips the grace period."""
        if self._stop_code is None:
            self._stop_code = exit_code
        else:
            self._kill_now = True

    @property
    def pids(self) -> dict[str, int]:
        """Process ids of the nodes running now (processes mode), for tests and tools."""
        return {s.node.name: s.child.process.pid for s in self._slots
                if s.state == "running" and isinstance(s.child, ProcessChild) and s.child.process}  # fmt: skip

    @property
    def states(self) -> dict[str, str]:
        """Each node's supervision state (new, running, waiting, finished, failed, stopped): a
        tool can tell a node that ended for good from one being restarted."""
        return {s.node.name: s.state for s in self._slots}

    def check(self) -> dict:
        """The checks ``run`` makes before any node starts, on their own: every configuration
        error (LaunchFileError naming the file and key) and the memory estimate (a flight that
        will not fit is refused now, not killed later). Returns the resolved parameters. A
        caller that runs the supervisor in a thread calls this first, so that a bad launch file
        or ``--set`` is its error, not the thread's."""
        params = resolve_launch(self.config, self.run_dir)
        check_memory(self.config, params)
        return params

    def run(self) -> int:
        """Supervise until done; see the class docstring for the exit code. Call it once."""
        if self._slots:
            raise RuntimeError("Supervisor.run() was already called; make a new Supervisor")
        params = self.check()
        lock = RunDirLock(self.run_dir)
        lock.acquire()
        try:
            check_ports(self.config, params)
            return self._run(params)
        finally:
            lock.release()

    def _run(self, params: dict) -> int:
        logs = self.run_dir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        self._launch_log = open(logs / "launch.log", "a", buffering=1, encoding="utf-8")
        context = None
        if self.config.compose:
            context = self._context or zmq.Context()
        for node in self.config.nodes:
            log = NodeLog(logs / f"{node.name}.log")
            child = (ThreadChild(node.name, node.exec, params[node.name], log, context) if context is not None
                     else ProcessChild(node.name, node.exec, params[node.name], log))  # fmt: skip
            self._slots.append(_Slot(node, child))
        restore = self._install_signal_handlers()
        root = logging.getLogger()
        root_level = root.level
        if self.config.compose and root.getEffectiveLevel() > logging.INFO:
            root.setLevel(logging.INFO)  # node INFO records must reach the per-node handlers
        try:
            mode = "composed (threads, inproc)" if self.config.compose else "processes"
            self._status(f"launch {self.config.name}: {len(self._slots)} nodes, {mode}, run_dir {self.run_dir}")
            return self._supervise()
        finally:
            all_stopped = self._stop_all()
            restore()
            root.setLevel(root_level)
            for slot in self._slots:
                slot.child.close()
                slot.child.log.close()
            # Destroying a context under a live thread's sockets would crash it: only when all stopped.
            if context is not None and self._context is None and all_stopped:
                context.destroy(linger=0)
            self._launch_log.close()

    def _supervise(self) -> int:
        for slot in self._slots:
            self._start(slot)
        while True:
            if self._stop_code is not None:
                self._status(f"stopping all nodes ({self._reason(self._stop_code)})")
                return self._stop_code
            for slot in self._slots:
                if slot.state == "running":
                    code = slot.child.poll()
                    if code is not None:
                        result = self._on_exit(slot, code)
                        if result is not None:
                            return result
                elif slot.state == "waiting" and time.monotonic() >= slot.restart_at:
                    self._start(slot)
            if not any(s.state in ("running", "waiting") for s in self._slots):
                failed = [s.node.name for s in self._slots if s.state == "failed"]
                self._status(f"every node has ended{'; failed: ' + ', '.join(failed) if failed else ''}")
                return EXIT_FAILED if failed else EXIT_OK
            time.sleep(_TICK_S)

    def _start(self, slot: _Slot) -> None:
        slot.starts += 1
        slot.child.log.marker(f"start #{slot.starts} of node {slot.node.name} ({slot.node.exec})")
        how = slot.child.start(slot.restarts, slot.last_exit)
        slot.state = "running"
        self._status(f"{slot.node.name}: started ({how})")

    def _on_exit(self, slot: _Slot, code: int) -> int | None:
        """Record a node's exit; the launch's exit code if this ends the launch."""
        node, exit_when = slot.node, self.config.exit_when
        failure = getattr(slot.child, "failure", "")
        slot.last_exit = failure or describe_exit(code)
        self._status(f"{node.name}: {slot.last_exit}")
        slot.child.log.marker(f"node {node.name} {slot.last_exit}")
        if code in NOT_RESTARTABLE:
            slot.state = "failed"
            kind = "bad input" if code == NOT_RESTARTABLE[0] else "configuration"
            self._status(
                f"launch failed: {node.name} failed on its {kind} (exit code {code}); a restart would not help"
            )
            return code
        if code == 0 and node.name in exit_when:
            slot.state = "finished"
            if all(s.state == "finished" for s in self._slots if s.node.name in exit_when):
                self._status(f"exit_when nodes finished ({', '.join(exit_when)}); stopping the rest")
                return EXIT_OK
            return None
        if node.restart == "never" or (node.restart == "on-failure" and code == 0):
            slot.state = "finished" if code == 0 else "failed"
            if code != 0:
                self._status(f"{node.name}: not restarted (restart: {node.restart})")
            return self._gave_up(slot)
        if slot.restarts >= node.max_restarts:
            slot.state = "failed"
            self._status(f"{node.name}: giving up after {slot.restarts} restarts (max_restarts: {node.max_restarts})")
            return self._gave_up(slot, exhausted=True)
        slot.restarts += 1
        slot.state = "waiting"
        delay = restart_delay(node.restart_delay_s, slot.restarts)
        slot.restart_at = time.monotonic() + delay
        self._status(f"{node.name}: restarting in {delay:g} s (restart {slot.restarts} of {node.max_restarts})")
        return None

    def _gave_up(self, slot: _Slot, exhausted: bool = False) -> int | None:
        """The launch's exit code when a node that will not run again ends it: one in
        ``exit_when``, or one that used up its restarts while others still run (they would wait
        on it for ever); None to go on (when nothing else runs, the loop ends the launch)."""
        if slot.state == "failed" and slot.node.name in self.config.exit_when:
            self._status(f"launch failed: {slot.node.name} is in exit_when and will not run again")
            return EXIT_FAILED
        if exhausted and any(s.state in ("running", "waiting") for s in self._slots):
            self._status(f"launch failed: {slot.node.name} gave up after {slot.restarts} restarts; stopping the rest")
            return EXIT_FAILED
        return None

    def _stop_all(self) -> bool:
        """SIGTERM (or the stop event) to every running node, in reverse start order; SIGKILL
        what is still running after ``stop_timeout_s``. True if every node has stopped."""
        running = [s for s in reversed(self._slots) if s.state == "running"]
        for slot in self._slots:
            if slot.state == "waiting":
                slot.state = "stopped"
        for slot in running:
            slot.child.terminate()
        deadline = time.monotonic() + self.config.stop_timeout_s
        while running:
            for slot in list(running):
                code = slot.child.poll()
                if code is not None:
                    slot.state = "stopped"
                    running.remove(slot)
                    self._status(f"{slot.node.name}: stopped ({describe_exit(code)})")
            if not running or self._kill_now or time.monotonic() >= deadline:
                break
            time.sleep(_TICK_S)
        for slot in running:
            if slot.child.kill():
                slot.state = "stopped"
                self._status(
                    f"{slot.node.name}: did not stop within {self.config.stop_timeout_s:g} s; killed (SIGKILL)"
                )
            else:
                self._status(
                    f"{slot.node.name}: did not stop within {self.config.stop_timeout_s:g} s; left running (a thread "
                    "cannot be killed)"
                )
        return all(s.state != "running" for s in self._slots)

    def _install_signal_handlers(self):
        """SIGINT/SIGTERM -> request_stop(128 + signum); returns a function that restores the
        previous handlers. A no-op outside the main thread (Python allows handlers only there)."""
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
        for sig in previous:
            signal.signal(sig, lambda signum, frame: self.request_stop(128 + signum))

        def restore() -> None:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

        return restore

    @staticmethod
    def _reason(code: int) -> str:
        if code > 128:
            try:
                return f"received {signal.Signals(code - 128).name}"
            except ValueError:
                pass
        return f"stop requested, exit code {code}"

    def _status(self, text: str) -> None:
        line = f"{time.strftime('%H:%M:%S')} [{self.config.name}] {text}"
        out = self.stdout or sys.stdout
        print(line, file=out, flush=True)
        if self._launch_log is not None:
            self._launch_log.write(line + "\n")


def restart_delay(first_s: float, restart: int) -> float:
    """Seconds before restart number ``restart`` (1, 2, ...): ``first_s``, doubling each time, at
    most ``MAX_RESTART_DELAY_S`` (or ``first_s`` when that is larger)."""
    return min(first_s * 2.0 ** (restart - 1), max(first_s, MAX_RESTART_DELAY_S))
