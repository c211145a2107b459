"""What ``bench graph`` reads of the nodes' processes: start-up from their logs, memory from /proc.

Shared by the graph run (``graph.py``) and the queries of a kept run (``requery.py``).
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Callable
from pathlib import Path

NODES = ("query_server", "ingest", "region_encoder", "accumulator", "refiner")

_READY = re.compile(r" (\S+) ready: ([0-9.]+) s after its process started")


def node_ready_s(logs: Path, latest: bool = False) -> dict[str, float]:
    """{node: seconds from its process's start to the end of its set-up}, each node's first
    start (``latest``: its latest), from the "ready" lines of the launch's node logs
    (``nodes.base.Node.run``)."""
    ready: dict[str, float] = {}
    for log_file in sorted(logs.glob("*.log")):
        for line in log_file.read_text(errors="replace").splitlines():
            found = _READY.search(line)
            if found and (latest or found[1] not in ready):
                ready[found[1]] = float(found[2])
    return ready


def process_memory(pid: int) -> dict[str, float]:
    """{rss_mb, peak_rss_mb, private_mb} of a live process from /proc (Linux); {} once it is gone."""
    values: dict[str, float] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                values["rss_mb" if key == "VmRSS" else "peak_rss_mb"] = int(rest.split()[0]) / 1024
        private = 0
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("Private_Clean", "Private_Dirty"):
                private += int(rest.split()[0])
        values["private_mb"] = private / 1024
    except (OSError, ValueError, IndexError):
        return {}
    return values


def process_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system, every thread) a live process has used, from /proc/PID/stat;
    None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime: fields 14, 15
    except (OSError, ValueError, IndexError):
        return None


class MemoryWatch:
    """Samples every node's memory, every ``every_s`` in a background thread (none when
    ``every_s`` is 0: then only the explicit ``sample()`` calls): per node the highest peak RSS
    seen (over restarts too) and a series of (views stored, rss_mb, private_mb)."""

    def __init__(self, pids: Callable[[], dict[str, int]], views_stored: Callable[[], int], every_s: float):
        self.pids, self.views_stored, self.every_s = pids, views_stored, every_s
        self.peak: dict[str, float] = {}
        self.series: dict[str, list[tuple[int, float, float]]] = {}
        self.flight_over = False  # after the final map: peaks still taken, the series stops
        self.cpu_s: dict[str, dict[int, float]] = {}  # node -> {pid: CPU seconds}: a restart's too
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="memory-watch", daemon=True)

    def start(self) -> None:
        if self.every_s > 0:
            self.thread.start()

    def _loop(self) -> None:
        while not self.stop.wait(self.every_s):
            self.sample()

    def sample(self) -> None:
        views = self.views_stored()
        for name, pid in self.pids().items():
            cpu = process_cpu_s(pid)
            if cpu is not None and not self.flight_over:
                self.cpu_s.setdefault(name, {})[pid] = cpu
            values = process_memory(pid)
            if values:
                self.peak[name] = max(self.peak.get(name, 0.0), values["peak_rss_mb"])
                if not self.flight_over:
                    self.series.setdefault(name, []).append((views, values["rss_mb"], values["private_mb"]))

    def node_cpu_s(self) -> dict[str, float]:
        """{node: CPU seconds its processes used until the last sample of the flight}."""
        return {name: sum(by_pid.values()) for name, by_pid in self.cpu_s.items()}

    def growth(self, name: str, views: int) -> float:
        """Resident MB at the last sample minus at the first sample once a quarter of the
        flight's ``views`` were stored (start-up, the first map and the first caches are
        behind by then: what is left is growth with the flight)."""
        series = [s for s in self.series.get(name, []) if s[0] >= max(1, views // 4)]
        return series[-1][1] - series[0][1] if series else 0.0
