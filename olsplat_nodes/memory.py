"""The process's memory, for the nodes and the offline runs alike (a small utility of the base
layer: it imports nothing of the package). ``release_free_memory`` hands freed heap back to the
operating system (the refiner after a pass). The peak resident set is resettable:
``olsplat eval`` reports each method's own peak (its aggregation and scoring), not the highest
of every method run before it in the process.

Linux keeps the peak as ``VmHWM`` in /proc/self/status; writing "5" to /proc/self/clear_refs
resets it to the current resident set. Elsewhere (or where /proc is not writable) the reset does
nothing and the peak is ``getrusage``'s, the process's peak since it started.
"""

from __future__ import annotations

import resource
from pathlib import Path


def reset_peak_rss() -> bool:
    """Start a new peak from the current resident set; False where that is not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """Peak resident set in MB since the last ``reset_peak_rss`` (or since the process started)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def release_free_memory() -> bool:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``); False where there
    is no glibc. A long-lived node that makes large temporaries from several threads (a refiner
    pass) otherwise keeps their freed pages in its resident set: the large flight's refiner sat
    ~300 MB higher between passes after its 150th view than before, with nothing more in use."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        return bool(libc.malloc_trim(0)) if libc is not None else False
    except (OSError, AttributeError):
        return False
