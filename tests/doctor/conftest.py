"""Shared by the pre-flight tests: the installed ``olsplat`` run as a subprocess (as an operator
runs it), and the ``--set`` arguments that point the shipped ``replay`` launch at the tiny
generated flight (``tiny``, tests/conftest.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

OLSPLAT = Path(sys.executable).parent / "olsplat"  # the console script of this environment


def run_olsplat(*args: str, cwd: Path | None = None, env: dict | None = None, timeout: float = 120):
    """``olsplat ARGS`` in a subprocess: the CompletedProcess (text output)."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run([str(OLSPLAT), *args], cwd=cwd, env=full_env, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


def rows_of(json_file: Path) -> dict[str, dict]:
    """``doctor --json``'s rows by name."""
    return {row["name"]: row for row in json.loads(json_file.read_text())["rows"]}


@pytest.fixture(scope="session")
def replay_sets(tiny) -> list[str]:
    """``--set`` arguments of the shipped replay launch for the tiny flight (absolute paths)."""
    scene, _ = tiny
    ply = scene / "map" / "point_cloud.ply"
    sets = [f"ingest.source={scene / 'replay.mcap'}"]
    sets += [f"{node}.map={ply}" for node in ("query_server", "accumulator", "refiner")]
    return [word for item in sets for word in ("--set", item)]
