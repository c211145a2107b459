/* The relevance rule of README "Queries" over a float16 table, as ``query/winners.winning_rows``
 * does it over float32 rows in numba (numba has no float16): row g wins when its dot product
 * with embeddings[0] is at least its dot product with every other embedding. Each row is read
 * once, only when observed, widened to float32 exactly (F16C); the negatives are tried one at a
 * time until one beats the query. A language map stores its rows as float16, so this reads half
 * the bytes of a float32 pass. Tested against ``query/_reference.winners_reference``
 * (tests/query/test_winners.py).
 */
#include <stdint.h>
#ifdef __AVX2__
#include <immintrin.h>
#endif

#ifdef __AVX2__
static inline float sum8_rows(__m256 v)
{
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    s = _mm_add_ss(s, _mm_movehdup_ps(s));
    return _mm_cvtss_f32(s);
}
#endif

static inline float half_bits_to_float(uint16_t h) /* IEEE binary16 -> float, exactly */
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

/* Dot product of a float16 row with a float32 embedding, both [dim]. */
static inline float dot_half(const uint16_t *row, const float *embedding, int64_t dim)
{
    int64_t d = 0;
    float tail = 0.0f;
#ifdef __AVX2__
    __m256 sum = _mm256_setzero_ps();
    for (; d + 8 <= dim; d += 8)
        sum = _mm256_fmadd_ps(_mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)(row + d))),
                              _mm256_loadu_ps(embedding + d), sum);
    tail = sum8_rows(sum);
#endif
    for (; d < dim; d++)
        tail += half_bits_to_float(row[d]) * embedding[d];
    return tail;
}

/* wins[g] = 1 when row g of table [n, dim] (float16 bits) picks embeddings[0] over every other of
 * the n_embeddings rows of embeddings [n_embeddings, dim] float32, and observed[g] (observed:
 * [n] uint8, or NULL: every row counts); else 0. */
void winning_rows_half(const uint16_t *table, int64_t n, int64_t dim, const float *embeddings,
                       int64_t n_embeddings, const uint8_t *observed, uint8_t *wins, int threads)
{
#pragma omp parallel for schedule(static, 4096) num_threads(threads)
    for (int64_t g = 0; g < n; g++) {
        wins[g] = 0;
        if (observed && !observed[g])
            continue;
        const uint16_t *row = table + g * dim;
        const float query = dot_half(row, embeddings, dim);
        int won = 1;
        for (int64_t q = 1; q < n_embeddings && won; q++)
            won = dot_half(row, embeddings + q * dim, dim) <= query;
        wins[g] = (uint8_t)won;
    }
}
