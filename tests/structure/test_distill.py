"""h_theta: online distillation learns a mapping, saves/loads exactly, fuses as the paper says."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.structure.distill import DistillConfig, OnlineDistiller, fuse_regions


def _views(rng, mapping, n_views=12, regions=60):
    for _ in range(n_views):
        f3d = rng.normal(size=(regions, 10)).astype(np.float32)
        f2d = np.tanh(f3d @ mapping)
        yield f3d, (f2d / np.linalg.norm(f2d, axis=1, keepdims=True)).astype(np.float32)


def test_online_updates_learn_the_teacher_and_save_load_exactly(tmp_path):
    rng = np.random.default_rng(0)
    mapping = rng.normal(size=(10, 6))
    distiller = OnlineDistiller(10, 6, DistillConfig(hidden=64, steps_per_view=40, reservoir=300, warmup_regions=100))
    losses = [distiller.update(a, b) for a, b in _views(rng, mapping)]
    assert losses[-1] < 0.5 * losses[0]
    assert distiller.ready and distiller.seen == 12 * 60 and len(distiller.memory_3d) == 300
    test3d, test2d = next(_views(np.random.default_rng(99), mapping, 1, 200))
    assert (distiller.project(test3d) * test2d).sum(1).mean() > 0.8  # generalises to unseen regions
    distiller.save(tmp_path / "h.npz")
    loaded = OnlineDistiller.load(tmp_path / "h.npz")
    assert np.array_equal(loaded.project(test3d), distiller.project(test3d)) and loaded.seen == distiller.seen
    params = dict(np.load(tmp_path / "h.npz"))
    params["param_0"] = params["param_0"][:, :5]
    np.savez(tmp_path / "bad.npz", **params)
    with pytest.raises(SceneFormatError, match="parameter 0 has shape"):
        OnlineDistiller.load(tmp_path / "bad.npz")


def test_fusion_keeps_2d_where_no_point_is_visible():
    f2d = np.array([[1.0, 0.0], [0.0, 2.0]], np.float32)
    h = np.array([[0.0, 1.0], [1.0, 0.0]], np.float32)
    fused = fuse_regions(f2d, h, np.array([3, 0]), lambda_f=0.7)
    np.testing.assert_allclose(fused, [[0.7, 0.3], [0.0, 2.0]])


def test_fusion_by_points_scales_the_3d_share_with_the_visible_points():
    f2d = np.array([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]], np.float32)
    h = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]], np.float32)
    fused = fuse_regions(f2d, h, np.array([5, 10, 40]), lambda_f=0.6, full_points=20)
    np.testing.assert_allclose(fused, [[0.9, 0.1], [0.8, 0.2], [0.6, 0.4]], atol=1e-6)  # 3D share 0.4 n / 20
    np.testing.assert_allclose(fuse_regions(f2d, h, np.array([5, 10, 40]), 0.6), [[0.6, 0.4]] * 3, atol=1e-6)
