"""What a launch claims on the machine before any node starts: its run folder (one graph at a
time: ``RUN_DIR/launch.lock``) and its TCP ports (free, or held by someone else: a ghost graph of
a launcher that was killed, say). Either refusal is one ``OlsplatInputError`` line naming the
folder or the port and the process holding it.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import Any, TextIO

from ..errors import OlsplatInputError
from ._config import LaunchConfig

LOCK_NAME = "launch.lock"


class RunDirLock:
    """``RUN_DIR/launch.lock``, held (``fcntl.flock``, exclusive) while the launch runs; the file
    holds the launcher's pid. The kernel drops the lock with its holder, so the file a killed
    launcher leaves behind is no lock: the next launch takes it over. ``release`` unlocks and
    closes (the file stays: removing it would race with a launch taking it)."""

    def __init__(self, run_dir: Path):
        self.path = run_dir / LOCK_NAME
        self._file: TextIO | None = None

    def acquire(self) -> None:
        """Take the lock or raise ``OlsplatInputError`` naming the folder and the holder's pid."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        file = open(self.path, "a+", encoding="utf-8")  # not "w": the holder's pid must survive our try
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            file.seek(0)
            holder = file.read().strip()
            file.close()
            raise OlsplatInputError(
                f"run folder {self.path.parent} is in use by another launch (pid {holder or 'unknown'}, {self.path}): "
                "stop that launch, or use another --run-dir"
            ) from None
        file.seek(0)
        file.truncate()
        file.write(f"{os.getpid()}\n")
        file.flush()
        self._file = file

    def release(self) -> None:
        if self._file is not None:
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None


def check_ports(config: LaunchConfig, params: dict[str, dict[str, Any]]) -> None:
    """Every TCP endpoint the launch binds can be bound now (the pre-flight check of
    ``olsplat launch --check``); else ``OlsplatInputError``: the port, the endpoint's param and,
    where /proc tells, the pid holding it."""
    from ..nodes.base import node_class
    from .preflight._launch import LaunchPlan
    from .preflight._resources import port_rows

    effective = {node.name: {**node_class(node.exec).defaults(), **params[node.name]} for node in config.nodes}
    for row in port_rows(LaunchPlan(config, effective)):
        if row.status == "blocker":
            raise OlsplatInputError(f"{row.name}: {row.figure}: {row.fix}")
