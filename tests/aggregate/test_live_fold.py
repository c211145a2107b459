"""A live map's fold: new views folded into the running features, against the numpy oracle
(``fold_dense``), for the median against a pass over all views, and through the store."""

from __future__ import annotations

import math

import numpy as np
import pytest

from olsplat_nodes.aggregate import AggregationConfig
from olsplat_nodes.aggregate._reference import fold_dense, refine_dense
from olsplat_nodes.aggregate.refine import MixedObservations, refine_mixed
from olsplat_nodes.storage import ObservationStore

from .test_refine_store import _views

CONFIGS = [
    AggregationConfig(),
    AggregationConfig(min_retained_views=None),
    AggregationConfig(iterations=2, beta=(1.0, 3.0), min_retained_views=0.8),
    AggregationConfig(iterations=0),
]


def _observations(features, strength):
    owner, view = np.nonzero(strength)
    return MixedObservations.dense(owner, strength[owner, view], features[owner, view])


@pytest.mark.parametrize("config", CONFIGS)
def test_the_fold_equals_the_dense_equations(config):
    rng = np.random.default_rng(3)
    n, dim = 60, 5
    early, late = rng.normal(size=(n, 4, dim)), rng.normal(size=(n, 3, dim))
    early[:, :3] += 2.0 * rng.normal(size=(n, 1, dim))
    late += early[:, :1]  # the new views mostly agree with the first ones
    seen_early = rng.uniform(0.1, 1.0, (n, 4)) * (rng.random((n, 4)) < 0.7)
    seen_late = rng.uniform(0.1, 1.0, (n, 3)) * (rng.random((n, 3)) < 0.7)
    seen_early[:10] = 0.0  # first seen in the new views: computed exactly
    seen_late[10:15] = 0.0  # not in the new views: left alone

    weight, norm = np.zeros(n), np.zeros(n)
    first, _ = refine_mixed(_observations(early, seen_early), n, config, (np.zeros((0, dim), np.float32), weight, norm))
    expected_first, expected_weight = fold_dense(np.zeros((n, dim)), np.zeros(n), early, seen_early, config)
    np.testing.assert_allclose(first, expected_first, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(weight, expected_weight, rtol=1e-5)
    np.testing.assert_allclose(norm, np.linalg.norm(expected_first, axis=1), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(first, refine_dense(early, seen_early, config), rtol=1e-5, atol=1e-6)

    # the prior as a live refiner keeps it: unit rows (float16) and the norms
    unit = (first / np.maximum(np.linalg.norm(first, axis=1, keepdims=True), 1e-12)).astype(np.float16)
    rows = unit.astype(np.float64)
    prior_mean = rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12) * norm[:, None]
    before = weight.copy()
    folded, _ = refine_mixed(_observations(late, seen_late), n, config, (unit.astype(np.float32), weight, norm))
    expected, expected_weight = fold_dense(prior_mean, before, late, seen_late, config)
    moved = seen_late.any(1)
    np.testing.assert_allclose(folded[moved], expected[moved], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(weight, expected_weight, rtol=1e-5)
    assert not folded[~moved].any() and (weight[10:15] == before[10:15]).all()
    # Gaussians first seen now are exact; the others differ from an exact pass over all views
    both = np.concatenate([early, late], 1), np.concatenate([seen_early, seen_late], 1)
    exact = refine_dense(*both, config)
    np.testing.assert_allclose(folded[:10], exact[:10], rtol=1e-5, atol=1e-6)


def test_the_median_folds_exactly():
    """VALA's streaming median is incremental by nature: two folds give one pass's result."""
    rng = np.random.default_rng(4)
    n, dim = 50, 6
    features, strength = rng.normal(size=(n, 6, dim)), rng.uniform(0.1, 1, (n, 6)) * (rng.random((n, 6)) < 0.7)
    config = AggregationConfig(combine="streaming_median")
    owner, view = np.nonzero(strength.T)[::-1]  # in arrival order: view by view
    whole, _ = refine_mixed(MixedObservations.dense(owner, strength[owner, view], features[owner, view]), n, config)
    weight, norm = np.zeros(n), np.zeros(n)
    state = (np.zeros((0, dim), np.float32), weight, norm)
    half = np.zeros_like(strength)
    half[:, :3] = strength[:, :3]
    first, _ = refine_mixed(_observations(features, half), n, config, state)
    rest = strength - half
    folded, _ = refine_mixed(_observations(features, rest), n, config, (first, weight, norm))
    later = rest.any(1)
    np.testing.assert_allclose(folded[later], whole[later], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(first[~later], whole[~later], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(weight, strength.sum(1), rtol=1e-6)


def test_a_state_with_a_wrong_shape_is_refused():
    observations = _observations(np.ones((3, 2, 4)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="state for 3 Gaussians of width 4"):
        refine_mixed(observations, 3, AggregationConfig(), (np.zeros((2, 4), np.float32), np.zeros(3), np.zeros(3)))


@pytest.mark.parametrize("unit_float16", [False, True])
def test_the_store_folds_new_views_as_the_kernel_does(tmp_path, unit_float16):
    """``refine(views=...)`` folds exactly the segments asked for, range by range, into F and the
    state, the same as the kernel over those views' observations; an exact pass afterwards
    equals a pass of a fresh store (the final map stays exact)."""
    n, config = 150, AggregationConfig()
    store = ObservationStore(tmp_path / "s", n, writer=True)
    views = list(_views(5, n))
    for view in views[:2]:
        store.append(*view)
    weight, norm = np.zeros(n), np.zeros(n)
    F, _ = store.refine(None, config, False, unit_float16=unit_float16, state=(weight, norm))
    for view in views[2:]:
        store.append(*view)
    prior, prior_weight, prior_norm = F.astype(np.float32), weight.copy(), norm.copy()
    new = store.gather(np.ones(n, bool), views=(2, 5))
    expected, _ = refine_mixed(new, n, config, (prior, prior_weight, prior_norm))
    F, folded = store.refine(F, config, unit_float16=unit_float16, state=(weight, norm), views=(2, 5), max_gaussians=9)
    assert store.touched.any()  # a fold leaves the exact pass's bookkeeping alone
    changed = np.bincount(new.owner, minlength=n) > 0
    np.testing.assert_array_equal(folded, changed)
    if unit_float16:
        expected /= np.maximum(np.linalg.norm(expected, axis=1, keepdims=True), 1e-12)
    tolerance = 1e-3 if unit_float16 else 1e-6
    np.testing.assert_allclose(F[changed].astype(np.float32), expected[changed], rtol=tolerance, atol=tolerance)
    np.testing.assert_allclose(weight, prior_weight, rtol=1e-6)
    np.testing.assert_allclose(norm, prior_norm, rtol=1e-6)

    live = F.copy()
    final, _ = store.refine(F, config, False, unit_float16=unit_float16, state=(weight, norm))
    fresh = ObservationStore(tmp_path / "fresh", n, writer=True)
    for view in views:
        fresh.append(*view)
    exact, _ = fresh.refine(None, config, False, unit_float16=unit_float16)
    np.testing.assert_array_equal(final, exact)
    assert not np.array_equal(live, exact)  # the fold is an approximation for Gaussians seen before

    with pytest.raises(ValueError, match="needs the current features"):
        store.refine(None, config, state=(weight, norm), views=(4, 5))


def test_a_live_map_folds_refreshes_and_ends_exact(tmp_path):
    """LiveMap's passes over a growing store: the first is exact; a fold changes the rows of the
    Gaussians its views touched plus its refresh slice; a refresh budget as large as the map
    makes a fold recompute everything exactly; the final exact pass equals an offline pass."""
    from olsplat_nodes.method.live import LiveMap

    n, config = 150, AggregationConfig()
    views = list(_views(6, n))
    stores = {k: ObservationStore(tmp_path / k, n, writer=True) for k in ("plain", "whole", "offline")}
    live = {  # never the cheaper exact pass here (fold_limit inf): the folds themselves are tested
        "plain": LiveMap(stores["plain"], refresh=0.0, fold_limit=math.inf),
        "whole": LiveMap(stores["whole"], refresh=1e9, fold_limit=math.inf),
    }
    for store in stores.values():
        for view in views[:2]:
            store.append(*view)
    for live_map in live.values():
        assert live_map.update(config, exact=False) is None  # the first pass: exact, every row
    assert not live["plain"].update(config, exact=False).any()  # no new view: nothing to do
    for store in stores.values():
        for view in views[2:]:
            store.append(*view)
    changed = {k: m.update(config, exact=False) for k, m in live.items()}
    new_ids = np.unique(np.concatenate([np.asarray(v[1].gaussians) for v in views[2:]]))
    assert set(np.flatnonzero(changed["plain"])) == set(new_ids) and live["plain"].views == 6
    offline, observed = stores["offline"].refine(None, config, False, unit_float16=True)
    np.testing.assert_array_equal(live["whole"].features, offline)  # everything refreshed: exact
    np.testing.assert_array_equal(live["whole"].observed, observed)
    assert changed["whole"].sum() == observed.sum()
    np.testing.assert_array_equal(live["whole"].exact_at, live["whole"].seen)  # nothing left stale
    assert not np.array_equal(live["plain"].features, offline)
    live["plain"].update(config, exact=True)  # the final pass
    np.testing.assert_array_equal(live["plain"].features, offline)
    np.testing.assert_array_equal(live["plain"].observed, observed)


def test_the_refresh_takes_the_likeliest_wrong_gaussians_within_its_budget(tmp_path):
    """After each fold the refresh recomputes, exactly, the stale Gaussians (folded observations
    since their last exact computation) with the largest spread x share / seen (ties by index),
    as many as ``refresh`` times the new view's observations hold: the ranking against a plain
    Python oracle on the live map's state at that moment, the refreshed rows against an offline
    pass, the counts against the store's own."""
    from olsplat_nodes.method.live import LiveMap

    n, config = 150, AggregationConfig()
    # unit region features, as the encoders give: a mean's length then tells how views agree
    views = [(name, obs, bank / np.linalg.norm(bank, axis=1, keepdims=True)) for name, obs, bank in _views(8, n)]
    store = ObservationStore(tmp_path / "s", n, writer=True)
    offline = ObservationStore(tmp_path / "offline", n, writer=True)
    live = LiveMap(store, refresh=2.0, fold_limit=math.inf)
    chosen: list[np.ndarray] = []
    reordered: list[bool] = []
    real = live.stalest

    def oracle(budget: float):
        seen, exact_at, norm = live.seen.astype(np.int64), live.exact_at.astype(np.int64), live.norm
        priority = {
            g: (1 - min(max(norm[g], 0.0), 1.0)) * (seen[g] - exact_at[g]) / seen[g] ** 2
            for g in range(n)
            if seen[g] > exact_at[g]
        }
        ranked = sorted(priority, key=lambda g: (-priority[g], g))
        reordered.append(ranked != sorted(priority))  # not the index order: the priorities rank
        take, spent = 0, 0
        while take < len(ranked) and spent + seen[ranked[take]] <= budget:
            spent += seen[ranked[take]]
            take += 1
        expected = np.zeros(n, bool)
        expected[ranked[: max(take, 1)]] = True
        got = real(budget)
        np.testing.assert_array_equal(got, expected)
        assert budget == 2.0 * (seen.sum() - seen_before.sum())
        chosen.append(got)
        return got

    live.stalest = oracle
    for s_ in (store, offline):
        s_.append(*views[0])
    live.update(config, exact=True)
    np.testing.assert_array_equal(live.exact_at, live.seen)  # everything exact after an exact pass
    for view in views[1:]:
        for s_ in (store, offline):
            s_.append(*view)
        seen_before, exact_before = live.seen.astype(np.int64), live.exact_at.astype(np.int64)
        live.update(config, exact=False)
        seen = store.observation_counts().astype(np.int64)
        np.testing.assert_array_equal(live.seen, seen)
        expected = exact_before.copy()
        expected[seen_before == 0] = seen[seen_before == 0]  # first seen in this view: folded exactly
        expected[chosen[-1]] = seen[chosen[-1]]
        np.testing.assert_array_equal(live.exact_at, expected)
        reference, _ = offline.refine(None, config, False, unit_float16=True)
        np.testing.assert_array_equal(live.features[chosen[-1]], reference[chosen[-1]])  # refreshed: exact
    assert len(chosen) == len(views) - 1 and all(c.any() for c in chosen) and all(reordered)
    assert real(0.0) is None


def test_a_fold_that_would_read_more_than_its_share_of_an_exact_pass_is_exact(tmp_path):
    """A live pass folds while the observations it would read (the new ones plus its refresh's,
    at most the still-stale Gaussians' observations) are at most ``fold_limit`` times an exact
    pass's (every Gaussian touched since the last exact pass, all of its views); above that it
    is exact: the offline map's rows, nothing left stale. The counts against a Python oracle
    over the views' id lists; fold_limit 0 makes every pass with a new view exact."""
    from olsplat_nodes.method.live import LiveMap

    n, config = 150, AggregationConfig()
    views = list(_views(5, n))
    ids = [set(np.asarray(v[1].gaussians).tolist()) for v in views]

    def oracle(done: int, exact_done: int, arriving: int) -> dict:
        """Reads after exact passes over views < exact_done, folds up to ``done``, then ``arriving``."""
        seen = {g: sum(g in s for s in ids[: done + 1]) for g in range(n)}
        seen_at_exact = {g: sum(g in s for s in ids[:exact_done]) for g in range(n)}
        added = len(ids[arriving])
        stale = [g for g in range(n) if sum(g in s for s in ids[:done]) > 0 and seen[g] > seen_at_exact[g]]
        touched = set().union(*ids[exact_done : done + 1])
        refresh = min(2.0 * added, sum(seen[g] for g in stale))
        return {"added": added, "fold": int(added + refresh), "exact": sum(seen[g] for g in touched)}

    offline = ObservationStore(tmp_path / "offline", n, writer=True)
    for limit, kinds in ((math.inf, [False, False]), (0.0, [True, True])):
        store = ObservationStore(tmp_path / f"s{limit}", n, writer=True)
        live = LiveMap(store, refresh=2.0, fold_limit=limit)
        for view in views[:3]:
            store.append(*view)
        live.update(config, exact=False)
        assert live.last_exact  # the first pass
        for index, kind in zip((3, 4), kinds, strict=True):
            store.append(*views[index])
            live.update(config, exact=False)
            assert live.last_exact is kind
        assert not live.update(config, exact=False).any() and not live.last_exact  # nothing new: nothing read
    # at the limit itself a fold, just under it exact: the reads of the fourth view after three
    for view in views[:4]:
        offline.append(*view)
    reference, _ = offline.refine(None, config, False, unit_float16=True)
    expected = oracle(3, 3, 3)
    ratio = expected["fold"] / expected["exact"]
    for limit, exact in ((ratio, False), (ratio * 0.999, True)):
        store = ObservationStore(tmp_path / f"r{limit}", n, writer=True)
        live = LiveMap(store, refresh=2.0, fold_limit=limit)
        for view in views[:3]:
            store.append(*view)
        live.update(config, exact=False)
        store.append(*views[3])
        live.update(config, exact=False)
        assert live.last_reads == expected and live.last_exact is exact
        assert np.array_equal(live.features, reference) is exact
        assert np.array_equal(live.exact_at, live.seen) is exact
    # after a fold the exact pass would read every Gaussian touched since the last exact one
    store.append(*views[4])
    live.update(config, exact=False)
    assert live.last_reads["exact"] == oracle(4, 4, 4)["exact"]


def test_a_segment_written_during_a_pass_waits_for_the_next(tmp_path):
    """A store pass reads the segments up to ``upto`` only: a view that lands while a live map's
    exact pass or refresh runs is not taken in, so the next fold does not take it in twice."""
    n, config = 150, AggregationConfig()
    views = list(_views(4, n))
    store = ObservationStore(tmp_path / "s", n, writer=True)
    short = ObservationStore(tmp_path / "short", n, writer=True)
    for view in views[:3]:
        short.append(*view)
    for view in views:
        store.append(*view)
    expected, seen = short.refine(None, config, False)
    got, observed = store.refine(None, config, False, upto=3)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(observed, seen)
    mask = np.zeros(n, bool)
    mask[::3] = True
    part, _ = store.refine(np.zeros_like(got), config, gaussians=mask, upto=3)
    np.testing.assert_array_equal(part[mask], expected[mask])
    assert not part[~mask].any()
    with pytest.raises(ValueError, match="bool mask"):
        store.refine(got, config, gaussians=np.zeros(n, np.int64), upto=3)


def test_the_refiner_and_bench_live_fold_with_the_live_maps_default_refresh():
    """One default each (``LiveMap.refresh``, ``LiveMap.fold_limit``): the refiner node's
    parameters and ``olsplat bench live`` without --refresh / --fold-limit take the same, so a
    drift measured offline is the graph's."""
    import argparse

    from olsplat_nodes.bench import live as bench_live
    from olsplat_nodes.method.live import LiveMap
    from olsplat_nodes.nodes.refiner import RefinerNode

    assert RefinerNode.Params().refresh == LiveMap.refresh
    assert RefinerNode.Params().fold_limit == LiveMap.fold_limit
    parser = argparse.ArgumentParser()
    bench_live.add_parser(parser.add_subparsers())
    defaults = parser.parse_args(["live", "--scene", "S"])
    assert defaults.refresh is None and defaults.fold_limit is None  # resolved to LiveMap's in run


def test_the_fold_limit_is_fitted_from_the_replays_by_the_written_rule(tmp_path, capsys):
    """``olsplat bench live --fit``: least squares of both kinds' seconds per million reads over
    every pass but the first, the limit c_e / c_f rounded down to 0.05; against made-up replays
    with known costs (fold 0.5 s per million, exact 0.3: the limit 0.6), and a clear error for
    a file that is not a replay's figures."""
    import json

    from olsplat_nodes.bench.live import fit_fold_limit
    from olsplat_nodes.cli import main

    fold_reads = [1e6, 2e6, 4e6, 3e6]
    exact_reads = [1e6, 3e6, 6e6, 9e6]
    run = {
        "views": [5, 10, 15, 20],
        "fold_reads": fold_reads,
        "fold_s": [9.0] + [1.0 + 0.5 * r / 1e6 for r in fold_reads[1:]],  # the first pass: not fitted
        "exact_pass_reads": exact_reads,
        "exact_s": [9.0] + [0.2 + 0.3 * r / 1e6 for r in exact_reads[1:]],
        "exact_reads": exact_reads,
    }
    fit = fit_fold_limit([run])
    assert fit["passes"] == 3 and fit["fold_limit"] == 0.6
    assert fit["fold_s_per_m_reads"] == pytest.approx(0.5) and fit["exact_s_intercept"] == pytest.approx(0.2)
    # under the limit: the pass of 2 M fold reads against 3 M exact folds (2 <= 0.6 x 3 is false:
    # exact), 4 against 6 (exact), 3 against 9 (a fold)
    assert fit["seconds"]["under_the_limit"] == pytest.approx(round(0.2 + 0.9 + 0.2 + 1.8 + 1.0 + 1.5, 1))
    assert fit["exact_faster"] == 2  # 1.1 < 2.0 and 2.0 < 3.0 s; not 2.9 against 2.5
    path = tmp_path / "replay.json"
    path.write_text(json.dumps({"S/outlangsplat": run}))
    assert main(["bench", "live", "--fit", str(path), "--json", str(tmp_path / "fit.json")]) == 0
    assert "fold_limit 0.60" in capsys.readouterr().out
    assert json.loads((tmp_path / "fit.json").read_text())["fold_limit"] == 0.6
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    assert main(["bench", "live", "--fit", str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.json: not the --json of olsplat bench live" in err
