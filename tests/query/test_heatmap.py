"""Heatmaps computed inside the rasterizer against rendering the feature image first."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.query import heatmaps, render_feature_map
from olsplat_nodes.query.heatmap import render_heatmaps
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
    np.testing.assert_array_equal(got_alpha, alpha)
    assert (got[:, alpha == 0] == 0).all() and np.abs(got).max() <= 1 + 1e-5


def test_feature_queries_need_features_of_their_width():
    gaussians = random_gaussians(50, 0, seed=1)
    camera = camera_for("PINHOLE_CENTRED", 16, 12)
    with pytest.raises(ValueError, match="feature_queries"):
        rasterize(gaussians, camera, feature_queries=np.ones((2, 4), np.float32))
    with pytest.raises(ValueError, match="feature_queries"):
        rasterize(gaussians, camera, features=np.ones((50, 3)), feature_queries=np.ones((2, 4), np.float32))
