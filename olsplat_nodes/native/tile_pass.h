/* What the C compositing kernels share (heatmap_composite.c, topk_composite.c): the record
 * layout of ``raster/project.py``, a Gaussian's pixel box in a tile, and the vectorized pass of
 * one Gaussian over its box (weights and transmittance, the ``composite_tiles`` rule). */
#ifndef OLSPLAT_NATIVE_TILE_PASS_H
#define OLSPLAT_NATIVE_TILE_PASS_H

#include <math.h>
#include <stdint.h>

#include "simd.h"

/* columns of project.RECORD */
enum { MX, MY, CA, CB, CC, OPACITY, CUT, EX, EY, RED, GREEN, BLUE, DEPTH };
#define RECORD 16
#define CHUNK 64   /* Gaussians copied into the tile's buffers at a time (as composite.CHUNK) */
#define MAX_TILE 64 /* tile_size limit of this kernel (pixels per side) */

static inline float exp_neg(float s)
{
    float x = -s * 0.125f;
    float e = 1.0f / 362880.0f;
    e = e * x + 1.0f / 40320.0f;
    e = e * x + 1.0f / 5040.0f;
    e = e * x + 1.0f / 720.0f;
    e = e * x + 1.0f / 120.0f;
    e = e * x + 1.0f / 24.0f;
    e = e * x + 1.0f / 6.0f;
    e = e * x + 0.5f;
    e = e * x + 1.0f;
    e = e * x + 1.0f;
    e = e * e;
    e = e * e;
    return e * e;
}

/* The 8-pixel groups a box row [px0, px1) spans: from px0 rounded down to a multiple of 8. */
static inline int64_t box_groups(int64_t px0, int64_t px1) { return ((px1 - 1) >> 3) - (px0 >> 3) + 1; }

/* A Gaussian's pass over its pixel box comes in two steps, so that its rows' long dependency
 * chains (sigma, the exp polynomial) overlap in the CPU instead of running one after the other:
 * box_alphas computes every alpha of the box first (it does not depend on transmittance), then
 * row_blend takes each row front to back as the ``composite_tiles`` rule says.
 *
 * box_alphas: for the rows ly in [py0, py1) that still have a live pixel in [px0, px1)
 * (live_rows[ly] & span), alphas[((ly - py0) * groups + g) * 8 + lane] is the alpha of pixel
 * x = (px0 & ~7) + 8 g + lane of the tile row: 0 where the Gaussian cannot add (sigma outside [0,
 * cut] or alpha < alpha_min), -1 outside [px0, px1). Rows without live pixels are not written.
 * x_centre0 / y_centre0: the tile's first pixel centre (x_start + 0.5, y_start + 0.5). */
static inline void box_alphas(const float *rec, int64_t px0, int64_t px1, int64_t py0, int64_t py1,
                              const uint64_t *live_rows, uint64_t span, float x_centre0, float y_centre0, float cut,
                              float alpha_min, float alpha_max, float *restrict alphas)
{
    const float mx = rec[MX], my = rec[MY], ca = rec[CA], cb = rec[CB], cc = rec[CC], opacity = rec[OPACITY];
    const int64_t groups = box_groups(px0, px1), x_first = px0 & ~7;
#ifdef __AVX2__
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), half = _mm256_set1_ps(0.5f);
    const __m256 lane = _mm256_setr_ps(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f);
    const __m256 v_mx = _mm256_set1_ps(mx), v_ca = _mm256_set1_ps(ca), v_cb = _mm256_set1_ps(cb);
    const __m256 v_cut = _mm256_set1_ps(cut), v_opacity = _mm256_set1_ps(opacity);
    const __m256 v_amax = _mm256_set1_ps(alpha_max), v_amin = _mm256_set1_ps(alpha_min);
    const __m256 v_clamp = _mm256_set1_ps(5.6f), outside_alpha = _mm256_set1_ps(-1.0f);
    const __m256 lo = _mm256_set1_ps((float)px0), hi = _mm256_set1_ps((float)px1);
    for (int64_t ly = py0; ly < py1; ly++) {
        if (!(live_rows[ly] & span)) /* every pixel of the box's row has stopped */
            continue;
        const float dy = my - ((float)ly + y_centre0);
        const __m256 v_ccdy2 = _mm256_set1_ps(cc * dy * dy), v_dy = _mm256_set1_ps(dy);
        float *out = alphas + (ly - py0) * groups * 8;
        for (int64_t g = 0; g < groups; g++) {
            const __m256 xs = _mm256_add_ps(_mm256_set1_ps((float)(x_first + 8 * g)), lane);
            const __m256 inside = _mm256_and_ps(_mm256_cmp_ps(xs, lo, _CMP_GE_OQ), _mm256_cmp_ps(xs, hi, _CMP_LT_OQ));
            const __m256 dx = _mm256_sub_ps(v_mx, _mm256_add_ps(xs, _mm256_set1_ps(x_centre0)));
            /* sigma = 0.5 (ca dx^2 + cc dy^2) + cb dx dy */
            const __m256 sigma = _mm256_fmadd_ps(half, _mm256_fmadd_ps(_mm256_mul_ps(v_ca, dx), dx, v_ccdy2),
                                                 _mm256_mul_ps(_mm256_mul_ps(v_cb, dx), v_dy));
            /* exp(-s) as in exp_neg */
            const __m256 x = _mm256_mul_ps(_mm256_min_ps(_mm256_max_ps(sigma, zero), v_clamp), _mm256_set1_ps(-0.125f));
            __m256 e = _mm256_set1_ps(1.0f / 362880.0f);
            e = _mm256_fmadd_ps(e, x, _mm256_set1_ps(1.0f / 40320.0f));
            e = _mm256_fmadd_ps(e, x, _mm256_set1_ps(1.0f / 5040.0f));
            e = _mm256_fmadd_ps(e, x, _mm256_set1_ps(1.0f / 720.0f));
            e = _mm256_fmadd_ps(e, x, _mm256_set1_ps(1.0f / 120.0f));
            e = _mm256_fmadd_ps(e, x, _mm256_set1_ps(1.0f / 24.0f));
            e = _mm256_fmadd_ps(e, x, _mm256_set1_ps(1.0f / 6.0f));
            e = _mm256_fmadd_ps(e, x, half);
            e = _mm256_fmadd_ps(e, x, one);
            e = _mm256_fmadd_ps(e, x, one);
            e = _mm256_mul_ps(e, e);
            e = _mm256_mul_ps(e, e);
            e = _mm256_mul_ps(e, e);
            const __m256 alpha = _mm256_min_ps(_mm256_mul_ps(v_opacity, e), v_amax);
            __m256 hit = _mm256_and_ps(_mm256_cmp_ps(sigma, zero, _CMP_GE_OQ), _mm256_cmp_ps(sigma, v_cut, _CMP_LE_OQ));
            hit = _mm256_and_ps(hit, _mm256_cmp_ps(alpha, v_amin, _CMP_GE_OQ));
            _mm256_storeu_ps(out + 8 * g, _mm256_blendv_ps(outside_alpha, _mm256_and_ps(hit, alpha), inside));
        }
    }
#else
    for (int64_t ly = py0; ly < py1; ly++) {
        if (!(live_rows[ly] & span))
            continue;
        const float dy = my - ((float)ly + y_centre0);
        float *out = alphas + (ly - py0) * groups * 8;
        for (int64_t i = 0; i < groups * 8; i++) {
            const int64_t lx = x_first + i;
            const float dx = mx - ((float)lx + x_centre0);
            const float sigma = 0.5f * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
            const float alpha = fminf(opacity * exp_neg(fminf(fmaxf(sigma, 0.0f), 5.6f)), alpha_max);
            const int hit = sigma >= 0.0f && sigma <= cut && alpha >= alpha_min;
            out[i] = lx < px0 || lx >= px1 ? -1.0f : hit ? alpha : 0.0f;
        }
    }
#endif
}

/* One row of a Gaussian's box after box_alphas (``box``: its row's alphas, groups of 8 pixels
 * from x_first = px0 & ~7), on a tile row whose arrays start at the given pointers. A stopped
 * pixel keeps its transmittance negated (live: trans > 0); a live pixel with alpha > 0 stops when
 * its transmittance would fall to <= t_min, else adds w = alpha T and takes T (1 - alpha). Each
 * pixel's weight (0: no contribution) replaces its alpha in ``box``; returns the bits (1 << x) of
 * the pixels it stopped, sets *added to the bits of those it added to and adds its live pixels
 * inside the box to *live. The arrays hold 8 floats past a tile. ``colour`` 0: the colour sums
 * are left alone (a render nobody reads the colour of: the accumulator's). */
static inline uint64_t row_blend(float *restrict trans, float *restrict acc_r, float *restrict acc_g,
                                 float *restrict acc_b, float *restrict acc_z, float *restrict box, int64_t x_first,
                                 int64_t groups, const float *rec, float t_min, int colour, uint64_t *added,
                                 int64_t *live)
{
    int64_t live_n = 0;
    uint64_t stops = 0, adds = 0;
#ifdef __AVX2__
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), v_tmin = _mm256_set1_ps(t_min);
    const __m256 red = _mm256_set1_ps(rec[RED]), green = _mm256_set1_ps(rec[GREEN]);
    const __m256 blue = _mm256_set1_ps(rec[BLUE]), depth = _mm256_set1_ps(rec[DEPTH]);
    for (int64_t g = 0; g < groups; g++) {
        const int64_t x0 = x_first + 8 * g;
        const __m256 alpha = _mm256_loadu_ps(box + 8 * g), t = _mm256_loadu_ps(trans + x0);
        const __m256 live = _mm256_and_ps(_mm256_cmp_ps(alpha, zero, _CMP_GE_OQ), _mm256_cmp_ps(t, zero, _CMP_GT_OQ));
        const __m256 hit = _mm256_and_ps(live, _mm256_cmp_ps(alpha, zero, _CMP_GT_OQ));
        const __m256 next_t = _mm256_mul_ps(t, _mm256_sub_ps(one, alpha));
        const __m256 stop = _mm256_and_ps(hit, _mm256_cmp_ps(next_t, v_tmin, _CMP_LE_OQ));
        const __m256 add = _mm256_andnot_ps(stop, hit);
        const __m256 w = _mm256_and_ps(add, _mm256_mul_ps(alpha, t));
        _mm256_storeu_ps(box + 8 * g, w);
        /* add: next_t; stop: -t; else t */
        __m256 t_out = _mm256_blendv_ps(t, next_t, add);
        t_out = _mm256_blendv_ps(t_out, _mm256_sub_ps(zero, t), stop);
        _mm256_storeu_ps(trans + x0, t_out);
        if (colour) {
            _mm256_storeu_ps(acc_r + x0, _mm256_fmadd_ps(w, red, _mm256_loadu_ps(acc_r + x0)));
            _mm256_storeu_ps(acc_g + x0, _mm256_fmadd_ps(w, green, _mm256_loadu_ps(acc_g + x0)));
            _mm256_storeu_ps(acc_b + x0, _mm256_fmadd_ps(w, blue, _mm256_loadu_ps(acc_b + x0)));
        }
        _mm256_storeu_ps(acc_z + x0, _mm256_fmadd_ps(w, depth, _mm256_loadu_ps(acc_z + x0)));
        live_n += __builtin_popcount(_mm256_movemask_ps(live));
        stops |= (uint64_t)(uint32_t)_mm256_movemask_ps(stop) << x0;
        adds |= (uint64_t)(uint32_t)_mm256_movemask_ps(_mm256_cmp_ps(w, zero, _CMP_GT_OQ)) << x0;
    }
#else
    for (int64_t i = 0; i < groups * 8; i++) {
        const int64_t lx = x_first + i;
        const float alpha = box[i], t = trans[lx];
        box[i] = 0.0f;
        if (alpha < 0.0f) /* outside the box */
            continue;
        const int live = t > 0.0f, hit = live && alpha > 0.0f;
        const float next_t = t * (1.0f - alpha);
        const int stop = hit && next_t <= t_min, add = hit && !stop;
        const float w = add ? alpha * t : 0.0f;
        box[i] = w;
        trans[lx] = add ? next_t : stop ? -t : t;
        if (colour) {
            acc_r[lx] += w * rec[RED];
            acc_g[lx] += w * rec[GREEN];
            acc_b[lx] += w * rec[BLUE];
        }
        acc_z[lx] += w * rec[DEPTH];
        live_n += live;
        stops |= (uint64_t)stop << lx;
        adds |= (uint64_t)(w > 0.0f) << lx;
    }
#endif
    *added = adds;
    *live += live_n;
    return stops;
}

/* The bits (1 << lx) of pixels [px0, px1) of a tile row, px0 < px1 <= 64. */
static inline uint64_t span_bits(int64_t px0, int64_t px1)
{
    return (px1 - px0 >= 64 ? ~0ULL : (1ULL << (px1 - px0)) - 1) << px0;
}

/* Gaussian rec's tile-local pixel box [px0, px1) x [py0, py1) in the tile [x_start, x_end) x
 * [y_start, y_end), where alpha >= alpha_min is possible (pixel x, centre x + 0.5, is in when
 * |x + 0.5 - mx| <= extent; the extents are widened by 0.1 % + 0.01 px, more than the 1e-3
 * margin on cut moves the ellipse: the exact test in row_pass decides). Empty: px0 >= px1 or py0 >= py1. */
static inline void pixel_box(const float *rec, int64_t x_start, int64_t x_end, int64_t y_start, int64_t y_end,
                             int64_t box[4])
{
    const float mx = rec[MX], my = rec[MY];
    const float ex = rec[EX] * 1.001f + 0.01f, ey = rec[EY] * 1.001f + 0.01f;
    int64_t px0 = (int64_t)ceilf(mx - ex - 0.5f), px1 = (int64_t)floorf(mx + ex - 0.5f) + 1;
    int64_t py0 = (int64_t)ceilf(my - ey - 0.5f), py1 = (int64_t)floorf(my + ey - 0.5f) + 1;
    box[0] = (px0 > x_start ? px0 : x_start) - x_start;
    box[1] = (px1 < x_end ? px1 : x_end) - x_start;
    box[2] = (py0 > y_start ? py0 : y_start) - y_start;
    box[3] = (py1 < y_end ? py1 : y_end) - y_start;
}

/* One tile's compositing state: the tile [x_start, x_end) x [y_start, y_end) of a tile_size grid
 * (local pixel p = ly * tile_size + lx), its transmittance and colour/depth sums (8 floats past
 * the tile: a row's last 8-pixel group may reach past it, masked), the bits of its pixels not yet
 * stopped, and the two counts of out_evals. After tile_pass: the Gaussian's box rows [py0, py1),
 * added[ly - py0] the bits of the pixels it added to, their weights read by tile_weight. */
typedef struct {
    int64_t x_start, y_start, x_end, y_end, tile_size, length, n_live, evals, tile_pairs;
    uint64_t live_rows[MAX_TILE];
    float trans[MAX_TILE * MAX_TILE + 8], acc_r[MAX_TILE * MAX_TILE + 8], acc_g[MAX_TILE * MAX_TILE + 8];
    float acc_b[MAX_TILE * MAX_TILE + 8], acc_z[MAX_TILE * MAX_TILE + 8];
    int64_t py0, py1, x_first, groups;
    uint64_t added[MAX_TILE];
    float box[MAX_TILE * (MAX_TILE + 8)]; /* alphas, then weights: rows of 8-pixel groups */
} Tile;

/* Tile ``tile`` (row-major in a grid tiles_x wide) of a width x height image, with ``length``
 * Gaussians in its list: T = 1, sums 0, every pixel live. */
static inline void tile_start(Tile *t, int64_t tile, int64_t tiles_x, int64_t tile_size, int64_t width, int64_t height,
                              int64_t length)
{
    t->tile_size = tile_size;
    t->x_start = (tile % tiles_x) * tile_size, t->y_start = (tile / tiles_x) * tile_size;
    t->x_end = t->x_start + tile_size < width ? t->x_start + tile_size : width;
    t->y_end = t->y_start + tile_size < height ? t->y_start + tile_size : height;
    for (int64_t p = 0; p < tile_size * tile_size + 8; p++) {
        t->trans[p] = 1.0f;
        t->acc_r[p] = t->acc_g[p] = t->acc_b[p] = t->acc_z[p] = 0.0f;
    }
    for (int64_t ly = 0; ly < t->y_end - t->y_start; ly++)
        t->live_rows[ly] = span_bits(0, t->x_end - t->x_start);
    t->length = length;
    t->n_live = (t->x_end - t->x_start) * (t->y_end - t->y_start);
    t->evals = 0, t->tile_pairs = t->n_live * length;
    t->py0 = t->py1 = 0;
}

/* The pass of the tile's j-th Gaussian (record rec) over its pixel box, in two steps (box_alphas,
 * then row_blend row by row), skipping the rows where every pixel of the box has stopped.
 * Returns the bits of the pixels it added to, over all rows (0: it added nowhere). ``colour`` 0:
 * without the colour sums (row_blend). */
static inline uint64_t tile_pass(Tile *t, const float *rec, int64_t j, float alpha_min, float alpha_max, float t_min,
                                 int colour)
{
    int64_t box[4];
    pixel_box(rec, t->x_start, t->x_end, t->y_start, t->y_end, box);
    const int64_t px0 = box[0], px1 = box[1];
    t->py0 = box[2], t->py1 = box[3];
    if (px0 >= px1 || t->py0 >= t->py1) {
        t->py1 = t->py0;
        return 0;
    }
    const uint64_t span = span_bits(px0, px1);
    t->x_first = px0 & ~7, t->groups = box_groups(px0, px1);
    const float cut = rec[CUT] + 1e-3f; /* margin: the exact alpha test decides */
    box_alphas(rec, px0, px1, t->py0, t->py1, t->live_rows, span, (float)t->x_start + 0.5f,
               (float)t->y_start + 0.5f, cut, alpha_min, alpha_max, t->box);
    uint64_t any = 0;
    for (int64_t ly = t->py0; ly < t->py1; ly++) {
        uint64_t *added = t->added + (ly - t->py0);
        *added = 0;
        if (!(t->live_rows[ly] & span)) /* every pixel of the box's row has stopped */
            continue;
        const int64_t row = ly * t->tile_size;
        const uint64_t stops = row_blend(t->trans + row, t->acc_r + row, t->acc_g + row, t->acc_b + row, t->acc_z + row,
                                         t->box + (ly - t->py0) * t->groups * 8, t->x_first, t->groups, rec, t_min,
                                         colour, added, &t->evals);
        const int64_t stopped = __builtin_popcountll(stops);
        t->live_rows[ly] &= ~stops;
        t->n_live -= stopped;
        t->tile_pairs -= stopped * (t->length - j - 1);
        any |= *added;
    }
    return any;
}

/* The weight of the last tile_pass at local pixel (lx, ly), a pixel of its added bits. */
static inline float tile_weight(const Tile *t, int64_t lx, int64_t ly)
{
    return t->box[(ly - t->py0) * t->groups * 8 + lx - t->x_first];
}

/* The tile's colour (+ background x final T; out_rgb NULL: none), alpha = 1 - T and depth =
 * sum(w z) / alpha into the image's [H, W, 3] / [H, W] outputs, and its two counts into
 * out_evals[tile]. */
static inline void tile_finish(const Tile *t, int64_t tile, int64_t width, const float *background, float *out_rgb,
                               float *out_alpha, float *out_depth, int64_t *out_evals)
{
    for (int64_t ly = 0; ly < t->y_end - t->y_start; ly++) {
        for (int64_t lx = 0; lx < t->x_end - t->x_start; lx++) {
            const int64_t p = ly * t->tile_size + lx, at = (t->y_start + ly) * width + t->x_start + lx;
            const float final_t = fabsf(t->trans[p]), total = 1.0f - final_t;
            out_alpha[at] = total;
            out_depth[at] = total > 1e-10f ? t->acc_z[p] / total : 0.0f;
        }
    }
    /* the colour in a loop of its own: the loop above compiles the same with or without it, so
     * alpha and depth are the same bits either way */
    for (int64_t ly = 0; out_rgb && ly < t->y_end - t->y_start; ly++) {
        for (int64_t lx = 0; lx < t->x_end - t->x_start; lx++) {
            const int64_t p = ly * t->tile_size + lx, at = (t->y_start + ly) * width + t->x_start + lx;
            const float final_t = fabsf(t->trans[p]);
            out_rgb[at * 3] = t->acc_r[p] + final_t * background[0];
            out_rgb[at * 3 + 1] = t->acc_g[p] + final_t * background[1];
            out_rgb[at * 3 + 2] = t->acc_b[p] + final_t * background[2];
        }
    }
    out_evals[tile * 2] = t->evals;
    out_evals[tile * 2 + 1] = t->tile_pairs;
}

#endif
