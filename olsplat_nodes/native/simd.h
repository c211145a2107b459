/* Small helpers the C kernels share (heatmap_composite.c, winning_rows.c). */
#ifndef OLSPLAT_NATIVE_SIMD_H
#define OLSPLAT_NATIVE_SIMD_H

#include <stdint.h>
#if defined(__AVX2__) || defined(__F16C__)
#include <immintrin.h>
#endif

/* IEEE binary16 bits -> float, exactly (F16C when built with it, else by the bit layout). */
static inline float half_bits_to_float(uint16_t h)
{
#ifdef __F16C__
    return _cvtsh_ss(h);
#else
    const uint32_t sign = (uint32_t)(h & 0x8000) << 16, exponent = (h >> 10) & 0x1f, mantissa = h & 0x3ff;
    union { uint32_t u; float f; } out;
    if (exponent == 0x1f) /* inf, nan */
        out.u = sign | 0x7f800000u | (mantissa << 13);
    else if (exponent == 0) /* zero, subnormal: mantissa * 2^-24 */
        return (h & 0x8000 ? -1.0f : 1.0f) * (float)mantissa * (1.0f / 16777216.0f);
    else
        out.u = sign | ((exponent + 112) << 23) | (mantissa << 13);
    return out.f;
#endif
}

#ifdef __AVX2__
/* The sum of a register's 8 floats. */
static inline float sum8(__m256 v)
{
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    s = _mm_add_ss(s, _mm_movehdup_ps(s));
    return _mm_cvtss_f32(s);
}
#endif

#endif
