"""The compositing kernels' arguments, grouped in typed records.

``rasterize`` hands every compositing kernel the same few records: the numba kernel
(``composite.composite_tiles``) takes them as they are (numba compiles a ``NamedTuple`` of
arrays and scalars into a struct; the kernel reads its fields once, before its loops), and the
C kernels' wrappers (``heatmap_native.composite_heatmaps``, ``topk_native.composite_topk``)
spread them into the C functions' flat parameter lists.

The scalar fields keep the types the kernels were always given (Python ints and floats, i.e.
int64 and float64 in numba): the kernels narrow them to float32 where their loops need it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Splats(NamedTuple):
    """The projected Gaussians and what each one renders."""

    records: np.ndarray  # [M, RECORD] float32: one 64-byte record per Gaussian (``project.RECORD``)
    features: np.ndarray  # [N', D] float32 (float16 for the C heatmap kernel); D = 0: no features
    feature_rows: np.ndarray  # [M] int32: Gaussian g renders features[feature_rows[g]] (-1: 0); empty: row g


class TileLists(NamedTuple):
    """``binning.bin_tiles``'s output and the order the tiles are worked in: the Gaussians of
    tile t, front to back, are order[slots[offsets[t]:offsets[t + 1]]]."""

    order: np.ndarray  # [V] int32 rows of ``Splats.records``, front to back
    offsets: np.ndarray  # [T + 1] int64
    slots: np.ndarray  # [I] int32 positions in ``order``
    tile_order: np.ndarray  # [T] int64 the tiles in the order they are handed to the threads


class Canvas(NamedTuple):
    """The image the kernel fills and the rule it blends by (``RasterConfig``'s)."""

    width: int
    height: int
    tile_size: int
    alpha_min: float
    alpha_max: float
    t_min: float  # transmittance_min
    feature_eps: float
    background: np.ndarray  # [3] float32 RGB
    queries: np.ndarray  # [Q, D] float32: Q > 0 renders each pixel's cosine with them; Q = 0 the features


class TopK(NamedTuple):
    """The per-pixel adaptive Top-K (``RasterConfig``'s)."""

    k_cap: int  # entries kept per pixel at most (topk_max); 0: no Top-K
    topk_min: int
    coverage: float  # topk_coverage


class Outputs(NamedTuple):
    """The arrays the kernel writes (allocated by the caller; every entry is written)."""

    rgb: np.ndarray  # [H, W, 3] float32
    alpha: np.ndarray  # [H, W] float32
    depth: np.ndarray  # [H, W] float32
    features: np.ndarray  # [H, W, D] float32, or [H, W, Q] cosines with ``Canvas.queries``
    topk_ids: np.ndarray  # [H, W, k_cap] int32
    topk_weights: np.ndarray  # [H, W, k_cap] float32
    evals: np.ndarray  # [T, 2] int64 per tile: pairs evaluated, pairs a per-pixel list loop evaluates
    unit: np.ndarray  # [H * W, D] float32 F / |F| with queries (no rows: not written)
