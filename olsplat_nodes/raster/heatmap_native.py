"""Glue for the C heatmap compositing kernel (``olsplat_nodes/native/heatmap_composite.c``).

``available(tile)`` says whether ``rasterize`` can hand a view's heatmaps to it here (the
extension is built and loads: ``olsplat_nodes.native.library``); ``rasterize`` otherwise uses
the numba kernel, which computes the same outputs. ``composite_heatmaps`` passes ``rasterize``'s
arrays to it. The C kernel reads float32 or float16 feature tables.
"""

from __future__ import annotations

import ctypes

import numba
import numpy as np

from ..native import library

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_F = ctypes.c_float
MAX_TILE = 64  # the C kernel's largest tile side (pixels)
# composite_heatmaps's parameters, in order (see the C file)
ARGUMENTS: list = [
    _P, _P, _P, _P, _I64, _P, _P, _I64, ctypes.c_int, _P, _I64, _I64, _I64, _F, _F, _F, _P, _P, _I64,
    _P, _P, _P, _P, _P, _P, ctypes.c_int,
]  # fmt: skip


def kernel():
    """The loaded C library with ``composite_heatmaps`` typed, or None."""
    loaded = library()
    if loaded is not None and loaded.composite_heatmaps.argtypes != ARGUMENTS:
        loaded.composite_heatmaps.argtypes = ARGUMENTS
        loaded.composite_heatmaps.restype = ctypes.c_int
    return loaded


def available(tile_size: int) -> bool:
    """Whether the C kernel can composite tiles of this size here."""
    return tile_size <= MAX_TILE and kernel() is not None


def composite_heatmaps(
    offsets, slots, order, tile_order, records, features, rows, width, height, tile_size, config,
    background, queries, out_rgb, out_alpha, out_depth, out_heat, out_unit, out_evals,
) -> None:  # fmt: skip
    """The C kernel on ``rasterize``'s arrays (its layouts: C-contiguous, int32 slots/order/rows,
    int64 offsets/tile_order/evals, features float32 or float16, float32 otherwise; ``rows`` and
    ``out_unit`` may be empty), on the caller's numba thread count. Raises MemoryError when a
    tile's buffers cannot be had."""
    loaded = kernel()
    assert loaded is not None, "composite_heatmaps needs available() first"
    assert features.dtype in (np.float32, np.float16), features.dtype
    colour = np.ascontiguousarray(background, np.float32)  # a name: alive through the call

    def address(array):
        assert array.flags.c_contiguous, "the C kernel needs C-contiguous arrays"
        return array.ctypes.data if array.size else None

    status = loaded.composite_heatmaps(
        address(offsets), address(slots), address(order), address(tile_order), len(tile_order),
        address(records), address(features), features.shape[1], int(features.dtype == np.float16), address(rows),
        width, height, tile_size, config.alpha_min, config.alpha_max, config.transmittance_min, address(colour),
        address(queries), len(queries), address(out_rgb), address(out_alpha), address(out_depth), address(out_heat),
        address(out_unit), address(out_evals), numba.get_num_threads(),
    )  # fmt: skip
    if status != 0:
        raise MemoryError("the heatmap kernel could not allocate its tile buffers")
