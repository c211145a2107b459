"""Front-to-back alpha compositing per tile, with the per-pixel adaptive Top-K.

One tile is one unit of parallel work. Inside a tile the loop runs Gaussian by Gaussian
(front to back) and, for each, only over the pixels of the box where its alpha can reach
alpha_min (``extents``): pixels outside that box would be skipped by the alpha test anyway,
so the result is the same as testing every pixel of the tile, at a fraction of the work.

Per pixel, a contribution of Gaussian g is w = alpha_g * T with T the transmittance before g.
The pixel keeps an unsorted list of its best ``topk_max`` contributions: while the list is
full, a new contribution replaces the last-ranked entry when it ranks higher (rank: larger w
first, the nearer Gaussian first on ties). At the end the list is sorted once, and the
adaptive K is the smallest k whose cumulative weight reaches ``topk_coverage`` of the pixel's
total weight (1 - T_final), clamped to [topk_min, topk_max] and to the number of contributors.

Gaussians arrive as packed records in depth order (``pack_sorted``), so a tile's list walks
memory forwards and each Gaussian costs one cache line.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _ranks_before(w_a, s_a, w_b, s_b) -> bool:
    """Entry a ranks before b: larger weight first, nearer (smaller depth position s) on ties."""
    return w_a > w_b or (w_a == w_b and s_a < s_b)


@njit(cache=True, inline="always")
def _offer(weights, slots, top_n, top_last, p, w, s, k_cap):
    """Offer contribution (w, s) to pixel p's unsorted Top-k_cap list."""
    n = top_n[p]
    if n < k_cap:
        weights[n], slots[n] = w, s
        top_n[p] = n + 1
        if n + 1 == k_cap:
            _find_last(weights, slots, top_last, p, k_cap)
    elif w > weights[top_last[p]]:  # ties lose: the earlier contribution ranks first
        weights[top_last[p]], slots[top_last[p]] = w, s
        _find_last(weights, slots, top_last, p, k_cap)


@njit(cache=True, inline="always")
def _find_last(weights, slots, top_last, p, k_cap):
    last = 0
    for k in range(1, k_cap):
        if _ranks_before(weights[last], slots[last], weights[k], slots[k]):
            last = k
    top_last[p] = last


@njit(cache=True)
def _sort_ranked(weights, slots, n):
    """Insertion sort of the first n entries into rank order (input is nearly sorted)."""
    for i in range(1, n):
        w, s = weights[i], slots[i]
        k = i
        while k > 0 and _ranks_before(w, s, weights[k - 1], slots[k - 1]):
            weights[k], slots[k] = weights[k - 1], slots[k - 1]
            k -= 1
        weights[k], slots[k] = w, s


def _batcher_pairs(n: int) -> np.ndarray:
    """[C, 2] the compare-exchange pairs (i < j) of Batcher's odd-even merge sort for n inputs (a
    power of two): applied in order, each putting the larger value first, they sort any input."""
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return np.array(pairs, np.int64)


_PAIRS = _batcher_pairs(32)  # 191 compare-exchanges


@njit(cache=True)
def _network_sort(weights, slots, n, keys):
    """Rank-order the first n (<= 32) entries (as ``_sort_ranked``) with a 32-input sorting
    network on one uint64 key per entry: the weight's bits (a float >= 0 orders like its bits)
    above the inverted slot, so a larger key ranks first; padding keys are 0 (every real weight
    is > 0). Branch-free, unlike the insertion sort on lists that arrive far from sorted."""
    bits = weights.view(np.uint32)
    for i in range(n):
        keys[i] = (np.uint64(bits[i]) << np.uint64(32)) | np.uint64(0xFFFFFFFF - slots[i])
    for i in range(n, 32):
        keys[i] = np.uint64(0)
    for c in range(_PAIRS.shape[0]):
        a, b = keys[_PAIRS[c, 0]], keys[_PAIRS[c, 1]]
        keys[_PAIRS[c, 0]] = max(a, b)
        keys[_PAIRS[c, 1]] = min(a, b)
    for i in range(n):
        bits[i] = np.uint32(keys[i] >> np.uint64(32))
        slots[i] = np.int32(0xFFFFFFFF - (keys[i] & np.uint64(0xFFFFFFFF)))


# Columns of the packed per-Gaussian record: one 64-byte cache line per Gaussian, so the hot
# loop touches one line per Gaussian instead of one per array.
MX, MY, CA, CB, CC, OPACITY, CUT, EX, EY, RED, GREEN, BLUE, DEPTH = range(13)
RECORD = 16


@njit(parallel=True, cache=True)
def pack_sorted(order, means2d, conics, opacities, sigma_cuts, extents, colors, depths):
    """[M, RECORD] float32 records of the Gaussians ``order`` lists, in that (depth) order."""
    packed = np.zeros((order.shape[0], RECORD), np.float32)
    for s in prange(order.shape[0]):
        g = order[s]
        packed[s, MX], packed[s, MY] = means2d[g, 0], means2d[g, 1]
        packed[s, CA], packed[s, CB], packed[s, CC] = conics[g, 0], conics[g, 1], conics[g, 2]
        packed[s, OPACITY] = opacities[g]
        packed[s, CUT] = sigma_cuts[g] + np.float32(1e-3)  # margin: the exact alpha test decides
        packed[s, EX], packed[s, EY] = extents[g, 0], extents[g, 1]
        packed[s, RED], packed[s, GREEN], packed[s, BLUE] = colors[g, 0], colors[g, 1], colors[g, 2]
        packed[s, DEPTH] = depths[g]
    return packed


@njit(parallel=True, cache=True, fastmath=True)
def composite_tiles(
    offsets, slots, order, tile_order, packed,
    features, width, height, tile_size, alpha_min, alpha_max, t_min, want_topk,
    topk_min, topk_max, topk_coverage, feature_eps, background, queries,
    out_rgb, out_alpha, out_depth, out_features, out_topk_ids, out_topk_weights, out_evals,
):  # fmt: skip
    """Composite every tile. With queries [Q, D] (Q > 0) out_features [H, W, Q] receives the
    cosine of each pixel's rendered feature with each query row instead of the feature itself
    (a heatmap without the [H, W, D] feature image); else out_features is [H, W, D]."""
    tiles_x = (width + tile_size - 1) // tile_size
    n_feat = features.shape[1]
    n_pix = tile_size * tile_size
    k_cap = topk_max if want_topk else 0
    # float32 throughout the hot loop: mixing in float64 constants would promote it
    alpha_min, alpha_max, t_min = np.float32(alpha_min), np.float32(alpha_max), np.float32(t_min)
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
        # Per pixel, an unsorted list of up to k_cap (weight, depth-order position s); top_last
        # is the slot of the entry that ranks last. Tile-local so that it stays in cache (the
        # allocator hands the same block back tile after tile); entries >= top_n are never read.
        top_w = np.empty((n_pix, k_cap), np.float32)
        top_s = np.empty((n_pix, k_cap), np.int32)
        top_n = np.zeros(n_pix, np.int32)
        top_last = np.zeros(n_pix, np.int32)
        keys = np.empty(32, np.uint64)
        evals = 0
        # gsplat-style work for the same image: each pixel tests every Gaussian of the tile's
        # list until it saturates. Reported next to our own count, never used for the output.
        list_length = offsets[tile + 1] - offsets[tile]
        tile_pairs = n_live * list_length
        for j in range(offsets[tile + 1] - offsets[tile]):  # j: position in the tile's list
            if n_live == 0:
                break
            s = slots[offsets[tile] + j]  # position in depth order
            rec = packed[s]
            mx, my = rec[MX], rec[MY]
            ca, cb, cc = rec[CA], rec[CB], rec[CC]
            opac, cut = rec[OPACITY], rec[CUT]
            # pixel box (tile-local) where alpha >= alpha_min is possible; +1 px for rounding
            px0 = max(int(math.floor(mx - rec[EX] - 1.5)), x_start) - x_start
            px1 = min(int(math.ceil(mx + rec[EX] + 0.5)), x_end) - x_start
            py0 = max(int(math.floor(my - rec[EY] - 1.5)), y_start) - y_start
            py1 = min(int(math.ceil(my + rec[EY] + 0.5)), y_end) - y_start
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
                        acc_feat[p, f] += w * features[s, f]
                    if k_cap > 0:
                        _offer(top_w[p], top_s[p], top_n, top_last, p, w, s, k_cap)
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
                    weights, ranked = top_w[p], top_s[p]
                    if k_cap <= 32:  # the network sorts up to 32 keys (the rest padded)
                        _network_sort(weights, ranked, n, keys)
                    else:
                        _sort_ranked(weights, ranked, n)
                    keep = n
                    cumulative = np.float32(0.0)
                    for k in range(n):
                        cumulative += weights[k]
                        if cumulative >= topk_coverage * total:
                            keep = k + 1
                            break
                    keep = min(max(keep, topk_min), n)
                    for k in range(keep):
                        out_topk_ids[y, x, k] = order[ranked[k]]
                        out_topk_weights[y, x, k] = weights[k]
                    for k in range(keep, k_cap):  # pad; the outputs arrive uninitialised
                        out_topk_ids[y, x, k] = -1
                        out_topk_weights[y, x, k] = np.float32(0.0)
