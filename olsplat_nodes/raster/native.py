"""The C heatmap compositing kernel (``native/heatmap_composite.c``), when it was built and runs here.

``setup.py`` builds it as an optional extension; this module loads it with ctypes. ``kernel()`` is
the library, or None when it is missing (no C compiler at install), was built for AVX2 on a CPU
without it, or ``OLSPLAT_NATIVE=0`` is set (what the tests use to run the numba kernel).
``rasterize`` then uses the numba kernel, which computes the same outputs.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
from functools import cache
from pathlib import Path

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_F = ctypes.c_float
# composite_heatmaps's parameters, in order (see the C file)
ARGUMENTS: list = [
    _P, _P, _P, _P, _I64, _P, _P, _I64, _P, _I64, _I64, _I64, _F, _F, _F, _P, _P, _I64, _P, _P, _P, _P, _P, _P,
    ctypes.c_int,
]  # fmt: skip


def _cpu_has(*flags: str) -> bool:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    have = next((line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), [])
    return all(flag in have for flag in flags)


@cache
def kernel() -> ctypes.CDLL | None:
    if os.environ.get("OLSPLAT_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec("olsplat_nodes.raster._heatmap_native")
    if spec is None or spec.origin is None:
        return None
    library = ctypes.CDLL(spec.origin)
    if library.built_with_avx2() and not _cpu_has("avx2", "fma"):
        return None
    library.composite_heatmaps.argtypes = ARGUMENTS
    library.composite_heatmaps.restype = ctypes.c_int
    return library
