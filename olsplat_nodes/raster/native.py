"""The C heatmap compositing kernel (``native/heatmap_composite.c``), when it was built and runs here.

``setup.py`` builds it as an optional extension; this module loads it with ctypes. ``kernel()`` is
the library, or None when it is missing (no C compiler at install), was built for AVX2 on a CPU
without it, or ``OLSPLAT_NATIVE=0`` is set (what the tests use to run the numba kernel).
``rasterize`` then uses the numba kernel, which computes the same outputs. ``composite_heatmaps``
passes ``rasterize``'s arrays to it.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
from functools import cache
from pathlib import Path

import numba
import numpy as np

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_F = ctypes.c_float
MAX_TILE = 64  # the C kernel's largest tile side (pixels)
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


def available(tile_size: int) -> bool:
    """Whether the C kernel can composite tiles of this size here."""
    return tile_size <= MAX_TILE and kernel() is not None


def composite_heatmaps(
    offsets, slots, order, tile_order, records, features, rows, width, height, tile_size, config,
    background, queries, out_rgb, out_alpha, out_depth, out_heat, out_unit, out_evals,
) -> None:  # fmt: skip
    """The C kernel on ``rasterize``'s arrays (its layouts: C-contiguous, int32 slots/order/rows,
    int64 offsets/tile_order/evals, float32 otherwise; ``rows`` and ``out_unit`` may be empty),
    on the caller's numba thread count. Raises MemoryError when a tile's buffers cannot be had."""
    library = kernel()
    assert library is not None, "composite_heatmaps needs available() first"
    colour = np.ascontiguousarray(background, np.float32)  # a name: alive through the call

    def address(array):
        assert array.flags.c_contiguous, "the C kernel needs C-contiguous arrays"
        return array.ctypes.data if array.size else None

    status = library.composite_heatmaps(
        address(offsets), address(slots), address(order), address(tile_order), len(tile_order),
        address(records), address(features), features.shape[1], address(rows), width, height, tile_size,
        config.alpha_min, config.alpha_max, config.transmittance_min, address(colour), address(queries), len(queries),
        address(out_rgb), address(out_alpha), address(out_depth), address(out_heat), address(out_unit),
        address(out_evals), numba.get_num_threads(),
    )  # fmt: skip
    if status != 0:
        raise MemoryError("the heatmap kernel could not allocate its tile buffers")
