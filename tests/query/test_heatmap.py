"""Heatmaps computed inside the rasterizer against rendering the feature image first."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.query import heatmaps, render_feature_map
from olsplat_nodes.query.heatmap import relevancy_mask, render_heatmaps
from olsplat_nodes.raster import rasterize

from ..conftest import camera_for, random_gaussians


def test_heatmaps_in_the_rasterizer_equal_those_of_the_feature_image():
    rng = np.random.default_rng(0)
    gaussians = random_gaussians(400, 0, seed=1)
    features = rng.normal(size=(400, 24)).astype(np.float32)
    features[::7] = 0.0  # unobserved Gaussians: nothing rendered where only they are
    texts = rng.normal(size=(5, 24)).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    camera = camera_for("PINHOLE_CENTRED", 48, 36)
    feature_map, alpha = render_feature_map(gaussians, features, camera)
    expected = heatmaps(feature_map, texts)
    got, got_alpha = render_heatmaps(gaussians, features, texts, camera)
    assert got.shape == (5, 36, 48)
    np.testing.assert_allclose(got, expected, atol=2e-5)
    # heatmaps may come from the C kernel (raster/heatmap_native.py): its exp is a polynomial
    np.testing.assert_allclose(got_alpha, alpha, atol=2e-6)
    assert (got_alpha[alpha == 0] == 0).all() and (got[:, alpha == 0] == 0).all() and np.abs(got).max() <= 1 + 1e-5
    # the same pass can also write the unit features F / |F| into the caller's buffer
    unit = np.full((36 * 48, 24), np.nan, np.float32)
    again, _ = render_heatmaps(gaussians, features, texts, camera, unit_out=unit)
    np.testing.assert_array_equal(again, got)
    flat = feature_map.reshape(-1, 24)
    norm = np.linalg.norm(flat, axis=1, keepdims=True)
    np.testing.assert_allclose(unit, np.where(norm > 0, flat / np.maximum(norm, 1e-30), 0.0), atol=2e-6)
    with pytest.raises(ValueError, match="unit_features_out"):
        render_heatmaps(gaussians, features, texts, camera, unit_out=np.zeros((36 * 48, 23), np.float32))


def test_feature_queries_need_features_of_their_width():
    gaussians = random_gaussians(50, 0, seed=1)
    camera = camera_for("PINHOLE_CENTRED", 16, 12)
    with pytest.raises(ValueError, match="feature_queries"):
        rasterize(gaussians, camera, feature_queries=np.ones((2, 4), np.float32))
    with pytest.raises(ValueError, match="feature_queries"):
        rasterize(gaussians, camera, features=np.ones((50, 3)), feature_queries=np.ones((2, 4), np.float32))


def test_the_feature_image_cache_answers_as_rendering_and_keeps_to_its_budget():
    from olsplat_nodes.query.heatmap import FeatureImages

    rng = np.random.default_rng(2)
    gaussians = random_gaussians(400, 0, seed=3)
    features = rng.normal(size=(400, 24)).astype(np.float32)
    features[::5] = 0.0
    texts = rng.normal(size=(4, 24)).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    cameras = [camera_for(kind, 48, 36) for kind in ("PINHOLE_CENTRED", "PINHOLE_SKEWED", "SIMPLE_RADIAL")]
    per_view = 48 * 36 * (24 + 1) * 4  # unit features + alpha, float32
    cache = FeatureImages(budget_bytes=2 * per_view)
    for _ in range(2):
        for i, camera in enumerate(cameras):
            expected, alpha = render_heatmaps(gaussians, features, texts[i:], camera)
            got, got_alpha = cache.heatmaps(("v1", i), gaussians, features, texts[i:], camera)
            np.testing.assert_allclose(got, expected, atol=2e-5)
            np.testing.assert_array_equal(got_alpha, alpha)
            assert cache.bytes <= 2 * per_view
    # three views through a two-view budget, twice in the same order: every look was a miss
    assert (cache.hits, cache.misses) == (0, 6)
    cache.heatmaps(("v1", 2), gaussians, features, texts, cameras[2])  # the newest is kept
    assert cache.hits == 1
    # new features under a new key are rendered again, not taken from the old entry
    other = features[::-1].copy()
    got, _ = cache.heatmaps(("v2", 2), gaussians, other, texts, cameras[2])
    np.testing.assert_allclose(got, render_heatmaps(gaussians, other, texts, cameras[2])[0], atol=2e-5)
    assert cache.misses == 7
    # a view over the whole budget is answered, not kept
    small = FeatureImages(budget_bytes=per_view - 1)
    small.heatmaps("x", gaussians, features, texts, cameras[0])
    assert small.entries == {} and small.bytes == 0


def test_the_feature_image_cache_reuses_its_memory():
    """Reserved buffers take the first views, evicted views' buffers the next ones: no new
    memory once the budget is touched (first-touched memory costs as much as rendering)."""
    from olsplat_nodes.query.heatmap import FeatureImages

    rng = np.random.default_rng(4)
    gaussians = random_gaussians(300, 0, seed=5)
    features = rng.normal(size=(300, 16)).astype(np.float32)
    texts = rng.normal(size=(3, 16)).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    cameras = [camera_for(kind, 40, 30) for kind in ("PINHOLE_CENTRED", "PINHOLE_SKEWED", "SIMPLE_RADIAL")]
    per_view = 40 * 30 * (16 + 1) * 4
    cache = FeatureImages(budget_bytes=2 * per_view + 100)
    assert cache.reserve(40 * 30, 16) == 2 and cache.reserve(40 * 30, 16) == 0
    buffers = {id(b) for b in cache.spare}
    for i, camera in enumerate(cameras * 2):
        got, _ = cache.heatmaps(i, gaussians, features, texts, camera)
        np.testing.assert_allclose(got, render_heatmaps(gaussians, features, texts, camera)[0], atol=2e-5)
        assert {id(unit) for unit, _ in cache.entries.values()} <= buffers and len(cache.entries) <= 2
        assert cache.bytes <= cache.budget
    assert cache.spare == [] and cache.misses == 6


def test_codebook_features_render_as_their_rows():
    """feature_rows: a table of centres and one row per Gaussian (-1: no feature) renders as the
    dense [N, D] features it stands for, in the feature image and in the heatmaps."""
    rng = np.random.default_rng(6)
    gaussians = random_gaussians(300, 0, seed=7)
    centres = rng.normal(size=(9, 12)).astype(np.float32)
    rows = rng.integers(-1, 9, 300).astype(np.int32)
    dense = np.where(rows[:, None] >= 0, centres[np.maximum(rows, 0)], 0.0).astype(np.float32)
    texts = rng.normal(size=(3, 12)).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    camera = camera_for("PINHOLE_CENTRED", 40, 30)
    expected = rasterize(gaussians, camera, features=dense, want_topk=False)
    got = rasterize(gaussians, camera, features=centres, feature_rows=rows, want_topk=False)
    np.testing.assert_array_equal(got.features, expected.features)
    maps = rasterize(gaussians, camera, features=centres, feature_rows=rows, want_topk=False, feature_queries=texts)
    dense_maps = rasterize(gaussians, camera, features=dense, want_topk=False, feature_queries=texts)
    np.testing.assert_array_equal(maps.features, dense_maps.features)
    with pytest.raises(ValueError, match="feature_rows"):
        rasterize(gaussians, camera, features=centres, feature_rows=np.full(300, 9, np.int32))


@pytest.mark.parametrize("layout", ["planes", "render"])
def test_the_relevancy_mask_is_numpys_rule_in_either_layout(layout):
    """The one-pass mask equals (query > negatives.max(0)) & (alpha > 0.5), on [Q, H, W] planes
    (the cache's product) and on the strided view of a render's [H, W, Q] output, with ties,
    NaN in the query and in a negative, and alpha on both sides of its bar."""
    rng = np.random.default_rng(3)
    pixels = rng.choice([-0.5, 0.0, 0.25, 0.5], size=(37, 29, 6)).astype(np.float32)  # many ties
    pixels[3, 4, 0] = np.nan
    pixels[5, 6, 2] = np.nan
    maps = np.ascontiguousarray(np.moveaxis(pixels, -1, 0)) if layout == "planes" else np.moveaxis(pixels, -1, 0)
    assert maps.flags.c_contiguous == (layout == "planes")
    alpha = rng.choice([0.0, 0.5, 0.51, 1.0], size=(37, 29)).astype(np.float32)
    for negatives in (maps[1:], maps[1:2], maps[:0]):
        expected = (maps[0] > negatives.max(0)) & (alpha > 0.5) if len(negatives) else alpha > 0.5
        np.testing.assert_array_equal(relevancy_mask(maps[0], negatives, alpha), expected)
    mask = relevancy_mask(maps[0], maps[1:], alpha)
    assert mask.any() and not mask[3, 4]  # a NaN query never beats
