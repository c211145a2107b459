"""Look-alike feature errors (evaluate/confusion.py) against a slow, obviously-correct version,
and the properties the stress test promises: a surface is confused the same way in every view
at rho = 1, the substituted labels follow the confusion matrix, and every observation is
confused with probability p whatever rho."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.evaluate.confusion import (
    LevelTruth,
    Lookalikes,
    _confuse_lookalike_reference,
    confuse_lookalike,
    draw_labels,
    keyed_uniforms,
    lookalike_rows,
    measure_lookalikes,
    region_majority,
)

K, D = 5, 16


def _unit(x):
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _looks(rng, rows=None, has_prototype=None, levels=2):
    """Look-alikes with random stand-ins; label 4 never gets a prototype (the text fallback)."""
    counts = rng.integers(0, 20, (K, K))
    counts[2] = 0
    counts[2, 2] = 30  # a label never wrong: falls back to the other labels' regions
    if has_prototype is None:
        has_prototype = np.ones((levels, K), bool)
        has_prototype[:, 4] = False
    return Lookalikes(
        counts=counts,
        rows=lookalike_rows(counts) if rows is None else rows,
        prototypes=_unit(rng.normal(size=(levels, K, D))),
        has_prototype=has_prototype,
        texts=_unit(rng.normal(size=(K, D))),
    )


def _flight(rng, views=6, surfaces=30, regions=(12, 40), absent=(3, 4)):
    """A small synthetic flight: per view and level, regions on random surfaces (some on none),
    each region's truth its surface's label. Labels in ``absent`` have no region in odd views
    (so a look-alike of them needs the prototype or the text)."""
    surface_ids = rng.choice(10**12, surfaces, replace=False) + 10**12
    surface_labels = rng.integers(0, K, surfaces)
    flight = []
    for v in range(views):
        bank, levels = [], []
        for r in regions:
            pick = rng.integers(-1, surfaces, r)  # -1: on no surface
            label = np.where(pick >= 0, surface_labels[pick], -1)
            if v % 2:
                drop = np.isin(label, absent)
                pick, label = np.where(drop, -1, pick), np.where(drop, -1, label)
            surface = np.where(pick >= 0, surface_ids[pick], -1)
            bank.append(_unit(rng.normal(size=(r, D))))
            levels.append(LevelTruth(label.astype(np.int64), surface.astype(np.int64), label.astype(np.int64)))
        flight.append((bank, levels))
    return flight


def _received(before, after, levels, looks, level):
    """Per region of one level: -1 if unchanged, else the label of the feature it received (the
    donor region's truth, or the label of the prototype or text it equals)."""
    out = np.full(len(before), -1)
    for r in np.flatnonzero((before != after).any(1)):
        donors = np.flatnonzero((before == after[r]).all(1))
        if len(donors):
            out[r] = levels[level].truth[donors[0]]
        elif (looks.prototypes[level] == after[r]).all(1).any():
            out[r] = np.flatnonzero((looks.prototypes[level] == after[r]).all(1))[0]
        else:
            out[r] = np.flatnonzero((looks.texts == after[r]).all(1))[0]
    return out


@pytest.mark.parametrize(("p", "rho", "seed"), [(0.3, 0.7, 0), (1.0, 0.0, 1), (1.0, 1.0, 2), (0.5, 0.5, 3)])
def test_fast_confusion_matches_the_reference(p, rho, seed):
    rng = np.random.default_rng(seed)
    looks = _looks(rng)
    kinds = set()
    for view, (bank, levels) in enumerate(_flight(rng)):
        fast = confuse_lookalike(bank, levels, view, looks, p, rho, seed)
        slow = _confuse_lookalike_reference(bank, levels, view, looks, p, rho, seed)
        for level, (a, b, before) in enumerate(zip(fast, slow, bank, strict=True)):
            np.testing.assert_array_equal(a, b)
            changed = (a != before).any(1)
            assert not changed[levels[level].surface < 0].any()  # no surface, no confusion
            for row in a[changed]:
                if (before == row).all(1).any():
                    kinds.add("donor")
                else:
                    kinds.add("prototype" if (looks.prototypes[level] == row).all(1).any() else "text")
    assert kinds == {"donor", "prototype", "text"}  # every stand-in was compared


def test_nothing_changes_at_p_zero_and_the_input_is_left_alone():
    rng = np.random.default_rng(4)
    looks = _looks(rng)
    bank, levels = _flight(rng, views=1)[0]
    copies = [f.copy() for f in bank]
    for a, b in zip(confuse_lookalike(bank, levels, 0, looks, 0.0, 0.7, 0), bank, strict=True):
        np.testing.assert_array_equal(a, b)
    confuse_lookalike(bank, levels, 0, looks, 1.0, 0.7, 0)
    assert all(np.array_equal(a, b) for a, b in zip(bank, copies, strict=True))
    with pytest.raises(ValueError, match="feature rows"):
        confuse_lookalike([bank[0][:-1], bank[1]], levels, 0, looks, 0.5, 0.7, 0)


def _outcomes(flight, looks, p, rho, seed):
    """surface -> the set of labels its observations received (-1: not confused)."""
    seen: dict[int, set[int]] = {}
    for view, (bank, levels) in enumerate(flight):
        after = confuse_lookalike(bank, levels, view, looks, p, rho, seed)
        for level in range(len(bank)):
            got = _received(bank[level], after[level], levels, looks, level)
            for surface, label in zip(levels[level].surface, got, strict=True):
                if surface >= 0:
                    seen.setdefault(int(surface), set()).add(int(label))
    return seen


def test_at_full_correlation_a_surface_is_confused_the_same_way_in_every_view():
    rng = np.random.default_rng(5)
    looks = _looks(rng)
    flight = _flight(rng, views=8, surfaces=40, absent=())
    together = _outcomes(flight, looks, 0.5, 1.0, seed=7)
    assert all(len(labels) == 1 for labels in together.values()), together
    assert {-1} in together.values() and any(labels != {-1} for labels in together.values())
    apart = _outcomes(flight, looks, 0.5, 0.0, seed=7)
    assert sum(len(labels) > 1 for labels in apart.values()) > len(apart) // 2  # independent views differ


def test_substituted_labels_follow_the_confusion_matrix():
    rng = np.random.default_rng(6)
    rows = np.array(
        [
            [0.0, 0.7, 0.2, 0.1, 0.0],
            [0.5, 0.0, 0.5, 0.0, 0.0],
            [0.1, 0.1, 0.0, 0.1, 0.7],
            [0.0, 0.0, 1.0, 0.0, 0.0],
            [0.25, 0.25, 0.25, 0.25, 0.0],
        ]
    )
    looks = _looks(rng, rows=rows)
    flight = _flight(rng, views=10, surfaces=600, regions=(300,), absent=())
    got = np.zeros((K, K))
    for view, (bank, levels) in enumerate(flight):
        after = confuse_lookalike(bank, levels, view, looks, 1.0, 0.3, seed=11)
        received = _received(bank[0], after[0], levels, looks, 0)
        on = levels[0].surface >= 0
        assert (received[on] >= 0).all()  # p = 1: every region on a surface is confused
        np.add.at(got, (levels[0].surface_label[on], received[on]), 1)
    observed = got / got.sum(1, keepdims=True)
    n = got.sum(1, keepdims=True)
    # generous: 5 standard errors (observations of one surface are correlated, so fewer are free)
    bound = 5 * np.sqrt(rows * (1 - rows) / (n / 10)) + 0.02
    assert (np.abs(observed - rows) <= bound).all(), (observed.round(2), rows)
    assert (observed[rows == 0] == 0).all()  # never a label of zero probability, nor the true one


@pytest.mark.parametrize("rho", [0.0, 0.7, 1.0])
def test_every_observation_is_confused_with_probability_p_whatever_the_correlation(rho):
    rng = np.random.default_rng(8)
    looks = _looks(rng)
    flight = _flight(rng, views=12, surfaces=400, regions=(400,), absent=())
    hits = total = 0
    for view, (bank, levels) in enumerate(flight):
        after = confuse_lookalike(bank, levels, view, looks, 0.3, rho, seed=3)
        # one observation per (surface, view): its regions share the decision
        on = levels[0].surface >= 0
        decided = dict(zip(levels[0].surface[on], (after[0] != bank[0]).any(1)[on], strict=True))
        hits += sum(decided.values())
        total += len(decided)
    assert abs(hits / total - 0.3) < 0.04


def test_lookalike_rows_normalise_the_off_diagonal_and_fall_back_to_other_labels_regions():
    counts = np.array([[5, 3, 1], [0, 9, 0], [2, 2, 6]])
    rows = lookalike_rows(counts)
    np.testing.assert_allclose(rows[0], [0, 0.75, 0.25])
    np.testing.assert_allclose(rows[1], [9 / 19, 0, 10 / 19])  # never wrong: the other labels' regions
    np.testing.assert_allclose(rows[2], [0.5, 0.5, 0])
    np.testing.assert_allclose(lookalike_rows(np.zeros((3, 3), int))[0], [0, 0.5, 0.5])  # no regions at all
    with pytest.raises(ValueError, match="two labels"):
        lookalike_rows(np.ones((1, 1), int))


def test_draw_labels_inverts_the_cumulative_distribution():
    rows = np.array([[0.0, 0.5, 0.0, 0.5, 0.0]] * 4)
    np.testing.assert_array_equal(draw_labels(rows, np.array([0.0, 0.4999, 0.5, 0.9999999])), [1, 1, 3, 3])


def test_keyed_uniforms_are_uniform_and_depend_only_on_their_keys():
    a = keyed_uniforms(7, 2, np.arange(20000), 3)
    assert ((a >= 0) & (a < 1)).all() and abs(a.mean() - 0.5) < 0.01 and abs(a.var() - 1 / 12) < 0.005
    assert float(keyed_uniforms(7, 2, 123, 3)[0]) == a[123]
    assert keyed_uniforms(7, 2, 123, 4)[0] != a[123] and keyed_uniforms(8, 2, 123, 3)[0] != a[123]


def test_region_majority_against_a_loop():
    rng = np.random.default_rng(9)
    regions = rng.integers(-1, 7, (30, 40))
    values = rng.integers(-1, 4, (30, 40))
    expected = np.full(8, -1)
    for r in range(8):
        found = values[regions == r].tolist()
        if found:
            expected[r] = min(set(found), key=lambda v: (-found.count(v), v))
    np.testing.assert_array_equal(region_majority(regions, values, 8), expected)


def test_measure_lookalikes_counts_the_finest_level_and_averages_features():
    texts = np.eye(3, 4, dtype=np.float32)
    features = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [1, 0.1, 0, 0], [0, 0, 0, 1]], np.float32)
    truth = np.array([0, 0, 1, -1])
    levels = [LevelTruth(truth, np.zeros(4, np.int64), truth)]
    looks = measure_lookalikes([([_unit(features)], levels)], texts)
    np.testing.assert_array_equal(looks.counts, [[1, 1, 0], [1, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(looks.has_prototype, [[True, True, False]])
    np.testing.assert_allclose(looks.prototypes[0, 0], _unit(np.array([1.0, 1.0, 0, 0])), rtol=1e-6)
    np.testing.assert_allclose(looks.rows[1], [1, 0, 0])
