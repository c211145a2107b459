"""The fast rasterizer against the slow numpy reference, and its Top-K contract: with the numba
kernel and, where it is built, the C Top-K kernel (native/topk_composite.c)."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.raster import RasterConfig, rasterize, topk_native
from olsplat_nodes.raster._reference import rasterize_reference
from olsplat_nodes.raster.binning import radix_argsort

from ..conftest import camera_for, random_gaussians


@pytest.fixture(params=["numba", "c"])
def topk_kernel(request, monkeypatch):
    """Each Top-K test runs with both compositing kernels (the C one skipped where it is not built)."""
    if request.param == "numba":
        monkeypatch.setattr(topk_native, "kernel", lambda: None)
    elif topk_native.kernel() is None:
        pytest.skip("the C kernels are not built here")
    return request.param


def assert_topk_matches(fast, ref, tie_tol=1e-6):
    """Same weights everywhere; same ids wherever a weight is not tied with a neighbour rank."""
    np.testing.assert_allclose(fast.topk_weights, ref["topk_weights"], atol=2e-6)
    w = ref["topk_weights"]
    gap = np.full(w.shape, np.inf)
    step = w[..., :-1] - w[..., 1:]  # >= 0: ranks are sorted
    gap[..., 1:] = step
    gap[..., :-1] = np.minimum(gap[..., :-1], step)
    valid = ref["topk_ids"] >= 0
    untied = valid & (gap > tie_tol)
    assert untied.sum() >= 0.9 * valid.sum()
    np.testing.assert_array_equal(fast.topk_ids[untied], ref["topk_ids"][untied])
    np.testing.assert_array_equal((fast.topk_ids >= 0).sum(-1), valid.sum(-1))


CASES = [
    # (width, height, n, camera kind, sh degree, feature dim)
    (32, 24, 40, "PINHOLE_CENTRED", 0, 0),
    (47, 33, 120, "PINHOLE_SKEWED", 1, 3),
    (64, 48, 200, "SIMPLE_RADIAL", 2, 0),
    (50, 70, 150, "OPENCV_WIDE", 3, 17),
    (80, 60, 400, "PINHOLE_CENTRED", 3, 8),
]


@pytest.mark.parametrize("width,height,n,kind,sh_degree,dim", CASES)
def test_fast_matches_reference(width, height, n, kind, sh_degree, dim, topk_kernel):
    gaussians = random_gaussians(n, sh_degree, seed=n + width)
    camera = camera_for(kind, width, height)
    features = np.random.default_rng(1).normal(size=(n, dim)).astype(np.float32) if dim else None
    fast = rasterize(gaussians, camera, features=features)
    ref = rasterize_reference(gaussians, camera, features=features)

    assert fast.alpha.max() > 0.5, "the scene must actually cover pixels"
    assert np.abs(fast.rgb - ref["rgb"]).mean() < 1e-4
    assert np.abs(fast.alpha - ref["alpha"]).mean() < 1e-4
    np.testing.assert_allclose(fast.rgb, ref["rgb"], atol=1e-4)
    np.testing.assert_allclose(fast.depth, ref["depth"], rtol=1e-4, atol=1e-4)
    if dim:
        np.testing.assert_allclose(fast.features, ref["features"], rtol=1e-3, atol=1e-4)
    assert_topk_matches(fast, ref)
    assert fast.n_tile_pairs == ref["tile_pairs"]
    assert 0 < fast.n_evaluations <= fast.n_tile_pairs


def test_many_contributors_exercise_the_topk_cap(topk_kernel):
    """A dense, translucent stack: pixels with more than 32 contributors and K between the bounds."""
    gaussians = random_gaussians(600, 0, seed=7, spread=0.5)
    gaussians.opacity_logits[:] = -2.0  # opacity ~0.12: many layers before saturation
    camera = camera_for("PINHOLE_CENTRED", 24, 20)
    fast = rasterize(gaussians, camera)
    ref = rasterize_reference(gaussians, camera)
    counts = (fast.topk_ids >= 0).sum(-1)
    assert (counts == 32).any() and ((counts > 16) & (counts < 32)).any()
    assert np.abs(fast.rgb - ref["rgb"]).mean() < 1e-4
    assert_topk_matches(fast, ref)


def test_background_and_config_variants(topk_kernel):
    gaussians = random_gaussians(100, 1, seed=3)
    camera = camera_for("PINHOLE_SKEWED", 40, 30)
    config = RasterConfig(tile_size=8, topk_min=4, topk_max=12, topk_coverage=0.75, eps2d=0.1)
    fast = rasterize(gaussians, camera, config, background=(0.2, 0.5, 1.0))
    ref = rasterize_reference(gaussians, camera, config, background=(0.2, 0.5, 1.0))
    assert fast.topk_ids.shape == (30, 40, 12)
    np.testing.assert_allclose(fast.rgb, ref["rgb"], atol=1e-4)
    assert_topk_matches(fast, ref)


def test_topk_contract(topk_kernel):
    gaussians = random_gaussians(300, 0, seed=11)
    config = RasterConfig()
    out = rasterize(gaussians, camera_for("PINHOLE_CENTRED", 64, 48), config)
    w, ids = out.topk_weights, out.topk_ids
    valid = ids >= 0
    count = valid.sum(-1)
    assert np.all(np.diff(w, axis=-1) <= 0), "weights are sorted, largest first"
    assert np.all(w[~valid] == 0) and np.all(w[valid] > 0)
    assert np.all(valid[..., :-1] | ~valid[..., 1:]), "ids are packed at the front"
    assert np.all(w.sum(-1) <= out.alpha + 1e-5)
    # below the cap and above the floor, K is the first rank reaching 90 % coverage
    mid = (count > config.topk_min) & (count < config.topk_max)
    assert mid.any()
    covered = w.sum(-1)[mid]
    without_last = covered - np.take_along_axis(w, (count - 1)[..., None], -1)[..., 0][mid]
    assert np.all(covered >= config.topk_coverage * out.alpha[mid] - 1e-6)
    assert np.all(without_last < config.topk_coverage * out.alpha[mid] + 1e-6)
    # each id appears at most once per pixel
    sorted_ids = np.sort(np.where(valid, ids, -np.arange(1, 33)), axis=-1)
    assert np.all(np.diff(sorted_ids, axis=-1) != 0)


def test_degenerate_gaussians_are_skipped(topk_kernel):
    clean = random_gaussians(80, 2, seed=5)
    camera = camera_for("PINHOLE_CENTRED", 40, 30)
    expected = rasterize(clean, camera)
    bad = random_gaussians(86, 2, seed=5)
    bad.means[:80], bad.quats[:80], bad.log_scales[:80] = clean.means, clean.quats, clean.log_scales
    bad.opacity_logits[:80], bad.sh[:80] = clean.opacity_logits, clean.sh
    bad.means[80] = np.nan  # NaN position
    bad.log_scales[81] = -np.inf  # zero scale
    bad.means[82] = camera.center - 2.0 * camera.world_from_camera[:3, 2]  # behind the camera
    bad.quats[83] = 0.0  # no rotation at all
    bad.sh[84, 0, 1] = np.inf  # infinite colour
    bad.opacity_logits[85] = np.nan
    got = rasterize(bad, camera)
    assert got.n_visible == expected.n_visible
    np.testing.assert_array_equal(got.rgb, expected.rgb)
    np.testing.assert_array_equal(got.topk_ids, expected.topk_ids)
    ref = rasterize_reference(bad, camera)
    np.testing.assert_allclose(got.rgb, ref["rgb"], atol=1e-4)


def test_empty_view_and_no_topk(topk_kernel):
    gaussians = random_gaussians(50, 0, seed=2)
    camera = camera_for("PINHOLE_CENTRED", 40, 30)
    camera.world_from_camera[:3, 3] = [0.0, 0.0, -10.0]  # looking at nothing
    out = rasterize(gaussians, camera)
    assert out.n_visible == 0 and out.alpha.max() == 0 and (out.topk_ids == -1).all()
    plain = rasterize(random_gaussians(50, 0, seed=2), camera_for("PINHOLE_CENTRED", 40, 30), want_topk=False)
    assert plain.topk_ids is None and plain.alpha.max() > 0


def test_features_shape_is_checked():
    gaussians = random_gaussians(10, 0)
    with pytest.raises(ValueError, match="features must be"):
        rasterize(gaussians, camera_for("PINHOLE_CENTRED", 8, 8), features=np.zeros((9, 4)))


@pytest.mark.parametrize(
    "kind", ["wide", "one_exponent", "low_bits_only", "all_equal", "empty", "one", "with_zeros", "huge"]
)
def test_radix_argsort_matches_stable_argsort(kind):
    """Against numpy's stable argsort, with the cases where passes are skipped (a digit the
    same for every key: keys of one binade share their high bits; keys that differ only in
    their low bits; all equal) and many ties (their order must stay the input order)."""
    rng = np.random.default_rng(0)
    keys = {
        "wide": rng.uniform(0.01, 1000.0, 50_000),
        "one_exponent": rng.uniform(64.0, 128.0, 50_000),  # the top pass is skipped
        "low_bits_only": np.float32(100.0) + np.float32(1e-5) * rng.integers(0, 200, 50_000),
        "all_equal": np.full(1000, 3.5),
        "empty": np.zeros(0),
        "one": np.array([7.0]),
        "with_zeros": np.where(rng.random(20_000) < 0.3, 0.0, rng.uniform(0.0, 5.0, 20_000)),
        "huge": rng.uniform(0.0, 3e38, 20_000),
    }[kind].astype(np.float32)
    if len(keys) > 10:
        keys[::5] = keys[7]  # many ties
    order = radix_argsort(keys)
    assert order.dtype == np.int32
    np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="topk_min"):
        RasterConfig(topk_min=40, topk_max=32)
    with pytest.raises(ValueError, match="topk_coverage"):
        RasterConfig(topk_coverage=1.5)


def _list_and_rank(weights_in, k_cap):
    """Offer weights_in (positions 0, 1, ...) to one pixel's list, rank it: (positions, weights)."""
    from olsplat_nodes.raster.composite import offer, rank, rank_key

    keys, top_n, top_last = np.zeros(k_cap, np.uint64), np.zeros(1, np.int32), np.zeros(1, np.int32)
    bits = np.empty(1, np.float32)
    for j, w in enumerate(weights_in):
        offer(keys, top_n, top_last, 0, rank_key(np.float32(w), j, bits, bits.view(np.uint32)), k_cap)
    n = int(top_n[0])
    rank(keys, n, np.empty(32, np.uint64))
    positions = 0xFFFFFFFF - (keys[:n] & np.uint64(0xFFFFFFFF)).astype(np.int64)
    return positions, (keys[:n] >> np.uint64(32)).astype(np.uint32).view(np.float32)


@pytest.mark.parametrize("k_cap", [8, 32, 40])  # 40: past the network, numba's sort
def test_topk_list_keeps_the_stable_ranking_on_ties(k_cap):
    """The per-pixel list (offer, then rank) against a stable sort, with many exact ties."""
    rng = np.random.default_rng(4)
    for trial in range(100):
        weights_in = rng.choice(np.float32([0.1, 0.2, 0.3, 0.4, 1e-3, 0.999]), size=rng.integers(1, 80))
        positions, weights = _list_and_rank(weights_in, k_cap)
        expected = np.argsort(-weights_in, kind="stable")[:k_cap]
        np.testing.assert_array_equal(positions, expected, err_msg=f"trial {trial}")
        np.testing.assert_array_equal(weights, weights_in[expected])


def test_the_unrolled_network_is_the_generated_one_and_sorts():
    from itertools import product

    from olsplat_nodes.raster import sorting_network
    from olsplat_nodes.raster._network32 import sort_descending

    assert sorting_network.GENERATED.read_text() == sorting_network.generated_source(), (
        "run python -m olsplat_nodes.raster.sorting_network"
    )
    assert len(sorting_network.batcher_pairs(32)) == 191
    # 0-1 principle: a network that sorts every 0/1 input sorts every input; all 2^16 inputs of
    # the 16-input network, and random inputs of the 32-input one
    values = np.array(list(product((0, 1), repeat=16)), np.int8)  # [65536, 16]
    expected = np.sort(values, axis=1)[:, ::-1]
    for a, b in sorting_network.batcher_pairs(16):
        values[:, a], values[:, b] = np.maximum(values[:, a], values[:, b]), np.minimum(values[:, a], values[:, b])
    np.testing.assert_array_equal(values, expected)
    rng = np.random.default_rng(3)
    for _ in range(200):
        keys = rng.integers(0, 2**63, size=32, dtype=np.uint64)
        keys[rng.random(32) < 0.3] = 0
        got = keys.copy()
        sort_descending(got)
        np.testing.assert_array_equal(got, np.sort(keys)[::-1])


@pytest.mark.parametrize("kind,spread", [("PINHOLE_CENTRED", 3.0), ("PINHOLE_SKEWED", 3.0), ("OPENCV_WIDE", 12.0)])
def test_the_early_off_screen_test_keeps_every_gaussian_that_reaches_the_image(kind, spread):
    """Projection drops a Gaussian whose bounded radius cannot reach the image before computing
    its covariance: over Gaussians around the image's borders, long and thin in every
    direction (a centre off-screen, an end on it), the kept set and every kept radius are the
    reference's."""
    from olsplat_nodes.raster._reference import project_reference
    from olsplat_nodes.raster.project import project

    gaussians = random_gaussians(4000, 1, seed=11, spread=spread)
    rng = np.random.default_rng(12)
    gaussians.log_scales[:] = np.log(rng.uniform(0.01, 0.05, (4000, 3)))
    gaussians.log_scales[np.arange(4000), rng.integers(0, 3, 4000)] = np.log(rng.uniform(0.2, 2.0, 4000))
    gaussians.opacity_logits[:] = 3.0
    camera, config = camera_for(kind, 64, 48), RasterConfig()
    fast, ref = project(gaussians, camera, config), project_reference(gaussians, camera, config)
    centre_off = ~((ref["mean2d"] >= 0) & (ref["mean2d"] < [64, 48])).all(1)
    assert (ref["valid"] & centre_off).sum() > 100, "the case needs Gaussians that reach in from off-screen"
    assert (~ref["valid"]).sum() > 100, "and Gaussians that do not"
    np.testing.assert_array_equal(fast.radii > 0, ref["valid"])
    radius = np.ceil(config.radius_sigmas * np.sqrt(1 / np.linalg.eigvalsh(ref["conic"])[:, 0]))
    assert (np.abs(fast.radii[ref["valid"]] - radius[ref["valid"]]) <= 1).all()


def test_the_prefetch_hint_compiles_for_rows_and_changes_nothing():
    from numba import njit
    from numba.core.errors import TypingError

    from olsplat_nodes.raster.prefetch import prefetch

    @njit
    def first_column(table, rows):
        total = 0.0
        for r in rows:
            prefetch(table, r, 0)
            prefetch(table, r, 16)
        for r in rows:
            total += table[r, 0]
        return total

    table = np.arange(64 * 32, dtype=np.float32).reshape(64, 32)
    rows = np.array([3, 60, 0], np.int64)
    assert first_column(table, rows) == table[rows, 0].sum()

    @njit
    def flat(values):
        prefetch(values, 0, 0)

    with pytest.raises(TypingError):
        flat(np.zeros(4, np.float32))


def _gsplat_rectangles(projected, config, width, height):
    """The same projection with gsplat's own tile lists: every tile of each 3-sigma square."""
    import dataclasses

    from olsplat_nodes.raster.project import MX, MY

    t = config.tile_size
    r = projected.radii.astype(np.float64)
    u, v = projected.records[:, MX].astype(np.float64), projected.records[:, MY].astype(np.float64)
    rects = np.stack(
        [
            np.clip(np.floor((u - r) / t), 0, -(-width // t)),
            np.clip(np.floor((v - r) / t), 0, -(-height // t)),
            np.clip(np.ceil((u + r) / t), 0, -(-width // t)),
            np.clip(np.ceil((v + r) / t), 0, -(-height // t)),
        ],
        1,
    ).astype(np.int32)
    rects[projected.radii <= 0] = 0
    return dataclasses.replace(projected, tile_rects=rects)


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("kind,opacity", [("PINHOLE_CENTRED", None), ("OPENCV_WIDE", 4.0), ("SIMPLE_RADIAL", -3.0)])
def test_tiles_list_only_gaussians_whose_alpha_box_reaches_them(kind, opacity, native, monkeypatch):
    """A Gaussian is listed only in the tiles its alpha >= 1/255 box reaches (within gsplat's
    3-sigma square): every output is bit for bit that of gsplat's longer lists, over opaque
    Gaussians (box wider than 3 sigma), faint ones (box much narrower) and mixed ones, in the
    Top-K render and the heatmap render, with the C kernels and with numba's."""
    import importlib

    from olsplat_nodes.raster import heatmap_native
    from olsplat_nodes.raster.project import project

    raster_module = importlib.import_module("olsplat_nodes.raster.rasterize")  # the package exports the function
    if not native:
        monkeypatch.setattr(heatmap_native, "kernel", lambda: None)
        monkeypatch.setattr(topk_native, "kernel", lambda: None)
    gaussians = random_gaussians(700, 1, seed=5, spread=1.2)
    if opacity is not None:
        gaussians.opacity_logits[:] = opacity + np.random.default_rng(6).normal(0.0, 0.5, 700)
    camera, config = camera_for(kind, 72, 52), RasterConfig()
    rng = np.random.default_rng(7)
    features = rng.normal(size=(700, 16)).astype(np.float32)
    texts = rng.normal(size=(3, 16)).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)

    def renders():
        return (
            rasterize(gaussians, camera, config),
            rasterize(gaussians, camera, config, features=features, want_topk=False, feature_queries=texts),
        )

    snug = renders()
    with monkeypatch.context() as patch:
        patch.setattr(raster_module, "project", lambda *a, **k: _gsplat_rectangles(project(*a, **k), config, 72, 52))
        gsplat = renders()
    for ours, theirs in zip(snug, gsplat, strict=True):
        assert ours.alpha.max() > 0.5, "the scene must cover pixels"
        for name in ("rgb", "alpha", "depth", "features", "topk_ids", "topk_weights"):
            np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), err_msg=name)
        assert ours.n_evaluations == theirs.n_evaluations
        assert ours.n_intersections < theirs.n_intersections
