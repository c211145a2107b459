"""The C heatmap kernel (native/heatmap_composite.c) against the numba kernel and the numpy
reference: every output of a heatmap render, on small scenes of every camera model; float16
tables as their float32 values."""

from __future__ import annotations

import platform

import numpy as np
import pytest

from olsplat_nodes.native import cpu_has
from olsplat_nodes.query.heatmap import heatmaps
from olsplat_nodes.raster import heatmap_native as native
from olsplat_nodes.raster import rasterize
from olsplat_nodes.raster._reference import rasterize_reference

from ..conftest import camera_for, random_gaussians


def unit_rows(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def render(gaussians, camera, features, texts, rows=None, background=(0.0, 0.0, 0.0)):
    unit = np.full((camera.width * camera.height, features.shape[1]), np.nan, np.float32)
    result = rasterize(
        gaussians,
        camera,
        features=features,
        want_topk=False,
        feature_queries=texts,
        unit_features_out=unit,
        feature_rows=rows,
        background=background,
    )
    return result, unit


def test_the_kernel_is_built_and_used_on_this_machine():
    """``make setup`` builds it (setup.py); on an x86-64 Linux machine with AVX2 it must load."""
    if platform.machine() != "x86_64" or not cpu_has("avx2", "fma", "f16c"):
        pytest.skip("the C kernels' AVX2 build needs an x86-64 CPU with AVX2, FMA and F16C")
    assert native.kernel() is not None, "olsplat_nodes/native/_kernels was not built: run make setup"


# (width, height, Gaussians, camera model, feature channels): channels below, at and above the
# kernel's 64-channel register blocks
CASES = [
    (48, 36, 300, "PINHOLE_CENTRED", 24),
    (47, 33, 250, "PINHOLE_SKEWED", 64),
    (64, 48, 400, "SIMPLE_RADIAL", 130),
    (50, 70, 350, "OPENCV_WIDE", 128),
]


@pytest.mark.parametrize("width,height,n,kind,dim", CASES)
def test_c_heatmaps_equal_the_numba_kernels_and_the_reference(width, height, n, kind, dim, monkeypatch):
    if native.kernel() is None:
        pytest.skip("the C kernel is not built here")
    rng = np.random.default_rng(n + dim)
    gaussians = random_gaussians(n, 2, seed=n)
    camera = camera_for(kind, width, height)
    features = rng.normal(size=(n, dim)).astype(np.float32)
    features[::9] = 0.0  # unobserved Gaussians render nothing
    texts = unit_rows(rng.normal(size=(4, dim)))
    background = (0.2, 0.5, 0.9)

    fast, fast_unit = render(gaussians, camera, features, texts, background=background)
    monkeypatch.setattr(native, "kernel", lambda: None)
    slow, slow_unit = render(gaussians, camera, features, texts, background=background)
    ref = rasterize_reference(gaussians, camera, features=features, background=background)

    assert fast.alpha.max() > 0.5, "the scene must cover pixels"
    np.testing.assert_allclose(fast.alpha, slow.alpha, atol=2e-6)
    np.testing.assert_allclose(fast.rgb, slow.rgb, atol=2e-6)
    np.testing.assert_allclose(fast.depth, slow.depth, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(fast.features, slow.features, atol=2e-5)
    np.testing.assert_allclose(fast_unit, slow_unit, atol=2e-5)
    assert abs(fast.n_evaluations - slow.n_evaluations) <= 1e-4 * slow.n_evaluations
    assert fast.n_tile_pairs == ref["tile_pairs"]
    # and the rule itself: the reference's feature image, its cosines
    np.testing.assert_allclose(fast.rgb, ref["rgb"], atol=1e-4)
    np.testing.assert_allclose(fast.alpha, ref["alpha"], atol=1e-4)
    np.testing.assert_allclose(np.moveaxis(fast.features, -1, 0), heatmaps(ref["features"], texts), atol=1e-3)


def test_c_heatmaps_read_codebook_rows_as_the_numba_kernel(monkeypatch):
    if native.kernel() is None:
        pytest.skip("the C kernel is not built here")
    rng = np.random.default_rng(5)
    gaussians = random_gaussians(300, 1, seed=3)
    camera = camera_for("PINHOLE_CENTRED", 40, 30)
    centres = unit_rows(rng.normal(size=(16, 70)))
    rows = rng.integers(-1, 16, 300).astype(np.int32)  # -1: never observed, renders nothing
    texts = unit_rows(rng.normal(size=(3, 70)))
    fast, fast_unit = render(gaussians, camera, centres, texts, rows=rows)
    dense, dense_unit = render(gaussians, camera, np.where(rows[:, None] >= 0, centres[rows], 0.0), texts)
    monkeypatch.setattr(native, "kernel", lambda: None)
    slow, slow_unit = render(gaussians, camera, centres, texts, rows=rows)
    np.testing.assert_allclose(fast.features, slow.features, atol=2e-5)
    np.testing.assert_allclose(fast_unit, slow_unit, atol=2e-5)
    np.testing.assert_array_equal(fast.features, dense.features)  # same kernel, rows or dense
    np.testing.assert_array_equal(fast_unit, dense_unit)


@pytest.mark.parametrize("dim", [24, 64, 130])
def test_float16_tables_render_as_their_float32_values(dim):
    """A language map's float16 rows are read as they are (F16C), dense or through codebook
    rows: the same outputs as the same values widened to float32, bit for bit."""
    if native.kernel() is None:
        pytest.skip("the C kernel is not built here")
    rng = np.random.default_rng(dim)
    gaussians = random_gaussians(350, 2, seed=dim)
    camera = camera_for("PINHOLE_SKEWED", 45, 37)
    half = unit_rows(rng.normal(size=(350, dim))).astype(np.float16)
    half[::7] = 0.0
    texts = unit_rows(rng.normal(size=(5, dim)))
    got, got_unit = render(gaussians, camera, half, texts)
    wide, wide_unit = render(gaussians, camera, half.astype(np.float32), texts)
    assert got.alpha.max() > 0.5 and np.abs(got.features).max() > 0.1, "the scene must render features"
    np.testing.assert_array_equal(got.features, wide.features)
    np.testing.assert_array_equal(got_unit, wide_unit)
    np.testing.assert_array_equal(got.alpha, wide.alpha)
    rows = rng.integers(-1, 40, 350).astype(np.int32)
    got, got_unit = render(gaussians, camera, half[:40], texts, rows=rows)
    wide, wide_unit = render(gaussians, camera, half[:40].astype(np.float32), texts, rows=rows)
    np.testing.assert_array_equal(got.features, wide.features)
    np.testing.assert_array_equal(got_unit, wide_unit)


def test_float16_features_elsewhere_render_as_float32():
    """Paths the C kernel does not take (Top-K, a feature image) widen float16 to float32."""
    rng = np.random.default_rng(1)
    gaussians = random_gaussians(200, 1, seed=1)
    camera = camera_for("PINHOLE_CENTRED", 32, 24)
    half = rng.normal(size=(200, 16)).astype(np.float16)
    got = rasterize(gaussians, camera, features=half)
    wide = rasterize(gaussians, camera, features=half.astype(np.float32))
    np.testing.assert_array_equal(got.features, wide.features)
    np.testing.assert_array_equal(got.topk_ids, wide.topk_ids)
