"""Glue for the C heatmap compositing kernel (``olsplat_nodes/native/heatmap_composite.c``).

``available(tile)`` says whether ``rasterize`` can hand a view's heatmaps to it here (the
extension is built and loads: ``olsplat_nodes.native.library``); ``rasterize`` otherwise uses
the numba kernel, which computes the same outputs. ``composite_heatmaps`` passes ``rasterize``'s
records (``arguments.py``) to it, spread into the C function's flat parameter list. The C
kernel reads float32 or float16 feature tables.
"""

from __future__ import annotations

import ctypes

import numba
import numpy as np

from ..native import library
from .arguments import Canvas, Outputs, Splats, TileLists

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_F = ctypes.c_float
MAX_TILE = 64  # the C kernel's largest tile side (pixels)
# composite_heatmaps's parameters, in order (see the C file): the records of ``arguments.py``
# spread out, the C signature staying flat
ARGUMENTS: list = [
    *[_P, _P, _P, _P, _I64],  # TileLists: offsets, slots, order, tile_order, their length
    *[_P, _P, _I64, ctypes.c_int, _P],  # Splats: records, features, D, float16 or not, feature_rows
    *[_I64, _I64, _I64, _F, _F, _F, _P, _P, _I64],  # Canvas: width ... t_min, background, queries, Q
    *[_P, _P, _P, _P, _P, _P],  # Outputs: rgb, alpha, depth, features (the cosines), unit, evals
    ctypes.c_int,  # threads
]


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


def composite_heatmaps(splats: Splats, lists: TileLists, canvas: Canvas, out: Outputs) -> None:
    """The C kernel on ``rasterize``'s records (``arguments.py``; their arrays C-contiguous,
    int32 slots/order/feature_rows, int64 offsets/tile_order/evals, features float32 or
    float16, float32 otherwise; ``feature_rows`` and ``out.unit`` may be empty, the Top-K
    outputs are not read), on the caller's numba thread count. Raises MemoryError when a
    tile's buffers cannot be had."""
    loaded = kernel()
    assert loaded is not None, "composite_heatmaps needs available() first"
    features = splats.features
    assert features.dtype in (np.float32, np.float16), features.dtype
    colour = np.ascontiguousarray(canvas.background, np.float32)  # a name: alive through the call

    def address(array):
        assert array.flags.c_contiguous, "the C kernel needs C-contiguous arrays"
        return array.ctypes.data if array.size else None

    status = loaded.composite_heatmaps(
        # in ARGUMENTS's order, record by record
        *(address(lists.offsets), address(lists.slots), address(lists.order), address(lists.tile_order)),
        len(lists.tile_order),
        *(address(splats.records), address(features), features.shape[1], int(features.dtype == np.float16)),
        address(splats.feature_rows),
        *(canvas.width, canvas.height, canvas.tile_size, canvas.alpha_min, canvas.alpha_max, canvas.t_min),
        *(address(colour), address(canvas.queries), len(canvas.queries)),
        *(address(out.rgb), address(out.alpha), address(out.depth), address(out.features), address(out.unit)),
        address(out.evals),
        numba.get_num_threads(),
    )
    if status != 0:
        raise MemoryError("the heatmap kernel could not allocate its tile buffers")
