"""The process memory helpers: the peak resident set and its reset, and handing freed heap
pages back (``release_free_memory``), which the refiner calls after every pass."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np

from olsplat_nodes.memory import release_free_memory


def _resident_mb() -> float:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) / 1024 for line in status if line.startswith("VmRSS:"))


def test_the_peak_follows_a_large_array_and_resets():
    """In a fresh process (the test run's own heap and peak are whatever the tests before left)."""
    script = """
import numpy as np
from olsplat_nodes.memory import peak_rss_mb, reset_peak_rss
assert reset_peak_rss()
before = peak_rss_mb()
block = np.ones(64 * 2**20 // 8)  # 64 MB, touched
grown = peak_rss_mb()
del block
assert reset_peak_rss()
print(before, grown, peak_rss_mb())
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    before, grown, after = (float(x) for x in done.stdout.split())
    assert grown >= before + 60 and after < before + 30


def test_freed_heap_pages_go_back_to_the_system():
    """Many small arrays made in a thread (its own malloc arena) and freed but one in eight: the
    arena keeps the freed pages resident until ``release_free_memory``."""
    kept: list[np.ndarray] = []

    def fill() -> None:
        blocks = [np.ones(8_000) for _ in range(20_000)]  # 64 KB each, 1.3 GB in all: heap, not mmap
        kept.extend(blocks[::8])

    worker = threading.Thread(target=fill)
    worker.start()
    worker.join()
    held = _resident_mb()
    assert release_free_memory()
    assert _resident_mb() < held - 500  # ~1.1 GB of the 1.3 GB was freed
    assert len(kept) == 2_500
