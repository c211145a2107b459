"""The C Top-K kernel (native/topk_composite.c) against the numba kernel: the same renders and
the same per-pixel Top-K, on scenes of every camera model and Top-K settings; its ranking
network is Batcher's and its ranking sorts; Top-Ks past its network go to numba."""

from __future__ import annotations

import ctypes
import re
from pathlib import Path

import numpy as np
import pytest

import olsplat_nodes
from olsplat_nodes.raster import RasterConfig, rasterize, topk_native
from olsplat_nodes.raster._reference import rasterize_reference
from olsplat_nodes.raster.sorting_network import batcher_pairs

from ..conftest import camera_for, random_gaussians
from .test_rasterize import assert_topk_matches

C_FILE = Path(olsplat_nodes.__file__).parent / "native" / "topk_composite.c"


@pytest.fixture
def built():
    if topk_native.kernel() is None:
        pytest.skip("the C kernels are not built here")


def both_kernels(monkeypatch, gaussians, camera, config, **kwargs):
    fast = rasterize(gaussians, camera, config, **kwargs)
    with monkeypatch.context() as patch:
        patch.setattr(topk_native, "kernel", lambda: None)
        slow = rasterize(gaussians, camera, config, **kwargs)
    return fast, slow


def assert_same_render(fast, slow):
    np.testing.assert_allclose(fast.alpha, slow.alpha, atol=2e-6)
    np.testing.assert_allclose(fast.rgb, slow.rgb, atol=2e-6)
    np.testing.assert_allclose(fast.depth, slow.depth, rtol=1e-5, atol=1e-5)
    assert abs(fast.n_evaluations - slow.n_evaluations) <= 1e-4 * slow.n_evaluations
    assert abs(fast.n_tile_pairs - slow.n_tile_pairs) <= 1e-4 * slow.n_tile_pairs


# (width, height, Gaussians, camera model, opacity logit: low = many translucent layers)
CASES = [
    (48, 36, 300, "PINHOLE_CENTRED", None),
    (47, 33, 500, "PINHOLE_SKEWED", -2.0),
    (64, 48, 800, "SIMPLE_RADIAL", -1.0),
    (50, 70, 600, "OPENCV_WIDE", -2.5),
]
CONFIGS = [
    RasterConfig(),
    RasterConfig(tile_size=8, topk_min=4, topk_max=12, topk_coverage=0.75),
    RasterConfig(tile_size=24, topk_min=1, topk_max=1),
]


@pytest.mark.parametrize("config", CONFIGS, ids=["default", "tile8-k12", "tile24-k1"])
@pytest.mark.parametrize("width,height,n,kind,opacity", CASES)
def test_c_topk_equals_the_numba_kernel(width, height, n, kind, opacity, config, built, monkeypatch):
    gaussians = random_gaussians(n, 1, seed=n + width, spread=0.6)
    if opacity is not None:
        gaussians.opacity_logits[:] = opacity
    camera = camera_for(kind, width, height)
    fast, slow = both_kernels(monkeypatch, gaussians, camera, config, background=(0.1, 0.4, 0.8))
    assert fast.alpha.max() > 0.5, "the scene must cover pixels"
    if opacity is not None:  # many layers: lists fill up and entries are replaced
        assert ((slow.topk_ids >= 0).sum(-1) == config.topk_max).any()
    assert_same_render(fast, slow)
    reference_like = {"topk_ids": slow.topk_ids, "topk_weights": slow.topk_weights}
    assert_topk_matches(fast, reference_like)


def test_a_plain_render_without_topk_equals_the_numba_kernel(built, monkeypatch):
    gaussians = random_gaussians(400, 2, seed=3)
    fast, slow = both_kernels(monkeypatch, gaussians, camera_for("PINHOLE_CENTRED", 40, 30), None, want_topk=False)
    assert fast.topk_ids is None and fast.alpha.max() > 0.5
    assert_same_render(fast, slow)


def test_a_topk_past_the_network_goes_to_numba(monkeypatch):
    config = RasterConfig(topk_min=16, topk_max=40)
    assert not topk_native.available(config.tile_size, config.topk_max)
    called = []
    monkeypatch.setattr(topk_native, "composite_topk", lambda *args: called.append(args))
    gaussians = random_gaussians(600, 0, seed=7, spread=0.5)
    gaussians.opacity_logits[:] = -2.0
    camera = camera_for("PINHOLE_CENTRED", 24, 20)
    out = rasterize(gaussians, camera, config)
    assert not called and ((out.topk_ids >= 0).sum(-1) > 32).any()
    assert_topk_matches(out, rasterize_reference(gaussians, camera, config))


def test_the_c_network_is_batchers():
    """The C file's table is batcher_pairs(32) (which tests/raster/test_rasterize.py proves sorts)."""
    text = C_FILE.read_text()
    table = re.search(r"NETWORK32\[191\]\[2\] = \{(.*?)\};", text, re.S)
    assert table is not None
    pairs = [(int(a), int(b)) for a, b in re.findall(r"\{(\d+),\s*(\d+)\}", table.group(1))]
    assert pairs == batcher_pairs(32)


def test_the_c_ranking_sorts_like_numpy(built):
    """sort32 (the AVX2 bitonic sort in this build, Batcher's network without AVX2) puts every
    list of 32 keys largest first: distinct keys, ties, zero padding, keys near 2^63."""
    rng = np.random.default_rng(0)
    lists = [
        rng.integers(0, 2**63 - 1, (4000, 32), dtype=np.int64),  # distinct
        rng.integers(0, 4, (4000, 32), dtype=np.int64),  # many ties
        (rng.integers(0, 3, (4000, 32), dtype=np.int64) << 32) | rng.integers(0, 4, (4000, 32)),
        np.where(np.arange(32) < rng.integers(0, 33, (4000, 1)), rng.integers(1, 2**40, (4000, 32)), 0),  # padded
        np.tile(np.arange(32, dtype=np.int64), (4000, 1)),  # ascending: every key moves
        2**63 - 1 - rng.integers(0, 8, (4000, 32), dtype=np.int64),
    ]
    keys = np.ascontiguousarray(np.concatenate(lists), dtype=np.int64)
    expected = -np.sort(-keys, axis=1)
    sort = topk_native.kernel().sort_key_lists32
    sort.argtypes, sort.restype = [ctypes.c_void_p, ctypes.c_int64], None
    sort(keys.ctypes.data, len(keys))
    assert np.array_equal(keys, expected)


@pytest.mark.parametrize("width,height,n,kind,opacity", CASES[:2])
def test_without_the_colour_every_other_output_is_the_same_bits(width, height, n, kind, opacity, built):
    gaussians = random_gaussians(n, 1, seed=n, spread=0.6)
    if opacity is not None:
        gaussians.opacity_logits[:] = opacity
    camera = camera_for(kind, width, height)
    full = rasterize(gaussians, camera, RasterConfig())
    plain = rasterize(gaussians, camera, RasterConfig(), want_rgb=False)  # as the accumulator renders
    assert plain.rgb.shape == (0, 0, 3) and full.rgb.shape == (height, width, 3) and full.alpha.max() > 0.5
    for name in ("alpha", "depth", "topk_ids", "topk_weights"):
        assert np.array_equal(getattr(plain, name), getattr(full, name)), name
