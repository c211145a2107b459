"""Frustum culling by cells (raster/cull.py): a render with the cull is the render without it,
for cameras inside, above, beside and away from a town of Gaussians (some with huge scales, some
with non-finite fields), and every Gaussian the projection keeps is a candidate."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from olsplat_nodes.raster import RasterConfig, cull, project, rasterize
from olsplat_nodes.scene import Camera, intrinsics, look_at

from ..conftest import random_gaussians


@pytest.fixture(scope="module")
def town():
    gaussians = random_gaussians(6000, 1, seed=11, spread=40.0)
    gaussians.log_scales[:] = np.log(np.random.default_rng(3).uniform(0.05, 0.6, (len(gaussians), 3)))
    gaussians.log_scales[:20] = np.log(30.0)  # a few huge ones: their cells stay visible from afar
    gaussians.means[20:23] = np.nan  # the kernel culls non-finite centres and scales
    gaussians.log_scales[23:25] = np.inf
    return gaussians


def cameras() -> list[Camera]:
    K = intrinsics(300.0, 300.0, 160.0, 120.0)
    poses = [
        look_at([0.0, 0.0, 80.0], [0.0, 0.0, 0.0], (0.0, 1.0, 0.0)),  # nadir from above
        look_at([-20.0, -60.0, 30.0], [10.0, 10.0, 0.0]),  # oblique, most of the town in view
        look_at([35.0, 35.0, 5.0], [60.0, 60.0, 0.0]),  # at the corner, looking out: little in view
        look_at([0.0, 0.0, 2.0], [5.0, 3.0, 0.0]),  # inside the town: cells straddle the near plane
        look_at([0.0, 0.0, 80.0], [0.0, 0.0, 200.0], (0.0, 1.0, 0.0)),  # looking up: nothing
    ]
    wide = intrinsics(90.0, 90.0, 160.0, 120.0)  # a wide field of view: the Jacobian clamp matters
    return [Camera(f"c{i}", 320, 240, K, pose) for i, pose in enumerate(poses)] + [
        Camera("wide", 320, 240, wide, look_at([5.0, -30.0, 15.0], [0.0, 0.0, 0.0]))
    ]


@pytest.fixture
def always_cull(monkeypatch):
    monkeypatch.setattr(cull, "CULL_MIN", 0)


def test_every_kept_gaussian_is_a_candidate_and_most_others_are_not(town, always_cull):
    index = cull.cells_of(town)
    assert index is not None and len(index) > 50
    assert index is cull.cells_of(town)  # made once per map
    config = RasterConfig()
    culled_some = False
    for camera in cameras():
        kept = project(town, camera, config, cull=False).radii > 0
        candidates = index.candidates(camera, config)
        assert not np.any(kept & ~candidates), camera.name
        culled_some |= candidates.sum() < 0.5 * len(town)
    assert culled_some  # the test means something: some views cull most of the map


def _renders(town, camera, features, rows, queries, active=None) -> list:
    """A heatmap render (dense features and table rows) and a Top-K render of ``camera``."""
    return [
        rasterize(town, camera, features=features, want_topk=False, feature_queries=queries, active=active),
        rasterize(town, camera, features=features[:5], feature_rows=rows, want_topk=False, feature_queries=queries),
        rasterize(town, camera, features=features, want_topk=True, active=active),
        rasterize(town, camera, want_topk=True, active=active),
    ]


def _same(a, b) -> None:
    for name in ("rgb", "alpha", "depth", "features", "topk_ids", "topk_weights", "means2d", "radii"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.n_visible == b.n_visible and a.n_evaluations == b.n_evaluations


def test_a_render_with_the_cull_is_the_render_without_it(town, always_cull, monkeypatch):
    """The culled projection has rows for the candidates only; aligned with the map they are
    the whole projection's, and every render from them (features by id or by table row,
    heatmaps, Top-K ids and weights, centres and radii) is the same, with a level of detail's
    subset of the map too."""
    rng = np.random.default_rng(4)
    features = rng.normal(size=(len(town), 8)).astype(np.float32)
    rows = rng.integers(-1, 5, len(town)).astype(np.int32)
    queries = np.eye(8, dtype=np.float32)[:3]
    active = rng.random(len(town)) < 0.5  # a level of detail's subset
    culled_renders = []
    for camera in cameras():
        culled = project(town, camera, RasterConfig())
        whole = project(town, camera, RasterConfig(), cull=False)
        assert culled.ids is not None and len(culled.ids) <= len(town) and whole.ids is None
        aligned = culled.aligned(len(town))
        np.testing.assert_array_equal(aligned.radii, whole.radii)
        np.testing.assert_array_equal(aligned.records, whole.records)
        np.testing.assert_array_equal(aligned.tile_rects, whole.tile_rects)
        both = project(town, camera, RasterConfig(), active=active).aligned(len(town))
        np.testing.assert_array_equal(
            both.radii, project(town, camera, RasterConfig(), active=active, cull=False).radii
        )
        assert not np.any(both.radii[~active])
        culled_renders.append(_renders(town, camera, features, rows, queries, active if camera.name == "c1" else None))
    monkeypatch.setattr(cull, "CULL_MIN", 10**9)  # the same renders, projected whole
    for camera, renders in zip(cameras(), culled_renders, strict=True):
        wholes = _renders(town, camera, features, rows, queries, active if camera.name == "c1" else None)
        assert wholes[0].projected.ids is None
        for a, b in zip(renders, wholes, strict=True):
            _same(a, b)


def test_far_floaters_do_not_stretch_the_cubes(town, always_cull):
    """A trainer's floaters kilometres away go to the border cubes: the cubes keep the size of
    the town's bulk, a view out of the town still culls most of the map, and the renders are unchanged."""
    floating = dataclasses.replace(town, means=town.means.copy(), extras={})
    floating.means[30:34] = [[5e4, 0.0, 10.0], [-3e3, 2e5, 0.0], [0.0, 0.0, -7e4], [10.0, 10.0, 9e5]]
    index = cull.cells_of(floating)
    assert index is not None and index.cell_m == pytest.approx(cull.cells_of(town).cell_m, rel=0.1)
    config = RasterConfig()
    for camera in cameras():
        whole = project(floating, camera, config, cull=False)
        np.testing.assert_array_equal(project(floating, camera, config).aligned(len(floating)).records, whole.records)
        assert not np.any((whole.radii > 0) & ~index.candidates(camera, config))
    assert index.candidates(cameras()[2], config).sum() < 0.5 * len(floating)  # looking out of the town


def test_a_small_map_is_projected_whole(town):
    assert len(town) < cull.CULL_MIN
    assert cull.cells_of(town) is None
