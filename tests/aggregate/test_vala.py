"""The ``vala`` baseline: centre-pixel observations, the visibility gate and the streaming
median, each against a plain loop or the numpy reference; ``projection``'s contribution list."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.aggregate import AggregationConfig, stack_levels
from olsplat_nodes.aggregate._reference import streaming_median_reference
from olsplat_nodes.aggregate.refine import MixedObservations, refine_mixed
from olsplat_nodes.aggregate.vala import observe_view_centres, visibility_gate
from olsplat_nodes.method import named_method
from olsplat_nodes.method.table import ALL_CONTRIBUTORS
from olsplat_nodes.raster import rasterize

from ..conftest import camera_for, random_gaussians

MEDIAN = AggregationConfig(combine="streaming_median")


def _median(owner, view, strength, features, n):
    order = np.argsort(view, kind="stable")
    observations = MixedObservations.dense(owner[order], strength[order], features[order])
    return refine_mixed(observations, n, MEDIAN)


def test_streaming_median_equals_the_numpy_reference():
    rng = np.random.default_rng(5)
    n, views, dim = 50, 8, 6
    owner, view = np.nonzero(rng.random((n, views)) < 0.7)  # at most one observation per Gaussian and view
    shuffle = rng.permutation(len(owner))  # arrival order comes from `view`, not from the list order
    owner, view = owner[shuffle], view[shuffle]
    strength = rng.uniform(0.1, 1.0, len(owner))
    features = rng.normal(size=(len(owner), dim))
    features[::7] = 0.0  # a zero feature is skipped
    expected, expected_count = streaming_median_reference(owner, view, strength, features, n)
    got, count = _median(owner, view, strength, features, n)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(count, expected_count)


def test_streaming_median_steps_along_the_sphere():
    """Algorithm 1 by hand: z = f1; then z + w2 / (w1 + w2) (f2 - (f2 . z) z), normalised. A far
    outlier moves z less than it moves the weighted mean."""
    f = np.array([[1.0, 0.0], [0.0, 2.0]])  # the second is not unit: it is normalised first
    got, count = _median(np.zeros(2, int), np.arange(2), np.array([1.0, 3.0]), f, 1)
    step = np.array([1.0, 0.0]) + 0.75 * np.array([0.0, 1.0])
    np.testing.assert_allclose(got[0], step / np.linalg.norm(step), rtol=1e-6)
    assert count[0] == 2
    agree = np.tile([1.0, 0.0, 0.0], (4, 1))
    outlier = np.array([[-0.2, 1.0, 0.0]])
    f = np.concatenate([agree, outlier])
    z, _ = _median(np.zeros(5, int), np.arange(5), np.ones(5), f, 1)
    mean = (f / np.linalg.norm(f, axis=1, keepdims=True)).mean(0)
    assert z[0] @ [1.0, 0.0, 0.0] > mean @ [1.0, 0.0, 0.0] / np.linalg.norm(mean)


def _gate_by_definition(w, tau_mass, tau_abs, cut):
    """VALA's gate written out pair by pair (module docstring of aggregate/vala.py)."""
    order = sorted(range(len(w)), key=lambda i: (-w[i], i))
    total, running, top_mass = float(np.sum(w, dtype=np.float64)), 0.0, set()
    for i in order:
        top_mass.add(i)
        running += float(w[i])
        if running >= tau_mass * total:
            break
    stage_a = {i for i in top_mass if w[i] >= tau_abs} or {order[0]}
    cut = min(cut, float(np.quantile(w, 0.85)))
    stage_b = {i for i in range(len(w)) if w[i] > cut}
    half = set(order[: int(0.5 * len(w))])
    keep = np.zeros(len(w), bool)
    keep[sorted(stage_a & stage_b & half)] = True
    return keep


def test_visibility_gate_follows_its_definition():
    rng = np.random.default_rng(3)
    for _ in range(30):
        w = rng.uniform(0.0, 0.6, rng.integers(1, 60)).astype(np.float32) ** rng.uniform(0.5, 3.0)
        for tau_mass, tau_abs, cut in [(0.75, 0.13, 0.15), (0.5, 0.0, 0.15), (1.0, 0.3, 0.0), (0.9, 0.01, 0.05)]:
            expected = _gate_by_definition(w, tau_mass, tau_abs, cut)
            np.testing.assert_array_equal(visibility_gate(w, tau_mass, tau_abs, cut), expected)


def test_centre_observations_take_each_gaussians_centre_pixel():
    gaussians = random_gaussians(300, 0, seed=4)
    camera = camera_for("PINHOLE_CENTRED", 48, 36)
    method = named_method("vala")
    result = rasterize(gaussians, camera, method.raster)
    fine = ((np.arange(36)[:, None] // 6) * 8 + np.arange(48)[None, :] // 6).astype(np.int32)
    fine[:6, :6] = -1  # a corner without a feature
    coarse = (fine >= 0).astype(np.int32) - (fine < 0)
    slots, _ = stack_levels(np.stack([coarse, fine]), [np.eye(2, 5, dtype=np.float32), np.eye(48, 5, dtype=np.float32)])
    config = method.aggregation
    got = observe_view_centres(result.topk_ids, result.topk_weights, result.means2d, result.radii, slots, 300, config)
    # by hand: the weight of each Gaussian on the pixel holding its centre, then the gate
    reached, weight, pixel = [], [], []
    for i in range(300):
        u, v = result.means2d[i]
        if result.radii[i] == 0 or not (0 <= u < 48 and 0 <= v < 36):
            continue
        here = np.flatnonzero(result.topk_ids[int(v), int(u)] == i)
        if len(here):
            reached.append(i)
            weight.append(result.topk_weights[int(v), int(u), here[0]])
            pixel.append((int(v), int(u)))
    keep = visibility_gate(np.array(weight, np.float32), config.gate_mass, config.gate_floor, config.gate_cut)
    expected = [i for i, k, (y, x) in zip(reached, keep, pixel, strict=True) if k and fine[y, x] >= 0]
    assert 0 < len(expected) < len(reached)
    np.testing.assert_array_equal(got.gaussians, expected)
    by_id = dict(zip(reached, zip(weight, pixel, strict=True), strict=True))
    np.testing.assert_allclose(got.strength, [by_id[i][0] for i in expected])
    np.testing.assert_array_equal(got.slots, [2 + fine[by_id[i][1]] for i in expected])  # the finest level only
    np.testing.assert_array_equal(got.offsets, np.arange(len(expected) + 1))
    assert (got.weights == 1.0).all()


def test_projection_keeps_every_contributor_of_every_pixel():
    """The contribution list of ``projection`` (and ``vala``) never fills up, so no contributor
    is left out; the default Top-K does leave some out on the same view."""
    gaussians = random_gaussians(3000, 0, seed=7)
    camera = camera_for("PINHOLE_CENTRED", 64, 48)
    every = rasterize(gaussians, camera, named_method("projection").raster)
    counts = (every.topk_ids >= 0).sum(-1)
    assert counts.max() < ALL_CONTRIBUTORS and counts.max() > 32
    np.testing.assert_allclose(every.topk_weights.sum(-1), every.alpha, rtol=1e-4, atol=1e-6)
