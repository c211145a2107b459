"""The per-view step (``method.add_view``), the one the live accumulator and the offline runs
share, checked end to end against the slow references: the reference rasterizer's Top-K, then
the dense equations of the paper, for the method's own settings (including ones given as
parameters), and what lands in the store."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from olsplat_nodes.aggregate._reference import observe_view_dense
from olsplat_nodes.method import MethodParams, add_view
from olsplat_nodes.params import parse_params
from olsplat_nodes.raster._reference import rasterize_reference
from olsplat_nodes.storage import ObservationStore

from ..conftest import camera_for, random_gaussians


def _regions(height: int, width: int, dim: int = 8, seed: int = 0):
    rng = np.random.default_rng(seed)
    ys, xs = np.arange(height)[:, None], np.arange(width)[None, :]
    coarse = (ys // 12) * ((width + 11) // 12) + xs // 12
    fine = (ys // 6) * ((width + 5) // 6) + xs // 6
    label_maps = np.stack([coarse, fine]).astype(np.int32)
    label_maps[1, :3, :5] = -1  # pixels without a feature: M = 0 there
    bank = [rng.normal(size=(int(m.max()) + 1, dim)).astype(np.float32) for m in label_maps]
    return label_maps, [b / np.linalg.norm(b, axis=1, keepdims=True) for b in bank]


@pytest.mark.parametrize(
    "settings",
    [{"method": "outlangsplat"}, {"method": "outlangsplat", "tau_d": 0.3, "topk_max": 20, "q_min": 0.3},
     {"method": "projection"}],
)  # fmt: skip
def test_add_view_stores_what_the_reference_equations_give(tmp_path, settings):
    method = parse_params(MethodParams, settings, "test").resolve()
    gaussians = random_gaussians(300, 0, seed=1)
    camera = camera_for("PINHOLE_SKEWED", 48, 36)
    label_maps, bank = _regions(camera.height, camera.width)
    store = ObservationStore(tmp_path / "store", len(gaussians), writer=True)

    stages = add_view(gaussians, camera, label_maps, bank, method, store)

    reference = rasterize_reference(gaussians, camera, method.raster)
    pixel_features = bank[1][np.maximum(label_maps[1], 0)]  # the default: the finest level only
    valid = label_maps[1] >= 0
    oracle = method.aggregation
    if not oracle.use_quality:  # the dense equations always weigh by q: make q = 1 instead
        oracle = replace(oracle, q_min=1.0, tau_e=1e9)
    dense_f, dense_d = observe_view_dense(
        reference["topk_ids"], reference["topk_weights"], pixel_features, valid, len(gaussians), oracle
    )
    observations, stacked = store.load(0)
    kept = np.flatnonzero(dense_d > 0)
    assert store.names() == [camera.name] and stages["kept"] == len(observations) == len(kept) > 20
    np.testing.assert_array_equal(observations.gaussians, kept)
    np.testing.assert_allclose(observations.strength, dense_d[kept], rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(observations.features(np.asarray(stacked, np.float32)), dense_f[kept], atol=2e-3)
    assert (observations.strength > method.aggregation.tau_d).all()
    assert set(stages) == {"rasterize", "fuse", "observe", "append", "kept", "coverage", "height_m"}


def test_a_method_parameter_changes_what_the_step_keeps(tmp_path):
    gaussians = random_gaussians(300, 0, seed=2)
    camera = camera_for("PINHOLE_CENTRED", 48, 36)
    label_maps, bank = _regions(camera.height, camera.width, seed=2)
    kept = {}
    for tau_d in (0.0, 0.5):
        method = MethodParams(tau_d=tau_d).resolve()
        store = ObservationStore(tmp_path / f"store{tau_d}", len(gaussians), writer=True)
        kept[tau_d] = add_view(gaussians, camera, label_maps, bank, method, store)["kept"]
    assert kept[0.0] > kept[0.5] > 0
