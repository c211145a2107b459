"""The per-view step (``method.add_view``), the one the live accumulator and the offline runs
share, checked end to end against the slow references: the reference rasterizer's Top-K, then
the dense equations of the paper, for the method's own settings (including ones given as
parameters), and what lands in the store."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from olsplat_nodes.aggregate import observe_view, stack_levels
from olsplat_nodes.aggregate._reference import observe_view_dense
from olsplat_nodes.method import MethodParams, add_view, view_observations
from olsplat_nodes.method.view_step import sample_label_maps
from olsplat_nodes.params import parse_params
from olsplat_nodes.raster import rasterize
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


def _sampled_reference(label_maps: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel by pixel: the label under each small pixel's centre, in the large image's pixels."""
    levels, full_height, full_width = label_maps.shape
    out = np.empty((levels, height, width), np.int32)
    for y in range(height):
        for x in range(width):
            column = min(int(np.floor((x + 0.5) * full_width / width)), full_width - 1)
            row = min(int(np.floor((y + 0.5) * full_height / height)), full_height - 1)
            out[:, y, x] = label_maps[:, row, column]
    return out


@pytest.mark.parametrize(("width", "height"), [(48, 36), (24, 18), (17, 11), (1, 1)])
def test_label_maps_are_sampled_at_the_small_renders_pixel_centres(width, height):
    label_maps, _ = _regions(36, 48)
    np.testing.assert_array_equal(
        sample_label_maps(label_maps, width, height), _sampled_reference(label_maps, width, height)
    )


def test_a_smaller_topk_render_is_the_step_on_the_scaled_view_with_strengths_in_the_views_pixels():
    """topk_scale 0.5: the same as rendering the scaled camera (its pixel edges on the view's)
    with the labels at its pixel centres, each strength times the 4 view pixels a rendered pixel
    covers, kept against tau_d in those units; the mixtures the same. At 1, nothing changes."""
    gaussians = random_gaussians(300, 0, seed=3)
    camera = camera_for("PINHOLE_CENTRED", 48, 36)
    label_maps, bank = _regions(camera.height, camera.width, seed=3)
    full = MethodParams(tau_d=0.02).resolve()
    half = MethodParams(tau_d=0.02, topk_scale=0.5).resolve()
    assert repr(full) == repr(half) and MethodParams().resolve().raster.topk_scale == 1.0

    observations, stacked, _ = view_observations(gaussians, camera, label_maps, bank, half)

    small = camera.scaled(0.5)
    assert (small.width, small.height) == (24, 18)
    rendered = rasterize(gaussians, small, half.raster, want_rgb=False)
    slots, expected_bank = stack_levels(_sampled_reference(label_maps, 24, 18), bank)
    unscaled = observe_view(
        rendered.topk_ids, rendered.topk_weights, slots, len(gaussians), replace(half.aggregation, tau_d=0.0)
    )
    keep = unscaled.strength * 4.0 > 0.02
    assert 20 < keep.sum() < len(unscaled)  # the threshold in the view's pixels decides
    np.testing.assert_array_equal(observations.gaussians, unscaled.gaussians[keep])
    np.testing.assert_allclose(observations.strength, unscaled.strength[keep] * 4.0, rtol=1e-6)
    np.testing.assert_allclose(
        observations.features(stacked), unscaled.features(expected_bank)[keep], rtol=1e-6, atol=1e-7
    )
    full_observations, _, _ = view_observations(gaussians, camera, label_maps, bank, full)
    direct = observe_view(
        *_topk(gaussians, camera, full), stack_levels(label_maps, bank)[0], len(gaussians), full.aggregation
    )
    np.testing.assert_array_equal(full_observations.strength, direct.strength)
    with pytest.raises(ValueError, match="topk_scale"):
        MethodParams(topk_scale=1.5).resolve()
    with pytest.raises(ValueError, match="topk_scale applies to pixel-weighted view features, not vala"):
        MethodParams(method="vala", topk_scale=0.5).resolve()


def _topk(gaussians, camera, method):
    rendered = rasterize(gaussians, camera, method.raster, want_rgb=False)
    return rendered.topk_ids, rendered.topk_weights


def test_the_accumulators_topk_scale_reaches_its_method_and_the_stores_manifest():
    """``--set accumulator.topk_scale=0.5``: the node's method has it, the store's manifest keeps
    it (a resumed run with another value is refused by check_store's comparison of methods)."""
    from olsplat_nodes.method import Method, method_params_of
    from olsplat_nodes.nodes.accumulator import AccumulatorNode

    params = parse_params(AccumulatorNode.Params, {"map": "m.ply", "topk_scale": 0.5}, "accumulator")
    method = method_params_of(params).resolve("accumulator")
    assert method.raster.topk_scale == 0.5
    again = Method.from_record(method.record(), "manifest")
    assert again == method and again != MethodParams().resolve()
