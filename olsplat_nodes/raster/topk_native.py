"""Glue for the C Top-K compositing kernel (``olsplat_nodes/native/topk_composite.c``).

``available(tile, k)`` says whether ``rasterize`` can hand a render without features to it
here (the extension is built and loads: ``olsplat_nodes.native.library``, and k <= ``MAX_K``);
``rasterize`` otherwise uses the numba kernel, which keeps the same Top-K. ``composite_topk``
passes ``rasterize``'s records (``arguments.py``) to it, spread into the C function's flat
parameter list.
"""

from __future__ import annotations

import ctypes

import numba
import numpy as np

from ..native import library
from .arguments import Canvas, Outputs, Splats, TileLists, TopK

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_I32 = ctypes.c_int32
_F = ctypes.c_float
MAX_TILE = 64  # the C kernel's largest tile side (pixels)
MAX_K = 32  # its largest Top-K (topk_max): the ranking network's size
# composite_topk's parameters, in order (see the C file): the records of ``arguments.py``
# spread out, the C signature staying flat
ARGUMENTS: list = [
    *[_P, _P, _P, _P, _I64],  # TileLists: offsets, slots, order, tile_order, their length
    _P,  # Splats: records
    *[_I64, _I64, _I64, _F, _F, _F],  # Canvas: width, height, tile_size, alpha_min, alpha_max, t_min
    *[_I32, _I32, ctypes.c_double],  # TopK: k_cap, topk_min, coverage
    _P,  # Canvas: background
    *[_P, _P, _P, _P, _P, _P],  # Outputs: rgb (NULL: no colour), alpha, depth, topk_ids, topk_weights, evals
    _P,  # map_ids: the Gaussians' indices of a culled projection's rows (NULL: rows are indices)
    ctypes.c_int,  # threads
]


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
    splats: Splats, lists: TileLists, canvas: Canvas, topk: TopK, out: Outputs, map_ids: np.ndarray | None = None
) -> None:
    """The C kernel on ``rasterize``'s records (``arguments.py``; their arrays C-contiguous,
    int32 slots/order/topk_ids, int64 offsets/tile_order/evals, float32 otherwise; the Top-K
    outputs [H, W, topk.k_cap], k_cap 0 for a plain render; the features are not read: a render
    without them), on the caller's numba thread count. An empty ``out.rgb``: no colour (its sums
    skipped). ``map_ids`` [M] int64: the records are the rows of a culled projection and the
    Top-K ids are written as map_ids[row]. Raises MemoryError when a tile's buffers cannot be had."""
    loaded = kernel()
    assert loaded is not None, "composite_topk needs available() first"
    colour = np.ascontiguousarray(canvas.background, np.float32)  # a name: alive through the call
    ids = None if map_ids is None else np.ascontiguousarray(map_ids, np.int64)  # likewise

    def address(array):
        assert array.flags.c_contiguous, "the C kernel needs C-contiguous arrays"
        return array.ctypes.data if array.size else None

    status = loaded.composite_topk(
        # in ARGUMENTS's order, record by record
        *(address(lists.offsets), address(lists.slots), address(lists.order), address(lists.tile_order)),
        len(lists.tile_order),
        address(splats.records),
        *(canvas.width, canvas.height, canvas.tile_size, canvas.alpha_min, canvas.alpha_max, canvas.t_min),
        *(topk.k_cap, topk.topk_min, topk.coverage),
        address(colour),
        *(address(out.rgb), address(out.alpha), address(out.depth), address(out.topk_ids)),
        *(address(out.topk_weights), address(out.evals)),
        None if map_ids is None else address(ids),
        numba.get_num_threads(),
    )
    if status != 0:
        raise MemoryError("the Top-K kernel could not allocate its tile buffers")
