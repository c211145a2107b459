"""Glue for the C Top-K compositing kernel (``olsplat_nodes/native/topk_composite.c``).

``available(tile, k)`` says whether ``rasterize`` can hand a render without features to it
here (the extension is built and loads: ``olsplat_nodes.native.library``, and k <= ``MAX_K``);
``rasterize`` otherwise uses the numba kernel, which keeps the same Top-K. ``composite_topk``
passes ``rasterize``'s arrays to it.
"""

from __future__ import annotations

import ctypes

import numba
import numpy as np

from ..native import library
from .config import RasterConfig

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_I32 = ctypes.c_int32
_F = ctypes.c_float
MAX_TILE = 64  # the C kernel's largest tile side (pixels)
MAX_K = 32  # its largest Top-K (topk_max): the ranking network's size
# composite_topk's parameters, in order (see the C file)
ARGUMENTS: list = [
    _P, _P, _P, _P, _I64, _P, _I64, _I64, _I64, _F, _F, _F, _I32, _I32, ctypes.c_double, _P,
    _P, _P, _P, _P, _P, _P, ctypes.c_int,
]  # fmt: skip


def kernel():
    """The loaded C library with ``composite_topk`` typed, or None."""
    loaded = library()
    if loaded is not None and loaded.composite_topk.argtypes != ARGUMENTS:
        loaded.composite_topk.argtypes = ARGUMENTS
        loaded.composite_topk.restype = ctypes.c_int
    return loaded


def available(tile_size: int, k_cap: int) -> bool:
    """Whether the C kernel can composite tiles of this size with this Top-K (0: none) here."""
    return tile_size <= MAX_TILE and k_cap <= MAX_K and kernel() is not None


def composite_topk(
    offsets, slots, order, tile_order, records, width, height, tile_size, config: RasterConfig, k_cap: int,
    background, out_rgb, out_alpha, out_depth, out_topk_ids, out_topk_weights, out_evals,
) -> None:  # fmt: skip
    """The C kernel on ``rasterize``'s arrays (C-contiguous; int32 slots/order/ids, int64
    offsets/tile_order/evals, float32 otherwise; the Top-K outputs [H, W, k_cap], k_cap 0 for a
    plain render), on the caller's numba thread count. Raises MemoryError when a tile's
    buffers cannot be had."""
    loaded = kernel()
    assert loaded is not None, "composite_topk needs available() first"
    colour = np.ascontiguousarray(background, np.float32)  # a name: alive through the call

    def address(array):
        assert array.flags.c_contiguous, "the C kernel needs C-contiguous arrays"
        return array.ctypes.data if array.size else None

    status = loaded.composite_topk(
        address(offsets), address(slots), address(order), address(tile_order), len(tile_order),
        address(records), width, height, tile_size, config.alpha_min, config.alpha_max, config.transmittance_min,
        k_cap, config.topk_min, config.topk_coverage, address(colour), address(out_rgb), address(out_alpha),
        address(out_depth), address(out_topk_ids), address(out_topk_weights), address(out_evals),
        numba.get_num_threads(),
    )  # fmt: skip
    if status != 0:
        raise MemoryError("the Top-K kernel could not allocate its tile buffers")
