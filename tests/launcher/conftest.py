"""Helpers for the launcher tests: write a launch file, make the test nodes importable in the
child processes, run a supervisor with a deadline (waits: ``tests.helpers.wait_for``)."""

from __future__ import annotations

import io
import os
import threading
from pathlib import Path

import pytest
import yaml

from olsplat_nodes.launcher import LaunchConfig, Supervisor

REPO = Path(__file__).resolve().parents[2]
NODES = "tests.launcher.nodes_for_tests"


@pytest.fixture(autouse=True)
def importable_test_nodes(monkeypatch):
    """Children run ``python -m olsplat_nodes.nodes tests.launcher.nodes_for_tests:...``: put
    the repository root on their PYTHONPATH, whatever directory pytest runs from."""
    old = os.environ.get("PYTHONPATH")
    monkeypatch.setenv("PYTHONPATH", str(REPO) + (os.pathsep + old if old else ""))


def write_launch(folder: Path, nodes: list[dict], **top) -> Path:
    """A launch file in ``folder`` with run_dir ``folder/run`` unless given."""
    data = {"name": "t", "run_dir": str(folder / "run"), **top, "nodes": nodes}
    path = folder / "t.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


class Running:
    """A supervisor running in a background thread (so the test can act on its nodes)."""

    def __init__(self, config: LaunchConfig):
        self.out = io.StringIO()
        self.supervisor = Supervisor(config, stdout=self.out)
        self.code: int | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self.code = self.supervisor.run()

    def wait(self, timeout_s: float = 15.0) -> int:
        self.thread.join(timeout_s)
        if self.thread.is_alive():
            self.supervisor.request_stop()
            self.thread.join(10.0)
            pytest.fail(f"launch did not end within {timeout_s} s; output:\n{self.out.getvalue()}")
        return self.code


def run_launch(config: LaunchConfig, timeout_s: float = 15.0) -> tuple[int, str]:
    """Run to the end; (exit code, status output)."""
    running = Running(config)
    code = running.wait(timeout_s)
    return code, running.out.getvalue()
