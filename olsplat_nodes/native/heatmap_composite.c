/* Heatmap compositing in C: the ``composite.composite_tiles`` rule for one case, a view's cosine
 * heatmaps (feature_queries, no Top-K), with explicit SIMD where numba cannot get it.
 *
 * Same contract as the numba kernel (its docstring and ``rasterize``): per 16x16 tile, front to
 * back over the tile's depth-ordered list, each Gaussian only over its alpha >= alpha_min pixel
 * box; w = alpha * T; a pixel stops before T would fall to <= t_min. Outputs: rgb (+ background
 * * T), alpha = 1 - T, depth = sum(w z) / alpha, per query the cosine of the pixel's rendered
 * feature F = sum(w f) with the query, and (when unit_out is given) F / |F|.
 *
 * Three differences in how, none in what:
 * - a Gaussian's box is taken 8 pixels at a time in two steps (tile_pass.h): all its alphas,
 *   with exp(-s) as (Taylor_9(-s/8))^8 on 0 <= s <= 5.6 (relative error < 1e-6; every sigma that
 *   can pass the alpha test is below 5.6 = ln(255) + margin), then the blending row by row. The
 *   alphas do not depend on transmittance, so their long chains of dependent instructions
 *   overlap in the CPU (one row after another, they had waited on each other);
 * - a tile keeps a bit per pixel that has not stopped, and a Gaussian skips the rows of its box
 *   where every pixel has (32 % of the rows of a near view of the large map, 54 % of a far one);
 * - the feature channels are summed per pixel, not per Gaussian: a chunk of CHUNK Gaussians
 *   lists each pixel's (weight, Gaussian) pairs, then each pixel adds its list with 64 channels
 *   in eight AVX2 registers at a time, so the accumulators are read and written once per chunk
 *   instead of once per contribution (the numba kernel's channel sums are bound by that traffic).
 *   Additions per pixel keep their front-to-back order. A Gaussian's feature row is read only
 *   when it contributed to the tile, straight from the table (no copy).
 *
 * The feature table may be float32 or float16 (``half``: IEEE binary16 bits, widened with F16C as
 * they are read, exactly). A language map stores its features as float16, so the query server
 * keeps them so: half the memory, and half the bytes this kernel reads, its largest stall.
 *
 * Part of the optional extension of olsplat_nodes/native (setup.py); ``raster/heatmap_native.py``
 * calls it and ``rasterize`` falls back to the numba kernel without it. Tested against the numba
 * kernel and the numpy reference (tests/raster/test_native.py).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "tile_pass.h"

/* acc[p] += w * row[c] over pixel p's listed pairs (list order), for every pixel; empties the
 * lists. ``rows`` [CHUNK] point at the chunk's feature rows of ``dim`` values of type T (float or
 * uint16_t float16 bits); LOAD8 widens 8 values at a pointer to float32, LOAD1 one value. */
#define DEFINE_ADD_LISTED(NAME, T, LOAD8, LOAD1)                                                                  \
    static void NAME(float *restrict acc, const void *const *rows, int64_t dim, const float *list_w,             \
                     const uint8_t *list_c, int32_t *listed, int64_t n_pix)                                      \
    {                                                                                                             \
        for (int64_t p = 0; p < n_pix; p++) {                                                                     \
            const int32_t n = listed[p];                                                                          \
            if (n == 0)                                                                                           \
                continue;                                                                                         \
            const float *w = list_w + p * CHUNK;                                                                  \
            const uint8_t *c = list_c + p * CHUNK;                                                                \
            float *a = acc + p * dim;                                                                             \
            int64_t f = 0;                                                                                        \
            ADD_LISTED_BLOCKS(T, LOAD8)                                                                           \
            for (int32_t k = 0; k < n; k++) { /* channels past the last 64 (or all, without AVX2) */             \
                const T *r = (const T *)rows[c[k]];                                                               \
                for (int64_t g = f; g < dim; g++)                                                                 \
                    a[g] += w[k] * LOAD1(r + g);                                                                  \
            }                                                                                                     \
            listed[p] = 0;                                                                                        \
        }                                                                                                         \
    }

#ifdef __AVX2__
/* 64 channels at a time in eight registers: each pixel's sums are read and written once per chunk */
#define ADD_LISTED_BLOCKS(T, LOAD8)                                                                               \
    for (; f + 64 <= dim; f += 64) {                                                                              \
        __m256 a0 = _mm256_loadu_ps(a + f), a1 = _mm256_loadu_ps(a + f + 8);                                      \
        __m256 a2 = _mm256_loadu_ps(a + f + 16), a3 = _mm256_loadu_ps(a + f + 24);                                \
        __m256 a4 = _mm256_loadu_ps(a + f + 32), a5 = _mm256_loadu_ps(a + f + 40);                                \
        __m256 a6 = _mm256_loadu_ps(a + f + 48), a7 = _mm256_loadu_ps(a + f + 56);                                \
        for (int32_t k = 0; k < n; k++) {                                                                         \
            const __m256 wk = _mm256_set1_ps(w[k]);                                                               \
            const T *r = (const T *)rows[c[k]] + f;                                                               \
            a0 = _mm256_fmadd_ps(wk, LOAD8(r), a0);                                                               \
            a1 = _mm256_fmadd_ps(wk, LOAD8(r + 8), a1);                                                           \
            a2 = _mm256_fmadd_ps(wk, LOAD8(r + 16), a2);                                                          \
            a3 = _mm256_fmadd_ps(wk, LOAD8(r + 24), a3);                                                          \
            a4 = _mm256_fmadd_ps(wk, LOAD8(r + 32), a4);                                                          \
            a5 = _mm256_fmadd_ps(wk, LOAD8(r + 40), a5);                                                          \
            a6 = _mm256_fmadd_ps(wk, LOAD8(r + 48), a6);                                                          \
            a7 = _mm256_fmadd_ps(wk, LOAD8(r + 56), a7);                                                          \
        }                                                                                                         \
        _mm256_storeu_ps(a + f, a0);                                                                              \
        _mm256_storeu_ps(a + f + 8, a1);                                                                          \
        _mm256_storeu_ps(a + f + 16, a2);                                                                         \
        _mm256_storeu_ps(a + f + 24, a3);                                                                         \
        _mm256_storeu_ps(a + f + 32, a4);                                                                         \
        _mm256_storeu_ps(a + f + 40, a5);                                                                         \
        _mm256_storeu_ps(a + f + 48, a6);                                                                         \
        _mm256_storeu_ps(a + f + 56, a7);                                                                         \
    }
#define LOAD8_F32(r) _mm256_loadu_ps(r)
#define LOAD8_F16(r) _mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)(r)))
#else
#define ADD_LISTED_BLOCKS(T, LOAD8)
#define LOAD8_F32(r) 0
#define LOAD8_F16(r) 0
#endif
#define LOAD1_F16(r) half_bits_to_float(*(r))
#define LOAD1_F32(r) (*(r))

DEFINE_ADD_LISTED(add_listed_f32, float, LOAD8_F32, LOAD1_F32)
DEFINE_ADD_LISTED(add_listed_f16, uint16_t, LOAD8_F16, LOAD1_F16)

/* A pixel's outputs from its feature sum a [dim]: heat[q] = cos(a, queries[q]) (0 where a = 0;
 * the 1 / (alpha + eps) of F cancels) and, when unit is given, unit = a / |a|. */
static void pixel_outputs(const float *a, int64_t dim, const float *queries, int64_t n_queries, float *heat,
                          float *unit)
{
    int64_t q = 0;
#ifdef __AVX2__
    if (dim % 8 == 0) {
        __m256 s = _mm256_setzero_ps();
        for (int64_t f = 0; f < dim; f += 8) {
            const __m256 v = _mm256_loadu_ps(a + f);
            s = _mm256_fmadd_ps(v, v, s);
        }
        const float length = sqrtf(sum8(s)), scale = length > 0.0f ? 1.0f / length : 0.0f;
        if (unit) {
            const __m256 v_scale = _mm256_set1_ps(scale);
            for (int64_t f = 0; f < dim; f += 8)
                _mm256_storeu_ps(unit + f, _mm256_mul_ps(_mm256_loadu_ps(a + f), v_scale));
        }
        for (; q + 4 <= n_queries; q += 4) { /* four queries per pass over a */
            const float *q0 = queries + q * dim, *q1 = q0 + dim, *q2 = q1 + dim, *q3 = q2 + dim;
            __m256 d0 = _mm256_setzero_ps(), d1 = d0, d2 = d0, d3 = d0;
            for (int64_t f = 0; f < dim; f += 8) {
                const __m256 v = _mm256_loadu_ps(a + f);
                d0 = _mm256_fmadd_ps(v, _mm256_loadu_ps(q0 + f), d0);
                d1 = _mm256_fmadd_ps(v, _mm256_loadu_ps(q1 + f), d1);
                d2 = _mm256_fmadd_ps(v, _mm256_loadu_ps(q2 + f), d2);
                d3 = _mm256_fmadd_ps(v, _mm256_loadu_ps(q3 + f), d3);
            }
            heat[q] = sum8(d0) * scale;
            heat[q + 1] = sum8(d1) * scale;
            heat[q + 2] = sum8(d2) * scale;
            heat[q + 3] = sum8(d3) * scale;
        }
        for (; q < n_queries; q++) {
            const float *row = queries + q * dim;
            __m256 d = _mm256_setzero_ps();
            for (int64_t f = 0; f < dim; f += 8)
                d = _mm256_fmadd_ps(_mm256_loadu_ps(a + f), _mm256_loadu_ps(row + f), d);
            heat[q] = sum8(d) * scale;
        }
        return;
    }
#endif
    float square = 0.0f;
    for (int64_t f = 0; f < dim; f++)
        square += a[f] * a[f];
    const float length = sqrtf(square), scale = length > 0.0f ? 1.0f / length : 0.0f;
    if (unit)
        for (int64_t f = 0; f < dim; f++)
            unit[f] = a[f] * scale;
    for (; q < n_queries; q++) {
        float dot = 0.0f;
        for (int64_t f = 0; f < dim; f++)
            dot += a[f] * queries[q * dim + f];
        heat[q] = dot * scale;
    }
}

/* Returns 0, or -1 when a tile's buffers could not be allocated (outputs then incomplete). */
int composite_heatmaps(const int64_t *offsets, const int32_t *slots, const int32_t *order,
                       const int64_t *tile_order, int64_t n_tiles, const float *records, const void *features,
                       int64_t dim, int half, const int32_t *feature_rows, int64_t width, int64_t height, int64_t tile_size,
                       float alpha_min, float alpha_max, float t_min, const float *background,
                       const float *queries, int64_t n_queries, float *out_rgb, float *out_alpha, float *out_depth,
                       float *out_heat, float *out_unit, int64_t *out_evals, int threads)
{
    if (tile_size > MAX_TILE)
        return -1;
    const int64_t tiles_x = (width + tile_size - 1) / tile_size;
    const int64_t n_pix = tile_size * tile_size;
    const int64_t row_bytes = dim * (half ? 2 : 4);
    void (*const add_listed)(float *restrict, const void *const *, int64_t, const float *, const uint8_t *,
                             int32_t *, int64_t) = half ? add_listed_f16 : add_listed_f32;
    int failed = 0;
#pragma omp parallel for schedule(dynamic, 4) num_threads(threads) reduction(| : failed)
    for (int64_t work = 0; work < n_tiles; work++) {
        const int64_t tile = tile_order[work];
        const int64_t first = offsets[tile], length = offsets[tile + 1] - first;
        Tile t;
        tile_start(&t, tile, tiles_x, tile_size, width, height, length);
        float chunk[CHUNK][RECORD];
        float *acc = calloc((size_t)(n_pix * dim), sizeof(float));
        float *zero_row = calloc((size_t)dim + 1, sizeof(float)); /* the row of -1; + 1: never calloc(0) */
        const void *chunk_rows[CHUNK];
        float *list_w = malloc((size_t)(n_pix * CHUNK) * sizeof(float));
        uint8_t *list_c = malloc((size_t)(n_pix * CHUNK));
        int32_t *listed = calloc((size_t)n_pix, sizeof(int32_t));
        if (!acc || !zero_row || !list_w || !list_c || !listed) {
            failed = 1;
            free(acc), free(zero_row), free(list_w), free(list_c), free(listed);
            continue;
        }
        for (int64_t j = 0; j < length && t.n_live > 0; j++) {
            if (j % CHUNK == 0) {
                if (j > 0)
                    add_listed(acc, chunk_rows, dim, list_w, list_c, listed, n_pix);
                /* ask for the records of the chunk after this one now (at the tile's start, this
                 * one's too); feature rows are asked for once their Gaussian has contributed */
                const int64_t ahead = length < j + 2 * CHUNK ? length : j + 2 * CHUNK;
                for (int64_t c = j == 0 ? 0 : j + CHUNK; c < ahead; c++)
                    __builtin_prefetch(records + (int64_t)order[slots[first + c]] * RECORD);
                const int64_t m = length - j < CHUNK ? length - j : CHUNK;
                for (int64_t c = 0; c < m; c++) {
                    const int64_t g = order[slots[first + j + c]];
                    memcpy(chunk[c], records + g * RECORD, RECORD * sizeof(float));
                    const int64_t row = feature_rows ? feature_rows[g] : g;
                    chunk_rows[c] = row < 0 ? (const void *)zero_row : (const char *)features + row * row_bytes;
                }
            }
            if (!tile_pass(&t, chunk[j % CHUNK], j, alpha_min, alpha_max, t_min, 1))
                continue;
            for (int64_t ly = t.py0; ly < t.py1; ly++) {
                for (uint64_t added = t.added[ly - t.py0]; added; added &= added - 1) { /* in x order */
                    const int64_t lx = __builtin_ctzll(added), p = ly * tile_size + lx;
                    list_w[p * CHUNK + listed[p]] = tile_weight(&t, lx, ly);
                    list_c[p * CHUNK + listed[p]] = (uint8_t)(j % CHUNK);
                    listed[p]++;
                }
            }
            /* its feature row is read at the chunk's end: ask for it now (half of a tile's
             * Gaussians never contribute, and their rows are never read) */
            for (int64_t b = 0; b < row_bytes; b += 64)
                __builtin_prefetch((const char *)chunk_rows[j % CHUNK] + b);
        }
        add_listed(acc, chunk_rows, dim, list_w, list_c, listed, n_pix);
        tile_finish(&t, tile, width, background, out_rgb, out_alpha, out_depth, out_evals);
        for (int64_t ly = 0; ly < t.y_end - t.y_start; ly++) {
            for (int64_t lx = 0; lx < t.x_end - t.x_start; lx++) {
                const int64_t p = ly * tile_size + lx, at = (t.y_start + ly) * width + t.x_start + lx;
                pixel_outputs(acc + p * dim, dim, queries, n_queries, out_heat + at * n_queries,
                              out_unit ? out_unit + at * dim : NULL);
            }
        }
        free(acc), free(zero_row), free(list_w), free(list_c), free(listed);
    }
    return failed ? -1 : 0;
}
