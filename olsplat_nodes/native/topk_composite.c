/* Top-K compositing in C: the ``composite.composite_tiles`` rule for a view without features,
 * the accumulator's render (colour, alpha, depth and the per-pixel adaptive Top-K; k_cap = 0:
 * no Top-K, a plain render).
 *
 * Same contract as the numba kernel (its docstring and ``rasterize``): per tile, front to back
 * over the tile's depth-ordered list, each Gaussian only over its alpha >= alpha_min pixel box
 * (``pixel_box``), w = alpha * T, a pixel stops before T would fall to <= t_min. A pixel keeps
 * its k_cap best contributions by rank key: the weight's float bits above the inverted depth
 * position (larger weight first, the nearer Gaussian first on ties; ``composite.rank_key``),
 * in an unsorted list whose smallest key is replaced by a larger one once the list is full. At
 * the end the list is ranked and the adaptive K is the smallest k whose cumulative weight
 * reaches coverage * (1 - T_final), clamped to [topk_min, k_cap] and to the contributors.
 *
 * One difference in how, none in what is kept: a row of a Gaussian's box is one vectorized pass
 * (``tile_pass.h``: exp(-s) by a polynomial, relative error < 1e-6), so weights agree with the
 * numba kernel's within a few ulp (and a pixel whose transmittance lands within those of t_min
 * may stop one Gaussian apart).
 *
 * Part of the optional extension of olsplat_nodes/native (setup.py); ``raster/topk_native.py``
 * calls it and ``rasterize`` falls back to the numba kernel without it (or for k_cap > 32).
 * Tested against the numba kernel and the numpy reference (tests/raster/test_native.py).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "tile_pass.h"

#define MAX_K 32 /* largest k_cap (topk_max) of this kernel: the ranking network's size */

#ifndef __AVX2__ /* the ranking without AVX2 (sort32) */
/* Batcher's odd-even merge sort of 32 keys, the pairs of ``raster/sorting_network.batcher_pairs(32)``
 * (a test checks this table against it): 191 compare-exchanges, each putting the larger key first. */
static const int8_t NETWORK32[191][2] = {{0,1},{2,3},{4,5},{6,7},{8,9},{10,11},{12,13},{14,15},{16,17},{18,19},{20,21},{22,23},{24,25},{26,27},{28,29},{30,31},{0,2},{1,3},{4,6},{5,7},{8,10},{9,11},{12,14},{13,15},{16,18},{17,19},{20,22},{21,23},{24,26},{25,27},{28,30},{29,31},{1,2},{5,6},{9,10},{13,14},{17,18},{21,22},{25,26},{29,30},{0,4},{1,5},{2,6},{3,7},{8,12},{9,13},{10,14},{11,15},{16,20},{17,21},{18,22},{19,23},{24,28},{25,29},{26,30},{27,31},{2,4},{3,5},{10,12},{11,13},{18,20},{19,21},{26,28},{27,29},{1,2},{3,4},{5,6},{9,10},{11,12},{13,14},{17,18},{19,20},{21,22},{25,26},{27,28},{29,30},{0,8},{1,9},{2,10},{3,11},{4,12},{5,13},{6,14},{7,15},{16,24},{17,25},{18,26},{19,27},{20,28},{21,29},{22,30},{23,31},{4,8},{5,9},{6,10},{7,11},{20,24},{21,25},{22,26},{23,27},{2,4},{3,5},{6,8},{7,9},{10,12},{11,13},{18,20},{19,21},{22,24},{23,25},{26,28},{27,29},{1,2},{3,4},{5,6},{7,8},{9,10},{11,12},{13,14},{17,18},{19,20},{21,22},{23,24},{25,26},{27,28},{29,30},{0,16},{1,17},{2,18},{3,19},{4,20},{5,21},{6,22},{7,23},{8,24},{9,25},{10,26},{11,27},{12,28},{13,29},{14,30},{15,31},{8,16},{9,17},{10,18},{11,19},{12,20},{13,21},{14,22},{15,23},{4,8},{5,9},{6,10},{7,11},{12,16},{13,17},{14,18},{15,19},{20,24},{21,25},{22,26},{23,27},{2,4},{3,5},{6,8},{7,9},{10,12},{11,13},{14,16},{15,17},{18,20},{19,21},{22,24},{23,25},{26,28},{27,29},{1,2},{3,4},{5,6},{7,8},{9,10},{11,12},{13,14},{15,16},{17,18},{19,20},{21,22},{23,24},{25,26},{27,28},{29,30}};
#endif

#ifdef __AVX2__
/* The same order (largest key first) by AVX2, 4 keys per register, for sort32: a compare-exchange
 * of two registers lane by lane puts the larger of each lane in *a. Keys are below 2^63: signed. */
static inline void exchange4(__m256i *a, __m256i *b)
{
    const __m256i b_larger = _mm256_cmpgt_epi64(*b, *a);
    const __m256i larger = _mm256_blendv_epi8(*a, *b, b_larger);
    *b = _mm256_blendv_epi8(*b, *a, b_larger);
    *a = larger;
}

/* Within a register whose lanes are a bitonic sequence: lanes (0, 2), (1, 3), then (0, 1), (2, 3)
 * compare-exchanged, the larger to the lower lane: the lanes sorted. */
static inline __m256i clean_lanes(__m256i v)
{
    __m256i other = _mm256_permute4x64_epi64(v, 0x4E); /* lanes 2, 3, 0, 1 */
    __m256i v_larger = _mm256_cmpgt_epi64(v, other);
    __m256i larger = _mm256_blendv_epi8(other, v, v_larger), smaller = _mm256_blendv_epi8(v, other, v_larger);
    v = _mm256_blend_epi32(larger, smaller, 0xF0); /* lanes 0, 1 the larger, 2, 3 the smaller */
    other = _mm256_permute4x64_epi64(v, 0xB1); /* lanes 1, 0, 3, 2 */
    v_larger = _mm256_cmpgt_epi64(v, other);
    larger = _mm256_blendv_epi8(other, v, v_larger), smaller = _mm256_blendv_epi8(v, other, v_larger);
    return _mm256_blend_epi32(larger, smaller, 0xCC); /* lanes 0, 2 the larger, 1, 3 the smaller */
}

/* Merge two runs sorted largest first, r[0:n] and r[n:2n] (n registers each, n = 1 or 2 or 4),
 * into one: key j of the first against key 4n-1-j of the second (the larger of each pair, in
 * order of j, are the top half as a bitonic sequence, the smaller the bottom half), then each
 * half cleaned: compare-exchanges at register distances n/2 ... 1, then within registers. */
static inline void merge_runs(__m256i *r, int n)
{
    __m256i smaller[4];
    for (int i = 0; i < n; i++) { /* register i of the first run against the second run reversed */
        smaller[i] = _mm256_permute4x64_epi64(r[2 * n - 1 - i], 0x1B); /* lanes 3, 2, 1, 0 */
        exchange4(&r[i], &smaller[i]);
    }
    for (int i = 0; i < n; i++)
        r[n + i] = smaller[i];
    for (int half = 0; half < 2; half++) {
        __m256i *h = r + half * n;
        for (int distance = n / 2; distance >= 1; distance /= 2)
            for (int i = 0; i < n; i++)
                if (!(i & distance))
                    exchange4(&h[i], &h[i + distance]);
        for (int i = 0; i < n; i++)
            h[i] = clean_lanes(h[i]);
    }
}
#endif

/* Sort k[32] largest first (equal keys are equal: any order of them is the same array). With
 * AVX2 a bitonic sort of 8 registers: the 4 columns by an 8-key network across the registers,
 * a 4x4 transpose of each half so that each column is a run of 2 registers, then three merges
 * (about half the scalar network's time in a medium view's render, ~0.13 -> ~0.07 s;
 * tests/raster/test_topk_native.py checks both against numpy's sort).
 * Without AVX2 Batcher's network, unrolled so that k's indices are constants and the keys stay in
 * registers. Keys are below 2^63 (a weight's bits are those of a positive float): signed compares. */
static inline void sort32(int64_t *k)
{
#ifdef __AVX2__
    __m256i r[8];
    for (int i = 0; i < 8; i++)
        r[i] = _mm256_loadu_si256((const __m256i *)(k + 4 * i));
    /* Batcher's network for 8 (batcher_pairs(8)): each lane's column of 8 keys sorted down the registers */
    static const int8_t NETWORK8[19][2] = {{0, 1}, {2, 3}, {4, 5}, {6, 7}, {0, 2}, {1, 3}, {4, 6}, {5, 7}, {1, 2}, {5, 6},
                                           {0, 4}, {1, 5}, {2, 6}, {3, 7}, {2, 4}, {3, 5}, {1, 2}, {3, 4}, {5, 6}};
#pragma GCC unroll 19
    for (int e = 0; e < 19; e++)
        exchange4(&r[NETWORK8[e][0]], &r[NETWORK8[e][1]]);
    /* transpose each 4x4 block: column c becomes registers (c, c + 4) of the output, a run of 8 */
    __m256i runs[8];
    for (int block = 0; block < 2; block++) {
        const __m256i *b = r + 4 * block;
        const __m256i t0 = _mm256_unpacklo_epi64(b[0], b[1]), t1 = _mm256_unpackhi_epi64(b[0], b[1]);
        const __m256i t2 = _mm256_unpacklo_epi64(b[2], b[3]), t3 = _mm256_unpackhi_epi64(b[2], b[3]);
        runs[0 * 2 + block] = _mm256_permute2x128_si256(t0, t2, 0x20);
        runs[1 * 2 + block] = _mm256_permute2x128_si256(t1, t3, 0x20);
        runs[2 * 2 + block] = _mm256_permute2x128_si256(t0, t2, 0x31);
        runs[3 * 2 + block] = _mm256_permute2x128_si256(t1, t3, 0x31);
    }
    merge_runs(runs, 2);     /* columns 0 and 1: 16 keys */
    merge_runs(runs + 4, 2); /* columns 2 and 3 */
    merge_runs(runs, 4);     /* all 32 */
    for (int i = 0; i < 8; i++)
        _mm256_storeu_si256((__m256i *)(k + 4 * i), runs[i]);
#else
#pragma GCC unroll 200
    for (int e = 0; e < 191; e++) {
        const int64_t a = k[NETWORK32[e][0]], b = k[NETWORK32[e][1]];
        k[NETWORK32[e][0]] = a > b ? a : b;
        k[NETWORK32[e][1]] = a > b ? b : a;
    }
#endif
}

/* The slot of the smallest of keys[0:n] (keys are distinct). */
static inline int32_t smallest(const int64_t *keys, int32_t n)
{
    int32_t at = 0;
    for (int32_t i = 1; i < n; i++)
        at = keys[i] < keys[at] ? i : at;
    return at;
}

static inline float bits_float(uint32_t bits)
{
    float w;
    memcpy(&w, &bits, sizeof w);
    return w;
}

/* Returns 0, or -1 when a tile's buffers could not be allocated, tile_size is over MAX_TILE or
 * k_cap over MAX_K (outputs then incomplete). out_topk_ids / out_topk_weights are [H, W, k_cap]
 * (unused when k_cap is 0); every entry is written (padding -1 / 0). out_rgb NULL: no colour (the
 * colour sums are skipped, the rest is the same). map_ids [M] (NULL: none): the records are the
 * rows of a culled projection and out_topk_ids gets map_ids[row], the Gaussians' own indices. */
int composite_topk(const int64_t *offsets, const int32_t *slots, const int32_t *order, const int64_t *tile_order,
                   int64_t n_tiles, const float *records, int64_t width, int64_t height, int64_t tile_size,
                   float alpha_min, float alpha_max, float t_min, int32_t k_cap, int32_t topk_min, double coverage,
                   const float *background, float *out_rgb, float *out_alpha, float *out_depth,
                   int32_t *out_topk_ids, float *out_topk_weights, int64_t *out_evals, const int64_t *map_ids,
                   int threads)
{
    if (tile_size > MAX_TILE || k_cap > MAX_K || k_cap < 0)
        return -1;
    const int64_t tiles_x = (width + tile_size - 1) / tile_size;
    const int64_t n_pix = tile_size * tile_size;
    int failed = 0;
#pragma omp parallel for schedule(dynamic, 4) num_threads(threads) reduction(| : failed)
    for (int64_t work = 0; work < n_tiles; work++) {
        const int64_t tile = tile_order[work];
        const int64_t first = offsets[tile], length = offsets[tile + 1] - first;
        Tile t;
        tile_start(&t, tile, tiles_x, tile_size, width, height, length);
        float chunk[CHUNK][RECORD];
        int32_t chunk_position[CHUNK];
        /* pixel p's list: keys[p * MAX_K + i], count[p] of them; when full, last[p] is the slot of its smallest */
        int32_t count[MAX_TILE * MAX_TILE], last[MAX_TILE * MAX_TILE];
        int64_t *keys = k_cap > 0 ? malloc((size_t)(n_pix * MAX_K) * sizeof(int64_t)) : NULL;
        if (k_cap > 0 && !keys) {
            failed = 1;
            continue;
        }
        memset(count, 0, sizeof count);
        for (int64_t j = 0; j < length && t.n_live > 0; j++) {
            if (j % CHUNK == 0) { /* ask for the chunk after this one (at the tile's start, this one too) */
                const int64_t ahead = length < j + 2 * CHUNK ? length : j + 2 * CHUNK;
                for (int64_t c = j == 0 ? 0 : j + CHUNK; c < ahead; c++)
                    __builtin_prefetch(records + (int64_t)order[slots[first + c]] * RECORD);
                const int64_t m = length - j < CHUNK ? length - j : CHUNK;
                for (int64_t c = 0; c < m; c++) {
                    chunk_position[c] = slots[first + j + c];
                    memcpy(chunk[c], records + (int64_t)order[chunk_position[c]] * RECORD, RECORD * sizeof(float));
                }
            }
            if (!tile_pass(&t, chunk[j % CHUNK], j, alpha_min, alpha_max, t_min, out_rgb != NULL) || k_cap == 0)
                continue;
            /* the rank key's low half: the inverted depth position (the nearer ranks first on ties) */
            const int64_t low = (int64_t)(0xFFFFFFFFu - (uint32_t)chunk_position[j % CHUNK]);
            for (int64_t ly = t.py0; ly < t.py1; ly++) {
                for (uint64_t added = t.added[ly - t.py0]; added; added &= added - 1) { /* in x order */
                    const int64_t lx = __builtin_ctzll(added);
                    const float weight = tile_weight(&t, lx, ly);
                    uint32_t bits;
                    memcpy(&bits, &weight, sizeof bits);
                    const int64_t p = ly * tile_size + lx, key = ((int64_t)bits << 32) | low;
                    int64_t *list = keys + p * MAX_K;
                    if (count[p] < k_cap) {
                        list[count[p]++] = key;
                        if (count[p] == k_cap)
                            last[p] = smallest(list, k_cap);
                    } else if (key > list[last[p]]) {
                        list[last[p]] = key;
                        last[p] = smallest(list, k_cap);
                    }
                }
            }
        }
        tile_finish(&t, tile, width, background, out_rgb, out_alpha, out_depth, out_evals);
        for (int64_t ly = 0; k_cap > 0 && ly < t.y_end - t.y_start; ly++) { /* each pixel's Top-K */
            for (int64_t lx = 0; lx < t.x_end - t.x_start; lx++) {
                const int64_t p = ly * tile_size + lx, at = (t.y_start + ly) * width + t.x_start + lx;
                const float total = out_alpha[at]; /* 1 - T, as tile_finish wrote it */
                const int32_t n = count[p];
                int64_t ranked[MAX_K];
                memcpy(ranked, keys + p * MAX_K, (size_t)n * sizeof(int64_t));
                memset(ranked + n, 0, (size_t)(MAX_K - n) * sizeof(int64_t)); /* padding ranks last */
                sort32(ranked);
                /* the adaptive K: a float32 running sum, compared in double as the numba kernel does */
                int32_t keep = n;
                float cumulative = 0.0f;
                for (int32_t k = 0; k < n; k++) {
                    cumulative += bits_float((uint32_t)(ranked[k] >> 32));
                    if ((double)cumulative >= coverage * (double)total) {
                        keep = k + 1;
                        break;
                    }
                }
                keep = keep > topk_min ? keep : topk_min;
                keep = keep < n ? keep : n;
                int32_t *ids = out_topk_ids + at * k_cap;
                float *w = out_topk_weights + at * k_cap;
                for (int32_t k = 0; k < keep; k++) {
                    const int32_t row = order[0xFFFFFFFFu - (uint32_t)(ranked[k] & 0xFFFFFFFF)];
                    ids[k] = map_ids ? (int32_t)map_ids[row] : row;
                    w[k] = bits_float((uint32_t)(ranked[k] >> 32));
                }
                for (int32_t k = keep; k < k_cap; k++) {
                    ids[k] = -1;
                    w[k] = 0.0f;
                }
            }
        }
        free(keys);
    }
    return failed ? -1 : 0;
}

/* sort32 on n_lists lists of 32 keys (keys[32 * i : 32 * i + 32]), in place: for the tests, which
 * compare it with numpy's sort (its AVX2 path, or the network where the build has no AVX2). */
void sort_key_lists32(int64_t *keys, int64_t n_lists)
{
    for (int64_t i = 0; i < n_lists; i++)
        sort32(keys + 32 * i);
}
