"""Per-flight maps and change scores against the dense reference, and what the rule is for: a
Gaussian seen once obliquely raises no alarm, identical flights score ~0, a change scores high."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.aggregate import AggregationConfig
from olsplat_nodes.aggregate._reference import change_score_dense, flight_evidence_dense
from olsplat_nodes.aggregate.change import ChangeRule, change_score
from olsplat_nodes.aggregate.observe import ViewObservations
from olsplat_nodes.storage import LanguageMap
from olsplat_nodes.storage.flights import flight_map, flights_in
from olsplat_nodes.storage.store import ObservationStore
from olsplat_nodes.storage.tiles import TiledStore, TileGrid, Tiling

CONFIG = AggregationConfig()  # the method's own: T = 3, beta 2/4/8, the retained-views gate
RULE = ChangeRule()


def _store(folder, features, strength, flight, tile_m=0.0, means=None):
    """A run's store at folder/store with view v of flight[v] named f<flight>/view<v>: each kept
    observation one bank row (features [N, V, D] float16-exact, strength [N, V], 0 = unseen)."""
    n = len(features)
    means = np.random.default_rng(9).uniform(0, 30, (n, 3)) if means is None else means
    tiling = Tiling.of(means, TileGrid(tile_m))
    store = TiledStore(folder / "store", tiling, writer=True)
    for v in range(features.shape[1]):
        ids = np.flatnonzero(strength[:, v] > 0)
        observations = ViewObservations(
            ids.astype(np.int32),
            strength[ids, v].astype(np.float32),
            np.arange(len(ids) + 1, dtype=np.int64),
            np.arange(len(ids), dtype=np.int32),
            np.ones(len(ids), np.float32),
        )
        store.append(f"f{flight[v]}/view{v:03d}", observations, features[ids, v])
    return tiling


def _views(rng, n=60, views=10, dim=8, flights=2):
    """Random views in two camps per Gaussian (most agree, some disagree), some never seen."""
    features = rng.normal(size=(n, views, dim))
    features[:, : views * 2 // 3] += 2.5 * rng.normal(size=(n, 1, dim))
    features = features.astype(np.float16).astype(np.float64)  # what the store's float16 bank holds
    strength = (rng.uniform(0.05, 3.0, (n, views)) * (rng.random((n, views)) < 0.7)).astype(np.float32)
    strength[0] = 0.0  # never seen
    strength[1, 1:] = 0.0  # seen once
    flight = np.arange(views) % flights
    return features, strength.astype(np.float64), flight


@pytest.mark.parametrize("tile_m", [0.0, 12.0])
def test_a_flights_map_and_evidence_equal_the_dense_reference(tmp_path, tile_m):
    features, strength, flight = _views(np.random.default_rng(0))
    tiling = _store(tmp_path, features, strength, flight, tile_m)
    assert flights_in(tmp_path / "store", tiling) == {"f0": 5, "f1": 5}
    for k in (0, 1):
        got = flight_map(tmp_path / "store", tiling, f"f{k}", CONFIG, "test")
        assert got is not None and got.has_evidence()
        views = flight == k
        F, W, count, n_eff, spread = flight_evidence_dense(features[:, views], strength[:, views], CONFIG)
        seen = count > 0
        np.testing.assert_array_equal(got.observed, seen)
        unit = F / np.maximum(np.linalg.norm(F, axis=1, keepdims=True), 1e-300)
        np.testing.assert_allclose(got.features[seen].astype(np.float64), unit[seen], atol=1e-3)  # float16 rows
        np.testing.assert_array_equal(got.view_count, count)
        np.testing.assert_allclose(got.strength_sum, W, rtol=1e-6)
        np.testing.assert_allclose(got.effective_views, n_eff, rtol=1e-5)
        np.testing.assert_allclose(got.view_spread[seen], spread[seen], rtol=1e-4, atol=1e-6)
        assert np.isnan(got.view_spread[~seen]).all()


def test_a_flights_map_is_that_flight_aggregated_alone(tmp_path):
    """The views of f1 in a two-flight store give, to the bit, the map of a store of f1 alone."""
    features, strength, flight = _views(np.random.default_rng(1))
    tiling = _store(tmp_path / "both", features, strength, flight)
    alone = _store(tmp_path / "alone", features[:, flight == 1], strength[:, flight == 1], np.ones(5, int))
    ours = flight_map(tmp_path / "both" / "store", tiling, "f1", CONFIG, "test")
    theirs, observed = TiledStore(tmp_path / "alone" / "store", alone).refine(CONFIG)
    assert ours is not None and theirs is not None
    np.testing.assert_array_equal(ours.features, theirs)
    np.testing.assert_array_equal(ours.observed, observed)


def test_change_scores_equal_the_dense_reference(tmp_path):
    features, strength, flight = _views(np.random.default_rng(2), n=80)
    expected = change_score_dense(features, strength, flight, 0, 1, CONFIG, RULE)
    assert np.isfinite(expected).sum() > 20 and np.isnan(expected).sum() > 5  # both kinds are exercised
    # the scoring alone, on the reference's own float64 maps: to float rounding
    maps = []
    for k in (0, 1):
        F, W, count, n_eff, spread = flight_evidence_dense(features[:, flight == k], strength[:, flight == k], CONFIG)
        maps.append(LanguageMap(F, count > 0, "test", strength_sum=W, effective_views=n_eff, view_spread=spread))
    np.testing.assert_allclose(change_score(*maps, RULE), expected, rtol=1e-5, equal_nan=True)
    # end to end through the store and the stored (float16) maps
    tiling = _store(tmp_path, features, strength, flight)
    for k in (0, 1):
        language_map = flight_map(tmp_path / "store", tiling, f"f{k}", CONFIG, "test")
        assert language_map is not None
        language_map.save(tmp_path / f"f{k}.npz")
    got = change_score(LanguageMap.load(tmp_path / "f0.npz"), LanguageMap.load(tmp_path / "f1.npz"), RULE)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got, expected, rtol=0.01, atol=0.01, equal_nan=True)  # float16 features


def _scene(rng, centre_a, centre_b, strength_a, strength_b, scatter=0.15, dim=16):
    """One Gaussian's views: flight a's around centre_a, flight b's around centre_b."""
    views_a = centre_a + scatter * rng.normal(size=(len(strength_a), dim))
    views_b = centre_b + scatter * rng.normal(size=(len(strength_b), dim))
    features = np.concatenate([views_a, views_b])[None]
    strength = np.concatenate([strength_a, strength_b])[None]
    flight = np.array([0] * len(strength_a) + [1] * len(strength_b))
    return features, strength, flight


def _score(features, strength, flight):
    maps = []
    for k in (0, 1):
        F, W, count, n_eff, spread = flight_evidence_dense(features[:, flight == k], strength[:, flight == k], CONFIG)
        maps.append(LanguageMap(F, count > 0, "t", strength_sum=W, effective_views=n_eff, view_spread=spread))
    return float(change_score(*maps, RULE)[0])


def test_the_rule_does_what_it_is_for():
    rng = np.random.default_rng(3)
    dim = 16
    roof, other = np.eye(dim)[0], np.eye(dim)[1]
    grey = 0.4 * roof + np.sqrt(1 - 0.4**2) * other  # cosine distance 0.6 to the roof, as red to grey roofs
    good = np.full(8, 2.0)
    # flights alike: ~0
    assert _score(*_scene(rng, roof, roof, good, good, scatter=0.06)) < 0.5
    # a real appearance change seen well by both flights (8 views each, within ~0.03 of their
    # mean, as the well-seen Gaussians of the tiny town): above the threshold
    assert _score(*_scene(rng, roof, grey, good, good, scatter=0.06)) > RULE.threshold
    # flight b saw it once, obliquely (one view, little weight), and that view says something
    # else: no alarm (unknown)
    assert np.isnan(_score(*_scene(rng, roof, other, good, np.array([0.3]))))
    # one good view and two glimpses are about one view: unknown as well
    assert np.isnan(_score(*_scene(rng, roof, other, good, np.array([3.0, 0.1, 0.1]))))
    # two views that together drew almost no pixel weight: unknown
    assert np.isnan(_score(*_scene(rng, roof, other, good, np.array([0.2, 0.2]))))
    # fewer views: less certain, a lower score for the same change
    few = _score(*_scene(np.random.default_rng(4), roof, grey, good, np.array([2.0, 2.0])))
    many = _score(*_scene(np.random.default_rng(4), roof, grey, good, np.full(12, 2.0)))
    assert few < many


def test_views_split_in_two_camps_raise_no_alarm():
    """Flight a's views of an edge see the roof or the road, the roof winning; flight b's the
    same two, the road winning: the flights' features differ, but each flight's own views
    already disagree that much, so it is no change (the d-weighted spread says so)."""
    dim = 16
    roof, road = np.eye(dim)[0], np.eye(dim)[1]
    features = np.array([[roof, roof, roof, road, road, road, road, roof]], float)
    strength = np.array([[3.0, 3.0, 3.0, 2.0, 3.0, 3.0, 3.0, 2.0]])
    flight = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    assert _score(features, strength, flight) < RULE.threshold


def test_misuse_is_refused(tmp_path):
    plain = LanguageMap(np.eye(3, dtype=np.float16), np.ones(3, bool), "t")
    with pytest.raises(ValueError, match="carries no evidence"):
        change_score(plain, plain)
    with pytest.raises(ValueError, match="min_views"):
        ChangeRule(min_views=0.5)
    with pytest.raises(ValueError, match="a store's writer sees every view"):
        ObservationStore(tmp_path, 3, writer=True, keep=lambda name: True)


def test_the_medians_evidence_equals_the_dense_reference():
    """VALA's streaming median (``--method vala``) gives its evidence too: the spread about z."""
    from olsplat_nodes.aggregate._reference import streaming_median_reference
    from olsplat_nodes.aggregate.refine import MixedObservations, refine_mixed

    features, strength, _ = _views(np.random.default_rng(5))
    owner, view = np.nonzero(strength)
    n = len(features)
    sums, effective, spread = np.zeros(n), np.zeros(n), np.full(n, np.nan)
    observations = MixedObservations.dense(owner, strength[owner, view], features[owner, view])
    median = AggregationConfig(combine="streaming_median")
    z, _ = refine_mixed(observations, n, median, evidence=(sums, effective, spread))
    expected, _ = streaming_median_reference(owner, view, strength[owner, view], features[owner, view], n)
    np.testing.assert_allclose(z, expected, atol=1e-5)
    for i in range(n):
        seen = strength[i] > 0
        if not seen.any():
            assert np.isnan(spread[i]) and sums[i] == 0
            continue
        d, f = strength[i, seen], features[i, seen]
        cos = f @ expected[i] / np.linalg.norm(f, axis=1)
        assert spread[i] == pytest.approx((d * (1 - cos)).sum() / d.sum(), rel=1e-4, abs=1e-6)
        assert effective[i] == pytest.approx(d.sum() ** 2 / (d**2).sum(), rel=1e-9)
