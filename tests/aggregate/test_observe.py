"""Per-view observations: the compact mixtures equal the paper's dense equations."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.aggregate import AggregationConfig, observe_view, pixel_quality, stack_levels
from olsplat_nodes.aggregate._reference import observe_view_dense
from olsplat_nodes.raster import rasterize

from ..conftest import camera_for, random_gaussians


def view_with_regions(seed: int = 0, n: int = 300, dim: int = 8):
    gaussians = random_gaussians(n, 0, seed=seed)
    camera = camera_for("PINHOLE_SKEWED", 48, 36)
    result = rasterize(gaussians, camera)
    rng = np.random.default_rng(seed)
    coarse = (np.arange(36)[:, None] // 12) * 4 + np.arange(48)[None, :] // 12  # 3 x 4 blocks
    fine = (np.arange(36)[:, None] // 6) * 8 + np.arange(48)[None, :] // 6  # 6 x 8 blocks
    label_maps = np.stack([coarse, fine]).astype(np.int32)
    label_maps[1, :3, :5] = -1  # a few pixels without a feature (M = 0 there)
    bank = [rng.normal(size=(12, dim)).astype(np.float32), rng.normal(size=(48, dim)).astype(np.float32)]
    bank = [b / np.linalg.norm(b, axis=1, keepdims=True) for b in bank]
    return n, result, label_maps, bank


@pytest.mark.parametrize("level_weights", [None, (0.7, 0.3)])
def test_compact_observations_equal_the_dense_equations(level_weights):
    n, result, label_maps, bank = view_with_regions()
    config = AggregationConfig(level_weights=level_weights, tau_d=0.02)
    slots, stacked = stack_levels(label_maps, bank)
    obs = observe_view(result.topk_ids, result.topk_weights, slots, n, config)

    a = np.array(level_weights or (0.0, 1.0))  # default: the finest level only
    a = a / a.sum()
    pixel_features = sum(a[i] * bank[i][np.maximum(label_maps[i], 0)] for i in range(2))
    valid = (label_maps >= 0).all(0)
    dense_f, dense_d = observe_view_dense(result.topk_ids, result.topk_weights, pixel_features, valid, n, config)

    kept = np.flatnonzero(dense_d > 0)
    np.testing.assert_array_equal(obs.gaussians, kept)
    np.testing.assert_allclose(obs.strength, dense_d[kept], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(obs.features(stacked), dense_f[kept], rtol=1e-4, atol=1e-5)
    sums = np.add.reduceat(obs.weights, obs.offsets[:-1]) if len(obs) else []
    np.testing.assert_allclose(sums, 1.0, atol=1e-5)
    assert len(obs) > 20 and (obs.strength > config.tau_d).all()


def test_quality_terms():
    config = AggregationConfig(q_min=0.2, tau_e=2.0, kappa=1.0)
    weights = np.array([[0.9, 0.0, 0.0, 0.0], [0.25, 0.25, 0.25, 0.25], [0.05, 0.0, 0.0, 0.0]], np.float32)
    q_sum, q_eff, effective = pixel_quality(weights, config)
    np.testing.assert_allclose(effective, [1.0, 4.0, 1.0], rtol=1e-5)
    np.testing.assert_allclose(q_sum, [0.9, 1.0, 0.2], rtol=1e-6)
    np.testing.assert_allclose(q_eff, [1.0, np.exp(-2.0), 1.0], rtol=1e-5)


def test_mismatched_inputs_are_named():
    n, result, label_maps, bank = view_with_regions()
    with pytest.raises(ValueError, match="2 label maps but 1 feature levels"):
        stack_levels(label_maps, bank[:1])
    with pytest.raises(ValueError, match="level 1: region 47 has no feature"):
        stack_levels(label_maps, [bank[0], bank[1][:10]])
    slots, _ = stack_levels(label_maps, bank)
    with pytest.raises(ValueError, match="do not match the rendered view"):
        observe_view(result.topk_ids, result.topk_weights, slots[:, :10], n)
