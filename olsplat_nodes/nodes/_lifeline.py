"""A node process dies with its launcher: orphaned nodes would keep the graph's ports and answer
for a launch that no longer exists.

The launcher puts its pid in ``OLSPLAT_LAUNCHER_PID`` of each child's environment. The child
asks the kernel for SIGKILL when its parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``), then
checks that its parent is still that pid (the launcher may have died between fork and prctl,
and then no signal would ever come: the node takes its normal stop path at once).

Why SIGKILL and not a graceful SIGTERM: the launcher stops its nodes itself with SIGTERM on
every orderly end (Ctrl-C, SIGTERM, a node giving up); the parent-death signal fires only when
the launcher died abruptly (``kill -9``, out of memory). Then nobody supervises the node, and a
graceful stop is not bounded: a Python signal handler runs only between bytecodes, so a node
inside a long numba or ONNX call (seconds on a loaded machine) kept the query port for that
long. Every node's output is durable against SIGKILL already (atomic writes; the power-cut
tests kill each node mid-flight), so the kernel's SIGKILL loses nothing and ends the node at
once. Where prctl is not available, a daemon thread polls ``os.getppid()`` and takes the
graceful stop path instead.

The kernel sends the signal when the *thread* that forked the child ends, not the process: the
supervisor starts every child from the one thread that runs its loop, which lives as long as
the launch.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import signal
import sys
import threading

LAUNCHER_PID_ENV = "OLSPLAT_LAUNCHER_PID"
_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_WATCH_PERIOD_S = 0.5

log = logging.getLogger(__name__)


def die_with_launcher(on_orphaned) -> str:
    """Arrange for ``on_orphaned()`` (the node's stop) when the launcher named in the environment
    dies: how it was arranged ("prctl", "watchdog", "" when no launcher is named). When the
    launcher is already gone, ``on_orphaned`` is called at once."""
    expected = os.environ.get(LAUNCHER_PID_ENV, "")
    if not expected.isdigit():
        return ""
    parent = int(expected)
    how = "prctl" if _set_pdeathsig(signal.SIGKILL) else "watchdog"
    if os.getppid() != parent:  # the launcher died before prctl took effect: no signal will come
        log.error("launcher (pid %d) is gone: stopping", parent)
        on_orphaned()
        return how
    if how == "watchdog":
        threading.Thread(target=_watch, args=(parent, on_orphaned), name="olsplat-lifeline", daemon=True).start()
    return how


def _set_pdeathsig(sig: int) -> bool:
    """``prctl(PR_SET_PDEATHSIG, sig)``; False where there is no such call (not Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent: int, on_orphaned) -> None:
    stopped = threading.Event()
    while not stopped.wait(_WATCH_PERIOD_S):
        if os.getppid() != parent:
            log.error("launcher (pid %d) is gone: stopping", parent)
            on_orphaned()
            return
