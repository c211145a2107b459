"""Tile binning: for every 16x16 tile, the Gaussians that touch it, nearest first.

Gaussians are sorted by camera depth once; a counting sort by tile then keeps that order
inside each tile's list (stable), so no per-tile sort is needed. Ties in depth keep map order.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _bin_sorted(order, tile_rects, tiles_x, n_tiles):
    counts = np.zeros(n_tiles + 1, np.int64)
    for g in order:
        for ty in range(tile_rects[g, 1], tile_rects[g, 3]):
            for tx in range(tile_rects[g, 0], tile_rects[g, 2]):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    cursor = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int32)
    for g in order:
        for ty in range(tile_rects[g, 1], tile_rects[g, 3]):
            for tx in range(tile_rects[g, 0], tile_rects[g, 2]):
                tile = ty * tiles_x + tx
                ids[cursor[tile]] = g
                cursor[tile] += 1
    return offsets, ids


def bin_tiles(
    depths: np.ndarray,  # [N] float32 camera z
    radii: np.ndarray,  # [N] int32, 0 = culled
    tile_rects: np.ndarray,  # [N, 4] int32 (tx0, ty0, tx1, ty1)
    tiles_x: int,
    tiles_y: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns (offsets [tiles_x * tiles_y + 1] int64, ids [n_intersections] int32).

    The Gaussians of tile t (row-major, t = ty * tiles_x + tx) are ids[offsets[t]:offsets[t+1]],
    front to back.
    """
    visible = np.flatnonzero(radii > 0).astype(np.int32)
    order = visible[np.argsort(depths[visible], kind="stable")]
    return _bin_sorted(order, tile_rects, tiles_x, tiles_x * tiles_y)
