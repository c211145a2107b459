"""Tile binning: for every 16x16 tile, the Gaussians that touch it, nearest first.

Gaussians are sorted by camera depth once (a stable radix sort on the float bits); a
counting sort by tile then keeps that order inside each tile's list, so no per-tile sort is
needed. Ties in depth keep map order. The sort's passes and both binning passes run in parallel
over chunks of their input; chunk c writes after chunks < c (in every digit's run, in every
tile), which keeps the order stable.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Chunks of a radix pass that run in parallel (more than the threads: even loads; the result
# does not depend on it)
RADIX_CHUNKS = 8


@njit(parallel=True, cache=True, nogil=True)
def radix_argsort(keys):
    """Stable argsort of non-negative float32 ``keys`` [M] (LSD radix, 3 passes of 11 bits).

    Non-negative IEEE floats order like their bit patterns read as unsigned integers. Each pass
    moves (key, index) pairs, so it reads its input in order and only its writes scatter (a pass
    that looked each key up through the order so far read the keys at random, a cache miss per
    key, which was most of a far view's sort); a pass whose digit is the same for every key (depths
    share their high bits) is skipped: it would not move anything. Each pass runs in parallel
    over ``RADIX_CHUNKS`` runs of its input, chunk c writing each digit's keys after those of
    chunks < c, which keeps the sort stable. Its reference: ``np.argsort(keys, kind="stable")``
    (tests)."""
    bits = keys.view(np.uint32)
    n = bits.shape[0]
    every = np.zeros((3, 2048), np.int64)  # per pass, keys per digit
    for i in range(n):
        b = bits[i]
        every[0, b & 2047] += 1
        every[1, (b >> 11) & 2047] += 1
        every[2, (b >> 22) & 2047] += 1
    key_in = bits.copy()
    key_out = np.empty(n, np.uint32)
    order = np.arange(n).astype(np.int32)
    scratch = np.empty(n, np.int32)
    bounds = np.linspace(0, n, RADIX_CHUNKS + 1).astype(np.int64)
    for p in range(3):
        if every[p].max() == n:  # one digit for every key: the order stays
            continue
        shift = 11 * p
        starts = np.zeros((RADIX_CHUNKS, 2048), np.int64)
        for c in prange(RADIX_CHUNKS):
            for i in range(bounds[c], bounds[c + 1]):
                starts[c, (key_in[i] >> shift) & 2047] += 1
        at = 0
        for digit in range(2048):  # counts -> where each chunk's keys of each digit go
            for c in range(RADIX_CHUNKS):
                here = starts[c, digit]
                starts[c, digit] = at
                at += here
        for c in prange(RADIX_CHUNKS):
            for i in range(bounds[c], bounds[c + 1]):
                b = key_in[i]
                digit = (b >> shift) & 2047
                w = starts[c, digit]
                key_out[w] = b
                scratch[w] = order[i]
                starts[c, digit] = w + 1
        key_in, key_out = key_out, key_in
        order, scratch = scratch, order
    return order


@njit(parallel=True, cache=True, nogil=True)
def _bin_sorted(rects, n_chunks, tiles_x, n_tiles):
    """rects [M, 4] tile rectangles in depth order -> (offsets [n_tiles + 1], positions into rects)."""
    m = rects.shape[0]
    bounds = np.linspace(0, m, n_chunks + 1).astype(np.int64)
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for i in range(bounds[c], bounds[c + 1]):
            for ty in range(rects[i, 1], rects[i, 3]):
                for tx in range(rects[i, 0], rects[i, 2]):
                    counts[c, ty * tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    cursors = np.empty((n_chunks, n_tiles), np.int64)
    for t in range(n_tiles):
        position = offsets[t]
        for c in range(n_chunks):
            cursors[c, t] = position
            position += counts[c, t]
        offsets[t + 1] = position
    slots = np.empty(offsets[n_tiles], np.int32)
    for c in prange(n_chunks):
        for i in range(bounds[c], bounds[c + 1]):
            for ty in range(rects[i, 1], rects[i, 3]):
                for tx in range(rects[i, 0], rects[i, 2]):
                    tile = ty * tiles_x + tx
                    slots[cursors[c, tile]] = i
                    cursors[c, tile] += 1
    return offsets, slots


def bin_tiles(
    depths: np.ndarray,  # [N] float32 camera z
    radii: np.ndarray,  # [N] int32, 0 = culled
    tile_rects: np.ndarray,  # [N, 4] int32 (tx0, ty0, tx1, ty1)
    tiles_x: int,
    tiles_y: int,
    n_chunks: int = 8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns (order [M] int32, offsets [tiles_x * tiles_y + 1] int64, slots [n_intersections] int32).

    ``order`` lists the M visible Gaussians front to back (map indices). The Gaussians of tile t
    (row-major, t = ty * tiles_x + tx) are order[slots[offsets[t]:offsets[t+1]]], front to back;
    slots index ``order``, so data gathered in that order is read nearly sequentially.
    """
    visible = np.flatnonzero(radii > 0).astype(np.int32)
    order = _take(visible, radix_argsort(np.ascontiguousarray(depths[visible])))
    offsets, slots = _bin_sorted(_take_rows(tile_rects, order), n_chunks, tiles_x, tiles_x * tiles_y)
    return order, offsets, slots


# Random gathers in parallel: numpy's fancy indexing runs them on one thread, and a gather of
# scattered rows is bound by its cache misses, which the threads wait for side by side.
@njit(parallel=True, cache=True, nogil=True)
def _take(values, index):
    """values[index] for 1-D arrays."""
    out = np.empty(index.shape[0], values.dtype)
    for i in prange(index.shape[0]):
        out[i] = values[index[i]]
    return out


@njit(parallel=True, cache=True, nogil=True)
def _take_rows(values, index):
    """values[index] for a 2-D array: the rows index lists."""
    out = np.empty((index.shape[0], values.shape[1]), values.dtype)
    for i in prange(index.shape[0]):
        for k in range(values.shape[1]):
            out[i, k] = values[index[i], k]
    return out
