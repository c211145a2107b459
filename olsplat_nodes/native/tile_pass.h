/* What the C compositing kernels share (heatmap_composite.c, topk_composite.c): the record
 * layout of ``raster/project.py``, a Gaussian's pixel box in a tile, and the vectorized pass of
 * one Gaussian over one row of its box (weights and transmittance, the ``composite_tiles`` rule). */
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

/* One row of a Gaussian's box, pixels [px0, px1) of a tile row whose arrays start at the given
 * pointers. A stopped pixel keeps its transmittance negated (live: trans > 0). Writes each
 * pixel's weight (0: no contribution) to weights; counts[0] += live pixels, counts[1] += stops.
 * With AVX2 the row is taken 8 pixels at a time from px0 rounded down to a multiple of 8, lanes
 * outside [px0, px1) masked off (their values are written back unchanged): most boxes are a few
 * pixels wide, too short for a compiler's vector loop. The arrays hold 8 floats past a tile. */
static inline void row_pass(float *restrict trans, float *restrict acc_r, float *restrict acc_g, float *restrict acc_b,
                     float *restrict acc_z, float *restrict weights, int32_t px0, int32_t px1, float x_centre0,
                     const float *rec, float dy, float cut, float alpha_min, float alpha_max, float t_min,
                     float *counts)
{
    const float mx = rec[MX], ca = rec[CA], cb = rec[CB], cc = rec[CC], opacity = rec[OPACITY];
    const float red = rec[RED], green = rec[GREEN], blue = rec[BLUE], depth = rec[DEPTH];
#ifdef __AVX2__
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), half = _mm256_set1_ps(0.5f);
    const __m256 lane = _mm256_setr_ps(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f);
    const __m256 v_mx = _mm256_set1_ps(mx), v_ca = _mm256_set1_ps(ca), v_cb = _mm256_set1_ps(cb);
    const __m256 v_ccdy2 = _mm256_set1_ps(cc * dy * dy), v_dy = _mm256_set1_ps(dy), v_cut = _mm256_set1_ps(cut);
    const __m256 v_opacity = _mm256_set1_ps(opacity), v_amax = _mm256_set1_ps(alpha_max);
    const __m256 v_amin = _mm256_set1_ps(alpha_min), v_tmin = _mm256_set1_ps(t_min), v_clamp = _mm256_set1_ps(5.6f);
    const __m256 lo = _mm256_set1_ps((float)px0), hi = _mm256_set1_ps((float)px1);
    int live_n = 0, stop_n = 0;
    for (int32_t x0 = px0 & ~7; x0 < px1; x0 += 8) {
        const __m256 xs = _mm256_add_ps(_mm256_set1_ps((float)x0), lane);
        const __m256 inside = _mm256_and_ps(_mm256_cmp_ps(xs, lo, _CMP_GE_OQ), _mm256_cmp_ps(xs, hi, _CMP_LT_OQ));
        const __m256 t = _mm256_loadu_ps(trans + x0);
        const __m256 live = _mm256_and_ps(inside, _mm256_cmp_ps(t, zero, _CMP_GT_OQ));
        const __m256 dx = _mm256_sub_ps(v_mx, _mm256_add_ps(xs, _mm256_set1_ps(x_centre0)));
        /* sigma = 0.5 (ca dx^2 + cc dy^2) + cb dx dy */
        const __m256 sigma = _mm256_fmadd_ps(
            half, _mm256_fmadd_ps(_mm256_mul_ps(v_ca, dx), dx, v_ccdy2), _mm256_mul_ps(_mm256_mul_ps(v_cb, dx), v_dy));
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
        __m256 hit = _mm256_and_ps(live, _mm256_cmp_ps(sigma, zero, _CMP_GE_OQ));
        hit = _mm256_and_ps(hit, _mm256_cmp_ps(sigma, v_cut, _CMP_LE_OQ));
        hit = _mm256_and_ps(hit, _mm256_cmp_ps(alpha, v_amin, _CMP_GE_OQ));
        const __m256 next_t = _mm256_mul_ps(t, _mm256_sub_ps(one, alpha));
        const __m256 stop = _mm256_and_ps(hit, _mm256_cmp_ps(next_t, v_tmin, _CMP_LE_OQ));
        const __m256 add = _mm256_andnot_ps(stop, hit);
        const __m256 w = _mm256_and_ps(add, _mm256_mul_ps(alpha, t));
        _mm256_storeu_ps(weights + x0, w);
        /* add: next_t; stop: -t; else t */
        __m256 t_out = _mm256_blendv_ps(t, next_t, add);
        t_out = _mm256_blendv_ps(t_out, _mm256_sub_ps(zero, t), stop);
        _mm256_storeu_ps(trans + x0, t_out);
        _mm256_storeu_ps(acc_r + x0, _mm256_fmadd_ps(w, _mm256_set1_ps(red), _mm256_loadu_ps(acc_r + x0)));
        _mm256_storeu_ps(acc_g + x0, _mm256_fmadd_ps(w, _mm256_set1_ps(green), _mm256_loadu_ps(acc_g + x0)));
        _mm256_storeu_ps(acc_b + x0, _mm256_fmadd_ps(w, _mm256_set1_ps(blue), _mm256_loadu_ps(acc_b + x0)));
        _mm256_storeu_ps(acc_z + x0, _mm256_fmadd_ps(w, _mm256_set1_ps(depth), _mm256_loadu_ps(acc_z + x0)));
        live_n += __builtin_popcount(_mm256_movemask_ps(live));
        stop_n += __builtin_popcount(_mm256_movemask_ps(stop));
    }
    counts[0] += (float)live_n;
    counts[1] += (float)stop_n;
#else
    float live_n = 0.0f, stop_n = 0.0f;
    for (int32_t lx = px0; lx < px1; lx++) {
        float t = trans[lx];
        float live = t > 0.0f ? 1.0f : 0.0f;
        float dx = mx - ((float)lx + x_centre0);
        float sigma = 0.5f * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
        float alpha = fminf(opacity * exp_neg(fminf(fmaxf(sigma, 0.0f), 5.6f)), alpha_max);
        float hit = live * (sigma >= 0.0f ? 1.0f : 0.0f) * (sigma <= cut ? 1.0f : 0.0f) *
                    (alpha >= alpha_min ? 1.0f : 0.0f);
        float next_t = t * (1.0f - alpha);
        float stop = hit * (next_t <= t_min ? 1.0f : 0.0f);
        float add = hit - stop;
        float w = add * alpha * t;
        weights[lx] = w;
        trans[lx] = t + add * (next_t - t) - 2.0f * stop * t;
        acc_r[lx] += w * red;
        acc_g[lx] += w * green;
        acc_b[lx] += w * blue;
        acc_z[lx] += w * depth;
        live_n += live;
        stop_n += stop;
    }
    counts[0] += live_n;
    counts[1] += stop_n;
#endif
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

#endif
