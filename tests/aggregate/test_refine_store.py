"""Consistency refinement against the dense equations; the store: on disk, streaming = batch."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from olsplat_nodes.aggregate import AggregationConfig, observe_view, refine_observations, stack_levels
from olsplat_nodes.aggregate._reference import refine_dense
from olsplat_nodes.raster import rasterize
from olsplat_nodes.storage import ObservationStore

from ..conftest import camera_for, random_gaussians


def test_refinement_equals_the_dense_equations():
    rng = np.random.default_rng(0)
    n, views, dim = 40, 6, 5
    features = rng.normal(size=(n, views, dim))
    features[:, :2] += 3.0 * rng.normal(size=(n, 1, dim))  # two views agree, the rest is noise
    strength = rng.uniform(0.1, 1.0, (n, views)) * (rng.random((n, views)) < 0.8)
    strength[0] = 0.0  # a Gaussian never observed
    config = AggregationConfig(iterations=3, beta=(1.0, 3.0))
    expected = refine_dense(features, strength, config)
    owner, view = np.nonzero(strength)
    got, count = refine_observations(owner, strength[owner, view], features[owner, view], n, config)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    assert count[0] == 0 and not got[0].any()
    np.testing.assert_array_equal(count, (strength > 0).sum(1))


def test_consistency_downweights_the_outlier_view():
    """Four views agree on a direction, one disagrees: refinement moves F towards the four."""
    agree, outlier = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    features = np.array([agree, agree, agree, agree, outlier])
    strength = np.full(5, 0.5)
    owner = np.zeros(5, int)
    f0, _ = refine_observations(owner, strength, features, 1, AggregationConfig(iterations=0))
    f3, _ = refine_observations(owner, strength, features, 1, AggregationConfig(iterations=3, beta=(4.0,)))
    assert f3[0, 0] / f3[0, 1] > 2 * f0[0, 0] / f0[0, 1]


@pytest.mark.parametrize("min_retained", [0.3, 0.6, 0.9])
def test_min_retained_views_equals_the_dense_equations(min_retained):
    rng = np.random.default_rng(2)
    n, views, dim = 60, 7, 5
    features = rng.normal(size=(n, views, dim))
    features[: n // 2, :5] += 3.0 * rng.normal(size=(n // 2, 1, dim))  # half: most views agree
    strength = rng.uniform(0.1, 1.0, (n, views)) * (rng.random((n, views)) < 0.8)
    strength[0] = 0.0
    config = AggregationConfig(iterations=3, beta=(2.0, 4.0, 8.0), min_retained_views=min_retained)
    expected = refine_dense(features, strength, config)
    owner, view = np.nonzero(strength)
    got, _ = refine_observations(owner, strength[owner, view], features[owner, view], n, config)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    plain = refine_dense(
        features, strength, AggregationConfig(iterations=3, beta=(2.0, 4.0, 8.0), min_retained_views=None)
    )
    initial = refine_dense(features, strength, AggregationConfig(iterations=0))
    kept_initial = np.all(np.isclose(got, initial), axis=1) & ~np.all(np.isclose(plain, initial), axis=1)
    assert 0 < kept_initial.sum() < n  # some Gaussians fall back to F0, the others are refined


def test_min_retained_views_keeps_the_mean_of_two_disagreeing_groups():
    """Two equal groups of views disagree: the consistency update would pick one; with
    min_retained_views the Gaussian keeps the d-weighted mean. One outlier among four: refined."""
    a, b = np.array([1.0, 0.0]), np.array([0.0, 1.0])
    split = np.array([a, a, b, b, a + 0.1 * b])
    outlier = np.array([a, a, a, a, b])
    features = np.concatenate([split, outlier])
    owner = np.repeat([0, 1], 5)
    strength = np.full(10, 0.5)
    config = AggregationConfig(iterations=3, beta=(2.0, 4.0, 8.0), min_retained_views=None)
    f0, _ = refine_observations(owner, strength, features, 2, AggregationConfig(iterations=0))
    f3, _ = refine_observations(owner, strength, features, 2, config)
    gated, _ = refine_observations(
        owner, strength, features, 2, replace(config, min_retained_views=0.7)
    )  # kept: 3 of 5 vs 4 of 5
    assert not np.allclose(f3[0], f0[0])
    np.testing.assert_allclose(gated[0], f0[0], rtol=1e-6)
    np.testing.assert_allclose(gated[1], f3[1], rtol=1e-6)


def _views(count: int, n: int):
    gaussians = random_gaussians(n, 0, seed=4)
    rng = np.random.default_rng(1)
    for v in range(count):
        camera = camera_for("PINHOLE_CENTRED", 40, 30)
        camera.world_from_camera[:3, 3] += rng.normal(0, 0.4, 3)
        result = rasterize(gaussians, camera)
        labels = np.stack([(np.arange(30)[:, None] // 10) * 4 + np.arange(40)[None, :] // 10]).astype(np.int32)
        bank = [rng.normal(size=(12, 6)).astype(np.float32)]
        slots, stacked = stack_levels(labels, bank)
        yield f"v{v}", observe_view(result.topk_ids, result.topk_weights, slots, n), stacked


@pytest.mark.parametrize("min_retained", [None, 0.5])
def test_streaming_views_equal_the_batch(tmp_path, min_retained):
    n = 150
    config = AggregationConfig(min_retained_views=min_retained)
    streaming = ObservationStore(tmp_path / "stream", n, writer=True)
    compact = ObservationStore(tmp_path / "compact", n, writer=True)  # as the refiner node keeps it
    F = F16 = None
    for name, obs, bank in _views(5, n):
        streaming.append(name, obs, bank)
        compact.append(name, obs, bank)
        F, _ = streaming.refine(F, config)  # only the Gaussians this view touched
        F16, _ = compact.refine(F16, config, unit_float16=True)
    batch = ObservationStore(tmp_path / "batch", n, writer=True)
    for name, obs, bank in _views(5, n):
        batch.append(name, obs, bank)
    F_batch, observed = batch.refine(None, config, max_observations=37)  # small ranges: the chunking is exercised
    F_narrow, _ = batch.refine(None, config, max_gaussians=7)  # ranges of 7 Gaussians: the same
    np.testing.assert_array_equal(F_narrow, F_batch)
    assert observed.sum() > 50
    np.testing.assert_allclose(F, F_batch, rtol=1e-5, atol=1e-6)
    # the float16 form: the unit rows of the same features, to float16's precision
    assert F16.dtype == np.float16
    norm = np.linalg.norm(F_batch, axis=1, keepdims=True)
    unit = np.where(norm > 0, F_batch / np.maximum(norm, 1e-12), 0.0)
    np.testing.assert_allclose(F16.astype(np.float32), unit, atol=1e-3)
    assert ((F16 != 0).any(1) == observed).all()


def _memory_mapped(array: np.ndarray) -> bool:
    """Whether ``array`` reads a file's pages (its buffer chain ends in an mmap), not a copy."""
    import mmap

    base = array
    while base is not None and not isinstance(base, mmap.mmap):
        base = base.base if isinstance(base, np.ndarray) else getattr(base, "obj", None)
    return base is not None


def test_store_survives_reopening_and_half_written_views(tmp_path):
    n = 150
    store = ObservationStore(tmp_path, n, writer=True)
    for name, obs, bank in _views(2, n):
        store.append(name, obs, bank)
    (tmp_path / "views" / "000002.tmp").mkdir()  # as if a crash interrupted a third append
    reader = ObservationStore(tmp_path, n)  # e.g. the refiner: the writer may still be filling it
    assert len(reader) == 2 and (tmp_path / "views" / "000002.tmp").exists()
    with pytest.raises(RuntimeError, match="opened for reading"):
        reader.append(*next(_views(1, n)))
    reopened = ObservationStore(tmp_path, n, writer=True)
    assert len(reopened) == 2 and not (tmp_path / "views" / "000002.tmp").exists()
    obs, bank = reopened.load(1)
    assert _memory_mapped(obs.gaussians) and not obs.gaussians.flags.writeable and bank.dtype == np.float16
    F, observed = reopened.refine(None, AggregationConfig())
    assert F.shape == (n, 6) and observed.any()


def test_mixed_features_equal_their_dense_form(tmp_path):
    """The store refines from the views' banks and mixture entries; the same observations with
    their features mixed out beforehand give the same map."""
    from olsplat_nodes.aggregate.refine import refine_mixed

    n = 150
    store = ObservationStore(tmp_path, n, writer=True)
    for name, obs, bank in _views(4, n):
        store.append(name, obs, bank)
    mixed = store.gather(np.ones(n, bool))
    dense = np.stack(
        [
            (mixed.weights[a:b, None] * mixed.bank[mixed.slots[a:b]]).sum(0)
            for a, b in zip(mixed.entry_offsets[:-1], mixed.entry_offsets[1:], strict=True)
        ]
    )
    config = AggregationConfig()
    got, count = refine_mixed(mixed, n, config)
    expected, expected_count = refine_observations(mixed.owner, mixed.strength, dense, n, config)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(count, expected_count)
    assert len(mixed.slots) > len(mixed)  # some observations do mix several regions


def test_the_store_refuses_a_view_of_another_feature_width(tmp_path):
    n = 150
    store = ObservationStore(tmp_path, n, writer=True)
    views = list(_views(2, n))
    store.append(*views[0])
    name, obs, bank = views[1]
    with pytest.raises(ValueError, match="width 3, the store holds width 6"):
        store.append(name, obs, bank[:, :3])
    assert len(store) == 1
    store.refine(None, AggregationConfig())  # still refinable


def test_a_damaged_segment_is_quarantined_not_fatal(tmp_path):
    """A segment damaged on disk (here its bank overwritten with garbage) is skipped with a
    reason, for good (a marker in its folder), and the map is that of the other views."""
    n = 150
    views = list(_views(3, n))
    store = ObservationStore(tmp_path / "store", n, writer=True)
    for view in views:
        store.append(*view)
    (tmp_path / "store" / "views" / "000001" / "bank.npy").write_bytes(b"not an array")
    F, observed = store.refine(None, AggregationConfig())
    assert list(store.quarantined) == ["000001"] and "unreadable" in store.quarantined["000001"]
    assert (tmp_path / "store" / "views" / "000001" / "QUARANTINED.txt").exists()
    clean = ObservationStore(tmp_path / "clean", n, writer=True)
    for view in (views[0], views[2]):
        clean.append(*view)
    F_clean, observed_clean = clean.refine(None, AggregationConfig())
    np.testing.assert_array_equal(observed, observed_clean)
    np.testing.assert_array_equal(F, F_clean)
    reopened = ObservationStore(tmp_path / "store", n, writer=True)  # a restarted refiner skips it at once
    reopened.refine(None, AggregationConfig())
    assert list(reopened.quarantined) == ["000001"] and len(reopened) == 3
    assert reopened.names() == ["v0", "", "v2"]  # so the accumulator stores the view anew if it comes again
    assert reopened.append(*views[1]) == 3


@pytest.mark.parametrize(
    "array",
    [np.arange(7, dtype=np.int32), np.zeros((0, 6), np.float16), np.ones((5, 3), np.float32), np.zeros(0, np.int64)],
)
def test_a_segment_array_maps_as_np_load_reads_it(tmp_path, array):
    from olsplat_nodes.storage.store import _map_npy, _npy_header

    path = tmp_path / "a.npy"
    np.save(path, array)
    mapped = _map_npy(path, _npy_header(path))
    expected = np.load(path, mmap_mode="r")
    assert mapped.dtype == expected.dtype and mapped.shape == expected.shape
    np.testing.assert_array_equal(mapped, expected)
    if array.size:
        assert _memory_mapped(mapped) and not mapped.flags.writeable
        path.write_bytes(path.read_bytes()[:-2])  # truncated: its header promises more
        with pytest.raises(ValueError, match="bytes, its header needs"):
            _map_npy(path, _npy_header(path))


def test_observation_counts_follow_appends_and_skip_a_quarantined_view(tmp_path):
    """The store's running count equals a count made afresh over every usable segment."""
    n = 150
    views = list(_views(5, n))
    store = ObservationStore(tmp_path, n, writer=True)
    for name, obs, bank in views[:2]:
        store.append(name, obs, bank)
    reader = ObservationStore(tmp_path, n)
    first = reader.observation_counts().copy()
    for name, obs, bank in views[2:]:
        store.append(name, obs, bank)
    (tmp_path / "views" / "000003" / "strength.npy").write_bytes(b"damaged")  # quarantined when first read
    counts = reader.observation_counts()
    fresh = np.zeros(n, np.int64)
    for index, (_, obs, _) in enumerate(views):
        if index != 3:
            fresh[obs.gaussians] += 1
    assert not counts.flags.writeable
    np.testing.assert_array_equal(counts, fresh)
    np.testing.assert_array_equal(first, sum(np.bincount(obs.gaussians, minlength=n) for _, obs, _ in views[:2]))
    assert list(reader.quarantined) == ["000003"]
