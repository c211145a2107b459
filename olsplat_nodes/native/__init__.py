"""olsplat's compiled kernels: C files built by ``setup.py`` into one optional extension,
``olsplat_nodes.native._kernels``, and loaded here with ctypes.

- ``heatmap_composite.c``: a view's cosine heatmaps (glue: ``raster/heatmap_native.py``);
- ``topk_composite.c``: a view's render with the per-pixel Top-K, the accumulator's (glue:
  ``raster/topk_native.py``);
- ``winning_rows.c``: the relevance rule over a float16 table (glue: ``query/winners.py``);
- ``tile_pass.h``: what the two compositing kernels share (records, a Gaussian's pixel box, the
  vectorized pass over a row of it); ``simd.h``: float16 bits to float, a register's sum;
- ``module.c``: the (empty) Python module that makes setuptools build them, and the build's flags.

``library()`` is the loaded library, or None when the extension is missing (no C compiler at
install), was built for AVX2 on a CPU without it, or ``OLSPLAT_NATIVE=0`` is set (what the tests
use to run the numba kernels). Every caller then falls back to numba, which computes the same
outputs (float16 tables are then widened to float32 first: ``query.answer.QueryFeatures.of``).
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
from functools import cache
from pathlib import Path


def cpu_has(*flags: str) -> bool:
    """Whether /proc/cpuinfo lists every one of these CPU flags (False where it cannot be read)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    have = next((line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), [])
    return all(flag in have for flag in flags)


@cache
def library() -> ctypes.CDLL | None:
    """The compiled kernels, or None (see the module's docstring)."""
    if os.environ.get("OLSPLAT_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec("olsplat_nodes.native._kernels")
    if spec is None or spec.origin is None:
        return None
    loaded = ctypes.CDLL(spec.origin)
    if loaded.built_with_avx2() and not cpu_has("avx2", "fma", "f16c"):
        return None
    return loaded
