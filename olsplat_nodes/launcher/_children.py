"""One running node, as a child process or as a thread, behind the same small interface:
``start(restarts, last_exit) -> str``, ``poll() -> exit code | None``, ``terminate()``,
``kill() -> bool``, and ``failure``: the one-line reason of a failure a restart cannot mend.

Exit codes follow ``subprocess``: 0 finished, > 0 failed, ``-N`` killed by signal N;
``errors.NOT_RESTARTABLE`` codes are bad input or configuration (the node said why in one line).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any, TextIO

import zmq

from ..errors import EXIT_FAILED, NOT_RESTARTABLE, classify_failure
from ..nodes._lifeline import LAUNCHER_PID_ENV
from ..nodes.base import LAST_EXIT_ENV, RESTARTS_ENV, node_class


class NodeLog:
    """``run_dir/logs/NAME.log``, opened once for the whole launch and appended to: each start
    adds a marker line, so the output of every incarnation of the node stays in one file."""

    def __init__(self, path: Path):
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        # Line-buffered so markers reach the file before a child writes to the same fd.
        self.file: TextIO = open(path, "a", buffering=1, encoding="utf-8")

    def marker(self, text: str) -> None:
        self.file.write(f"----- {time.strftime('%Y-%m-%d %H:%M:%S')} olsplat launch: {text} -----\n")

    def close(self) -> None:
        self.file.close()


def describe_exit(code: int) -> str:
    """``exited with code 1``, ``killed by SIGKILL``."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


class ProcessChild:
    """``python -m olsplat_nodes.nodes EXEC --name NAME --params-json JSON`` with stdout and
    stderr in the node's log. The child inherits the launcher's environment and current
    directory (so ``module:Class`` executables import from the same places), plus the launcher's
    pid (the child stops when that process dies: ``nodes._lifeline``) and its restart count."""

    def __init__(self, name: str, exec_name: str, params: dict[str, Any], log: NodeLog):
        self.name = name
        self.log = log
        self.argv = [
            sys.executable,
            "-m",
            "olsplat_nodes.nodes",
            exec_name,
            "--name",
            name,
            "--params-json",
            json.dumps(params),
        ]
        self.process: subprocess.Popen | None = None
        self.failure = ""
        self._log_offset = 0

    def start(self, restarts: int = 0, last_exit: str = "") -> str:
        # Unbuffered so the log is live and nothing is lost when the node is killed.
        env = {
            **os.environ,
            "PYTHONUNBUFFERED": "1",
            LAUNCHER_PID_ENV: str(os.getpid()),
            RESTARTS_ENV: str(restarts),
            LAST_EXIT_ENV: last_exit,
        }
        self.failure = ""
        self.log.file.flush()
        self._log_offset = self.log.path.stat().st_size  # where this run's output starts
        try:
            self.process = subprocess.Popen(
                self.argv, stdin=subprocess.DEVNULL, stdout=self.log.file, stderr=subprocess.STDOUT, env=env
            )
        except OSError as exc:  # counted as a failed run, so the restart policy applies
            self.process, self.failure = None, f"could not start: {exc}"
            self.log.marker(self.failure)
            return self.failure
        return f"pid {self.process.pid}"

    def poll(self) -> int | None:
        code = 127 if self.process is None else self.process.poll()
        if code in NOT_RESTARTABLE and not self.failure:
            self.failure = self._reason() or ""
        return code

    def _reason(self) -> str | None:
        """The node's own one-line reason (``node NAME: error: REASON``, its last such line in
        this run's part of the log)."""
        prefix = f"node {self.name}: error: "
        try:
            with open(self.log.path, encoding="utf-8", errors="replace") as file:
                file.seek(self._log_offset)
                lines = [line.strip() for line in file if line.startswith(prefix)]
        except OSError:
            return None
        return lines[-1][len(prefix) :] if lines else None

    def terminate(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()  # SIGTERM: the node's handler sets its stop event

    def kill(self) -> bool:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            try:
                self.process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:  # pragma: no cover - a process stuck in the kernel
                pass
        return True

    def close(self) -> None:
        pass


class ThreadChild:
    """``NodeClass(name, params, context).run(stop)`` in a daemon thread of the launcher.

    Log records emitted from the thread go to the node's log (a root-logger handler filtered
    on the thread's name); ``print`` output is not separated and goes to the launcher's stdout.
    An exception is a failure: its traceback goes to the node's log and ``failure`` holds
    one line for the status output. A thread cannot be killed: ``kill`` returns False.
    """

    def __init__(self, name: str, exec_name: str, params: dict[str, Any], log: NodeLog, context: zmq.Context):
        self.name = name
        self.exec_name = exec_name
        self.params = params
        self.log = log
        self.context = context
        self.stop = threading.Event()  # shared with the node: set to ask it to finish
        self.thread: threading.Thread | None = None
        self.code: int | None = None
        self.failure = ""
        self.history: tuple[int, str] = (0, "")  # (restarts, last exit) for the node's status
        self.thread_name = f"olsplat-node-{name}"
        self.handler = logging.StreamHandler(log.file)
        self.handler.setFormatter(logging.Formatter(f"%(asctime)s {name} %(levelname)s %(message)s"))
        self.handler.addFilter(lambda record: record.threadName == self.thread_name)
        logging.getLogger().addHandler(self.handler)

    def start(self, restarts: int = 0, last_exit: str = "") -> str:
        self.stop.clear()
        self.code, self.failure = None, ""
        self.history = (restarts, last_exit)
        self.thread = threading.Thread(target=self._main, name=self.thread_name, daemon=True)
        self.thread.start()
        return f"thread {self.thread_name}"

    def _main(self) -> None:
        logger = logging.getLogger(f"olsplat.launch.{self.name}")
        code = EXIT_FAILED
        try:
            node = node_class(self.exec_name)(self.name, self.params, self.context)
            node.stats.restarts, node.stats.last_exit = self.history
            code = int(node.run(self.stop) or 0)
        except SystemExit as exc:  # what a process would have exited with
            code = exc.code if isinstance(exc.code, int) else 1
        except Exception as exc:
            failure = classify_failure(exc)
            if failure is not None:  # bad input or configuration: one line, as a process says it
                code, self.failure = failure
                logger.error("node %s: error: %s", self.name, self.failure)
                return
            self.failure = f"raised {type(exc).__name__}: {exc}"
            logger.error("node %s raised an exception:\n%s", self.name, traceback.format_exc().rstrip())
        finally:
            self.code = code

    def poll(self) -> int | None:
        if self.thread is None or self.thread.is_alive():
            return None
        return self.code

    def terminate(self) -> None:
        self.stop.set()

    def kill(self) -> bool:
        self.stop.set()
        return False

    def close(self) -> None:
        logging.getLogger().removeHandler(self.handler)
