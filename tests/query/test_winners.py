"""The relevance kernels (query/winners.py: numba over float32 rows, C over float16 ones) against
the numpy rule (query/_reference.py)."""

import numpy as np
import pytest

from olsplat_nodes.native import library
from olsplat_nodes.query._reference import winners_reference
from olsplat_nodes.query.answer import QueryFeatures
from olsplat_nodes.query.localize import VoxelIndex
from olsplat_nodes.query.winners import gather_verdicts, winning_rows

NONE = np.zeros(0, np.bool_)


def unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def margins(table, embeddings):
    """Per row, the query's dot product minus the best negative's (float64)."""
    dots = np.asarray(table, np.float64) @ np.asarray(embeddings, np.float64).T
    return dots[:, 0] - dots[:, 1:].max(1)


@pytest.mark.parametrize("negatives", [1, 3, 12])
def test_winning_rows_follow_the_rule_away_from_ties(negatives):
    rng = np.random.default_rng(negatives)
    table = unit(rng.normal(size=(20_000, 128)))
    embeddings = unit(rng.normal(size=(1 + negatives, 128)))
    got = winning_rows(table, embeddings, NONE)
    expected = winners_reference(table, embeddings)
    clear = np.abs(margins(table, embeddings)) > 1e-5  # float32 sums in another order decide ties
    assert clear.mean() > 0.99 and 0.01 < expected.mean() < 0.99
    np.testing.assert_array_equal(got[clear], expected[clear])


def test_exact_ties_go_to_the_query_and_unobserved_rows_never_win():
    embeddings = np.eye(3, 8, dtype=np.float32)
    table = np.zeros((5, 8), np.float32)
    table[0, :2] = 0.5  # query and first negative tie: the query wins (argmax takes the first)
    table[1, 1] = 1.0  # a negative wins
    table[2, 0] = 1.0  # the query wins, but the row is not observed
    table[3, 0] = 1.0
    # row 4 is a zero row: every dot product ties at 0
    observed = np.array([True, True, False, True, True])
    np.testing.assert_array_equal(winning_rows(table, embeddings, NONE), [True, False, True, True, True])
    np.testing.assert_array_equal(winning_rows(table, embeddings, observed), [True, False, False, True, True])
    np.testing.assert_array_equal(winning_rows(table, embeddings, NONE), winners_reference(table, embeddings))


def test_codebook_verdicts_gather_through_the_rows():
    rng = np.random.default_rng(7)
    centres = unit(rng.normal(size=(64, 32)))
    embeddings = unit(rng.normal(size=(4, 32)))
    rows = rng.integers(-1, 64, 5_000).astype(np.int32)
    observed = rng.random(5_000) < 0.8
    verdicts = winning_rows(centres, embeddings, NONE)
    got = gather_verdicts(verdicts, rows, observed)
    np.testing.assert_array_equal(got, winners_reference(centres, embeddings, rows) & observed)
    np.testing.assert_array_equal(gather_verdicts(verdicts, rows, NONE), winners_reference(centres, embeddings, rows))


def test_query_features_winners_match_the_rule_for_dense_and_codebook_maps():
    rng = np.random.default_rng(3)
    n = 3_000
    means = rng.uniform(0, 50, (n, 3))
    observed = rng.random(n) < 0.9
    embeddings = unit(rng.normal(size=(3, 16)))
    dense = unit(rng.normal(size=(n, 16)))
    dense[~observed] = 0.0
    clear = np.abs(margins(dense, embeddings)) > 1e-5
    got = QueryFeatures(dense).winners(embeddings, observed)
    np.testing.assert_array_equal(got[clear], (winners_reference(dense, embeddings) & observed)[clear])
    centres = unit(rng.normal(size=(50, 16)))
    rows = rng.integers(0, 50, n).astype(np.int32)
    rows[~observed] = -1
    book = QueryFeatures(centres, rows)
    expected = winners_reference(centres, embeddings, rows)
    np.testing.assert_array_equal(book.winners(embeddings, observed), expected)
    index = VoxelIndex.build(means, 2.0)
    np.testing.assert_array_equal(book.winners_in_order(embeddings, index), expected[index.order])
    assert QueryFeatures(dense).winners_in_order(embeddings, index) is None


needs_c = pytest.mark.skipif(library() is None, reason="the C kernels are not built here")


@needs_c
@pytest.mark.parametrize("dim,negatives", [(128, 3), (70, 1), (13, 12)])
def test_float16_rows_follow_the_rule_in_c(dim, negatives):
    """float16 tables (a language map's stored form) go to native/winning_rows.c: the rule on
    their float32 values, away from ties; dims off the 8-value blocks take the scalar tail."""
    rng = np.random.default_rng(dim)
    table = unit(rng.normal(size=(30_000, dim))).astype(np.float16)
    table[::11] = 0.0
    embeddings = unit(rng.normal(size=(1 + negatives, dim)))
    observed = rng.random(30_000) < 0.8
    wide = table.astype(np.float32)
    clear = np.abs(margins(wide, embeddings)) > 1e-5
    clear[::11] = True  # zero rows tie exactly at 0: the query wins
    expected = winners_reference(wide, embeddings)
    np.testing.assert_array_equal(winning_rows(table, embeddings, NONE)[clear], expected[clear])
    np.testing.assert_array_equal(winning_rows(table, embeddings, observed)[clear], (expected & observed)[clear])


@needs_c
def test_query_features_keep_a_maps_float16_rows():
    """QueryFeatures.of keeps a map's float16 rows (no float32 copy) where the C kernels are built."""
    from olsplat_nodes.storage.snapshot import LanguageMap

    rng = np.random.default_rng(2)
    observed = rng.random(500) < 0.7
    language_map = LanguageMap.from_features(rng.normal(size=(500, 32)) * observed[:, None], observed, "test")
    features = QueryFeatures.of(language_map)
    assert features.table.dtype == np.float16 and np.shares_memory(features.table, language_map.features)
    embeddings = unit(rng.normal(size=(3, 32)))
    expected = winners_reference(language_map.features.astype(np.float32), embeddings) & observed
    clear = np.abs(margins(language_map.features, embeddings)) > 1e-5
    np.testing.assert_array_equal(features.winners(embeddings, observed)[clear], expected[clear])
