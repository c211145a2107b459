"""Front-to-back alpha compositing per tile, with the per-pixel adaptive Top-K.

One tile is one unit of parallel work. Inside a tile the loop runs Gaussian by Gaussian
(front to back) and, for each, only over the pixels of the box where its alpha can reach
alpha_min (its record's ``EX``, ``EY``): pixels outside that box would be skipped by the alpha
test anyway, so the result is the same as testing every pixel of the tile, at a fraction of the
work.

Per pixel, a contribution of Gaussian g is w = alpha_g * T with T the transmittance before g.
The pixel keeps an unsorted list of its best ``topk_max`` contributions: while the list is
full, a new contribution replaces the last-ranked entry when it ranks higher (rank: larger w
first, the nearer Gaussian first on ties). At the end the list is sorted once, and the
adaptive K is the smallest k whose cumulative weight reaches ``topk_coverage`` of the pixel's
total weight (1 - T_final), clamped to [topk_min, topk_max] and to the number of contributors.

Each Gaussian is one 64-byte record (``project.RECORD``), so it costs one cache line; a tile
copies its records in chunks into a small buffer before compositing them (see ``CHUNK``), and
asks for the next chunk's records and feature rows ahead (``prefetch.prefetch``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._network32 import sort_descending
from .prefetch import prefetch
from .project import BLUE, CA, CB, CC, CUT, DEPTH, EX, EY, GREEN, MX, MY, OPACITY, RECORD, RED, pixel_box


@njit(cache=True, inline="always")
def rank_key(w, s, scratch, scratch_bits):
    """uint64 key of contribution (w >= 0, depth-order position s): the weight's bits (a float
    >= 0 orders like its bits) above the inverted position, so a larger key ranks first (larger
    weight first, the nearer Gaussian first on ties). Numba has no scalar bit cast: w goes
    through ``scratch``, a 1-element float32 array, and ``scratch_bits``, its uint32 view (made
    once by the caller: a view per call costs reference counting). Padding keys are 0."""
    scratch[0] = w
    return (np.uint64(scratch_bits[0]) << np.uint64(32)) | np.uint64(0xFFFFFFFF - s)


@njit(cache=True, inline="always")
def _smallest(keys, n):
    """Index of the smallest of keys[:n] (keys are distinct: positions are)."""
    low = keys[0]
    for k in range(1, n):  # a min reduction, which vectorizes, then one compare per entry
        low = min(low, keys[k])
    for k in range(n):
        if keys[k] == low:
            return k
    return 0


@njit(cache=True, inline="always")
def offer(keys, top_n, top_last, p, key, k_cap):
    """Offer ``key`` to pixel p's unsorted list keys [k_cap]: appended while there is room, else
    it replaces the smallest key when larger (ties cannot happen: positions differ)."""
    n = top_n[p]
    if n < k_cap:
        keys[n] = key
        top_n[p] = n + 1
        if n + 1 == k_cap:
            top_last[p] = _smallest(keys, k_cap)
    elif key > keys[top_last[p]]:
        keys[top_last[p]] = key
        top_last[p] = _smallest(keys, k_cap)


@njit(cache=True)
def rank(keys, n, scratch):
    """Sort keys[:n] largest first, in place. Up to 32 keys: the unrolled 32-input network
    (``sorting_network``) on ``scratch`` [32], padded with 0; more: numba's sort."""
    if n <= 32:
        for i in range(n):
            scratch[i] = keys[i]
        for i in range(n, 32):
            scratch[i] = np.uint64(0)
        sort_descending(scratch)
        for i in range(n):
            keys[i] = scratch[i]
    else:
        ordered = np.sort(keys[:n])
        for i in range(n):
            keys[i] = ordered[n - 1 - i]


# A tile's records are scattered over the map's record array (its Gaussians are a sparse subset
# of the map). Copying them CHUNK at a time in a tight loop of independent loads lets the core
# overlap the cache misses, which the compositing loop, one long dependent chain per record,
# cannot: on a large map most records miss the cache, and waiting for them one at a time was
# a good part of compositing. Records past the tile's saturation are copied for nothing, at
# most CHUNK - 1 of them.
CHUNK = 64


@njit(parallel=True, cache=True, fastmath=True)
def composite_tiles(splats, lists, canvas, topk, out):
    """Composite every tile: ``splats``, ``lists``, ``canvas``, ``topk`` and ``out`` are the
    records of ``arguments.py`` (Splats, TileLists, Canvas, TopK, Outputs). Gaussian g's
    feature is splats.features[g], or with feature_rows (when it has entries)
    features[feature_rows[g]] (a codebook's centres), zero where the row is -1. With queries
    [Q, D] (Q > 0) out.features [H, W, Q] receives the cosine of each pixel's rendered feature
    with each query row instead of the feature itself (a heatmap without the [H, W, D] feature
    image); else out.features is [H, W, D]. With queries, out.unit [H * W, D] (when it has
    rows) also receives the unit rendered feature F / |F| of each pixel (a row of 0 where
    nothing was rendered). Top-K with topk.k_cap > 0 (its largest K), none with 0."""
    # The fields as local names, read once here, one per statement: the parallel loop below sees
    # plain arrays and scalars under their own names, and numba sorts the loop's arguments by
    # name, so the loop compiles to the instructions it had when these were the kernel's
    # parameters (unpacked several to a statement they get temporary names, another argument
    # order, another register allocation).
    records = splats.records
    features = splats.features
    feature_rows = splats.feature_rows
    offsets = lists.offsets
    slots = lists.slots
    order = lists.order
    tile_order = lists.tile_order
    width = canvas.width
    height = canvas.height
    tile_size = canvas.tile_size
    feature_eps = canvas.feature_eps
    background = canvas.background
    queries = canvas.queries
    k_cap = topk.k_cap
    topk_min = topk.topk_min
    topk_coverage = topk.coverage
    out_rgb = out.rgb
    out_alpha = out.alpha
    out_depth = out.depth
    out_features = out.features
    out_topk_ids = out.topk_ids
    out_topk_weights = out.topk_weights
    out_evals = out.evals
    out_unit = out.unit
    tiles_x = (width + tile_size - 1) // tile_size
    n_feat = features.shape[1]
    n_pix = tile_size * tile_size
    # float32 throughout the hot loop: mixing in float64 constants would promote it
    alpha_min, alpha_max, t_min = np.float32(canvas.alpha_min), np.float32(canvas.alpha_max), np.float32(canvas.t_min)
    one, half = np.float32(1.0), np.float32(0.5)
    for work in prange(tile_order.shape[0]):
        tile = tile_order[work]
        x_start = (tile % tiles_x) * tile_size
        y_start = (tile // tiles_x) * tile_size
        x_end = min(x_start + tile_size, width)
        y_end = min(y_start + tile_size, height)
        tw = x_end - x_start
        n_live = tw * (y_end - y_start)
        trans = np.ones(n_pix, np.float32)
        done = np.zeros(n_pix, np.bool_)
        acc_rgb = np.zeros((n_pix, 3), np.float32)
        acc_depth = np.zeros(n_pix, np.float32)
        acc_feat = np.zeros((n_pix, n_feat), np.float32)
        # Per pixel, an unsorted list of up to k_cap rank keys (``rank_key``); top_last is the
        # slot of the smallest. Tile-local so that it stays in cache (the allocator hands the
        # same block back tile after tile); entries >= top_n are never read.
        top_keys = np.empty((n_pix, k_cap), np.uint64)
        top_n = np.zeros(n_pix, np.int32)
        top_last = np.zeros(n_pix, np.int32)
        scratch = np.empty(32, np.uint64)
        bits = np.empty(1, np.float32)
        bits_u32 = bits.view(np.uint32)
        ranked_w = np.empty(max(k_cap, 1), np.float32)
        ranked_bits = ranked_w.view(np.uint32)
        chunk = np.empty((CHUNK, RECORD), np.float32)
        chunk_feat = np.empty((CHUNK, n_feat), np.float32)
        evals = 0
        # gsplat-style work for the same image: each pixel tests every Gaussian of the tile's
        # list until it saturates. Reported next to our own count, never used for the output.
        list_length = offsets[tile + 1] - offsets[tile]
        tile_pairs = n_live * list_length
        for j in range(list_length):  # j: position in the tile's list
            if n_live == 0:
                break
            if j % CHUNK == 0:  # copy the next CHUNK records (and feature rows) into tile buffers
                # first the chunk after this one is asked for (its misses overlap this chunk's work),
                # and at the tile's start this chunk too (its misses overlap each other)
                for c in range(j if j == 0 else j + CHUNK, min(j + 2 * CHUNK, list_length)):
                    g = order[slots[offsets[tile] + c]]
                    prefetch(records, g, 0)
                    row = g if feature_rows.shape[0] == 0 else feature_rows[g]
                    if row >= 0:
                        for f in range(0, n_feat, 16):  # 16 float32: one 64-byte line
                            prefetch(features, row, f)
                for c in range(min(CHUNK, list_length - j)):
                    g = order[slots[offsets[tile] + j + c]]
                    for f in range(RECORD):
                        chunk[c, f] = records[g, f]
                    row = g if feature_rows.shape[0] == 0 else feature_rows[g]
                    if row < 0:
                        for f in range(n_feat):
                            chunk_feat[c, f] = np.float32(0.0)
                    else:
                        for f in range(n_feat):
                            chunk_feat[c, f] = features[row, f]
            s = slots[offsets[tile] + j]  # position in depth order
            rec = chunk[j % CHUNK]
            feat = chunk_feat[j % CHUNK]
            mx, my = rec[MX], rec[MY]
            ca, cb, cc = rec[CA], rec[CB], rec[CC]
            opac = rec[OPACITY]
            cut = rec[CUT] + np.float32(1e-3)  # margin: the exact alpha test decides
            # the pixel box where alpha >= alpha_min is possible, clipped to the tile (tile-local)
            bx0, bx1, by0, by1 = pixel_box(mx, my, rec[EX], rec[EY])
            px0, px1 = max(bx0, x_start) - x_start, min(bx1, x_end) - x_start
            py0, py1 = max(by0, y_start) - y_start, min(by1, y_end) - y_start
            for ly in range(py0, py1):
                dy = my - (np.float32(y_start + ly) + half)
                for lx in range(px0, px1):
                    p = ly * tile_size + lx
                    if done[p]:
                        continue
                    evals += 1
                    dx = mx - (np.float32(x_start + lx) + half)
                    sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if sigma < 0 or sigma > cut:  # beyond cut: alpha < alpha_min for sure
                        continue
                    alpha = min(alpha_max, opac * math.exp(-sigma))
                    if alpha < alpha_min:
                        continue
                    t = trans[p]
                    next_t = t * (one - alpha)
                    if next_t <= t_min:
                        done[p] = True
                        n_live -= 1
                        tile_pairs -= list_length - j - 1
                        continue
                    w = alpha * t
                    acc_rgb[p, 0] += w * rec[RED]
                    acc_rgb[p, 1] += w * rec[GREEN]
                    acc_rgb[p, 2] += w * rec[BLUE]
                    acc_depth[p] += w * rec[DEPTH]
                    for f in range(n_feat):
                        acc_feat[p, f] += w * feat[f]
                    if k_cap > 0:
                        offer(top_keys[p], top_n, top_last, p, rank_key(w, s, bits, bits_u32), k_cap)
                    trans[p] = next_t
        out_evals[tile, 0] = evals
        out_evals[tile, 1] = tile_pairs
        for ly in range(y_end - y_start):
            for lx in range(tw):
                p = ly * tile_size + lx
                y, x = y_start + ly, x_start + lx
                total = np.float32(1.0) - trans[p]
                out_alpha[y, x] = total
                for c in range(3):
                    out_rgb[y, x, c] = acc_rgb[p, c] + trans[p] * background[c]
                out_depth[y, x] = acc_depth[p] / total if total > 1e-10 else np.float32(0.0)
                if queries.shape[0] > 0:  # cos(F, q) = acc . q / |acc|: the 1 / (total + eps) cancels
                    square = np.float32(0.0)
                    for f in range(n_feat):
                        square += acc_feat[p, f] * acc_feat[p, f]
                    length = np.float32(math.sqrt(square))
                    if out_unit.shape[0] > 0:
                        scale = one / length if length > 0 else np.float32(0.0)
                        for f in range(n_feat):
                            out_unit[y * width + x, f] = acc_feat[p, f] * scale
                    for q in range(queries.shape[0]):
                        dot = np.float32(0.0)
                        for f in range(n_feat):
                            dot += acc_feat[p, f] * queries[q, f]
                        out_features[y, x, q] = dot / length if length > 0 else np.float32(0.0)
                else:
                    for f in range(n_feat):
                        out_features[y, x, f] = acc_feat[p, f] / (total + feature_eps)
                if k_cap > 0:
                    n = top_n[p]
                    keys = top_keys[p]
                    rank(keys, n, scratch)
                    for k in range(n):
                        ranked_bits[k] = np.uint32(keys[k] >> np.uint64(32))
                    keep = n
                    cumulative = np.float32(0.0)
                    for k in range(n):
                        cumulative += ranked_w[k]
                        if cumulative >= topk_coverage * total:
                            keep = k + 1
                            break
                    keep = min(max(keep, topk_min), n)
                    for k in range(keep):
                        out_topk_ids[y, x, k] = order[0xFFFFFFFF - np.int64(keys[k] & np.uint64(0xFFFFFFFF))]
                        out_topk_weights[y, x, k] = ranked_w[k]
                    for k in range(keep, k_cap):  # pad; the outputs arrive uninitialised
                        out_topk_ids[y, x, k] = -1
                        out_topk_weights[y, x, k] = np.float32(0.0)
