/* The relevance rule of README "Queries" over a float16 table, as ``query/winners.winning_rows``
 * does it over float32 rows in numba (numba has no float16): row g wins when its dot product
 * with embeddings[0] is at least its dot product with every other embedding. Each row is read
 * once, only when observed, widened to float32 exactly (F16C); the negatives are tried one at a
 * time until one beats the query. A language map stores its rows as float16, so this reads half
 * the bytes of a float32 pass. Tested against ``query/_reference.winners_reference``
 * (tests/query/test_winners.py).
 */
#include <stdint.h>

#include "simd.h"

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
    tail = sum8(sum);
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
