"""Pre-flight checks: what a flight needs from the machine and from its launch, as rows of a
table (``Row``: name, ok / warn / blocker, the figure, the fix in one line).

``machine_rows()`` checks the flight computer (Python, cores, CPU features, the C kernels,
numba's cache, onnxruntime, the shipped models' checksums, the clock); ``launch_rows(...)``
one launch (the file and every node's params, memory, input files, optional extras, camera,
MAVLink port, CURVE keys, disk space for the flight, TCP ports, ipc:// paths). ``olsplat
doctor`` prints both, ``olsplat launch --check`` the launch's. Nothing here starts a node or
opens a ZeroMQ socket; the checks read files, /proc and /sys, bind and close a plain socket per
TCP port, and list DepthAI devices.
"""

from __future__ import annotations

from collections.abc import Sequence

from ._launch import (
    LaunchPlan,
    camera_rows,
    extra_rows,
    input_rows,
    key_rows,
    launch_file,
    mavlink_rows,
    memory,
    plan_launch,
)
from ._machine import (
    clock_source,
    clock_sync,
    cores,
    cpu_features,
    native_kernels,
    onnxruntime_providers,
    python_version,
)
from ._models import model_folder, shipped_model_folders
from ._numba_cache import numba_cache
from ._resources import disk, ipc_paths, port_rows
from ._row import Row, blocked, format_table, write_json

DEFAULT_MINUTES = 30.0  # a multirotor's battery, rounded up


def numba_settings(plan: LaunchPlan | None) -> frozenset[str]:
    """The tags of ``_numba_cache.CONDITIONAL`` that are on: "no-native" without the C kernels,
    "codebook" for a refiner writing a codebook map."""
    from ...native import library

    tags = set() if library() is not None else {"no-native"}
    if plan is not None:
        for name, params in plan.params.items():
            exec_name = plan.config.node(name).exec
            if exec_name == "refiner" and int(params.get("codebook") or 0) > 0:
                tags.add("codebook")
    return frozenset(tags)


def machine_rows(plan: LaunchPlan | None = None) -> list[Row]:
    """The flight computer's rows (``plan``: the launch whose settings decide which optional
    kernels numba's cache must hold)."""
    return [
        python_version(),
        cores(),
        cpu_features(),
        native_kernels(),
        numba_cache(settings=numba_settings(plan)),
        onnxruntime_providers(),
        *(model_folder(folder) for folder in shipped_model_folders()),
        clock_source(),
        clock_sync(),
    ]


def launch_rows(
    name_or_file: str,
    overrides: Sequence[str] = (),
    run_dir: str | None = None,
    minutes: float = DEFAULT_MINUTES,
    rate_hz: float | None = None,
) -> tuple[list[Row], LaunchPlan | None]:
    """One launch's rows, and its plan (None when the file or a param is invalid: then the
    first row is that blocker and no other launch row can be made)."""
    row, plan = launch_file(name_or_file, overrides, run_dir)
    if plan is None:
        return [row], None
    rows = [row, memory(plan), *input_rows(plan), *extra_rows(plan), *camera_rows(plan), *key_rows(plan)]
    rows += mavlink_rows(plan)
    rows += [r for r in (disk(plan, minutes, rate_hz), ipc_paths(plan)) if r is not None]
    rows += port_rows(plan)
    return rows, plan


__all__ = [
    "DEFAULT_MINUTES",
    "LaunchPlan",
    "Row",
    "blocked",
    "format_table",
    "launch_rows",
    "machine_rows",
    "plan_launch",
    "write_json",
]
