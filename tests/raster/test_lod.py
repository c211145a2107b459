"""The level of detail (raster/lod.py): every cube's merged Gaussian and feature against the
cube-by-cube oracle; each Gaussian drawn exactly once for any camera; nothing merged means the
exact render; a far view of a town stays close to the exact heatmap; ``active`` draws a subset."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.raster import lod, rasterize
from olsplat_nodes.raster._reference import lod_cube_reference
from olsplat_nodes.scene import Camera, intrinsics, look_at
from olsplat_nodes.scene.rotations import quat_to_rotmat, rotmat_to_quat, rotmats_to_quats

from ..conftest import random_gaussians


def test_batched_quaternions_match_the_one_matrix_version():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    q[:6] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0], [0.5, 0.5, 0.5, 0.5]]
    rotations = quat_to_rotmat(q)
    got = rotmats_to_quats(rotations)
    np.testing.assert_allclose(quat_to_rotmat(got), rotations, atol=1e-12)
    expected = np.array([rotmat_to_quat(r) for r in rotations])
    same_sign = np.sign(np.where(np.abs(expected) > 1e-9, expected, 1.0)[:, :1])  # w = 0: either sign
    np.testing.assert_allclose(got * same_sign, expected * same_sign, atol=1e-9)


@pytest.fixture(scope="module")
def town():
    gaussians = random_gaussians(3000, 2, seed=5, spread=3.0)
    gaussians.means[:, :2] -= 1.0  # cubes on both sides of 0: floor, not truncation
    tree = lod.build_lod(gaussians, lod.LodConfig(cell_m=0.5, levels=4, max_px=3.0))
    return gaussians, tree


def test_every_cube_is_the_moment_match_of_its_members(town):
    gaussians, tree = town
    features = np.random.default_rng(1).normal(size=(len(gaussians), 8)).astype(np.float32)
    merged = lod.node_features(tree, features, None)
    leaves = np.flatnonzero(tree.node_level == 1)
    cube_members: dict[int, list[int]] = {int(j): [] for j in range(len(tree))}
    for g, leaf in enumerate(tree.leaf):
        node = int(leaf)
        while node >= 0:  # the cube and every cube above it
            cube_members[node].append(g)
            node = int(tree.parent[node])
    assert sum(len(cube_members[int(j)]) for j in leaves) == len(gaussians)  # level 1 partitions the map
    top = np.flatnonzero(tree.node_level == tree.config.levels)
    assert sum(len(cube_members[int(j)]) for j in top) == len(gaussians)
    rotations = quat_to_rotmat(tree.nodes.quats)
    variances = np.exp(2.0 * tree.nodes.log_scales.astype(np.float64))
    for node in np.random.default_rng(2).choice(len(tree), 60, replace=False):
        members = np.array(cube_members[int(node)])
        ref = lod_cube_reference(gaussians, members, features)
        cov = rotations[node] @ np.diag(variances[node]) @ rotations[node].T
        np.testing.assert_allclose(tree.nodes.means[node], ref["mean"], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(cov, ref["cov"], rtol=1e-3, atol=1e-6)
        opacity = 1.0 / (1.0 + np.exp(-float(tree.nodes.opacity_logits[node])))
        assert opacity == pytest.approx(ref["opacity"], rel=1e-4)
        np.testing.assert_allclose(tree.nodes.sh[node, 0], ref["dc"], rtol=1e-4, atol=1e-6)
        assert not tree.nodes.sh[node, 1:].any()
        np.testing.assert_allclose(merged[node], ref["feature"], rtol=1e-4, atol=1e-5)
        side = tree.config.cell_m * 2 ** (tree.node_level[node] - 1)
        corner = np.floor(gaussians.means[members[0]] / side)
        assert (np.floor(gaussians.means[members] / side) == corner).all()  # one cube


def test_codebook_rows_give_the_features_of_the_rows(town):
    gaussians, tree = town
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(16, 8)).astype(np.float16)
    rows = rng.integers(-1, 16, len(gaussians)).astype(np.int32)  # -1: never observed, a 0 feature
    dense = np.where(rows[:, None] >= 0, centres[np.maximum(rows, 0)].astype(np.float32), 0.0)
    np.testing.assert_allclose(lod.node_features(tree, centres, rows), lod.node_features(tree, dense, None), atol=1e-6)


def _camera(distance: float, width: int = 80, height: int = 60) -> Camera:
    pose = look_at([0.0, -distance, 0.6 * distance], [0.0, 0.0, 0.0])
    return Camera("far", width, height, intrinsics(70.0, 70.0, width / 2, height / 2), pose)


@pytest.mark.parametrize("distance", [2.0, 15.0, 60.0, 400.0])
def test_each_gaussian_is_drawn_exactly_once(town, distance):
    _, tree = town
    own, merged = lod.select(tree, _camera(distance))
    count = own.astype(int)
    for node in np.flatnonzero(merged):
        count[_members(tree, node)] += 1
    assert (count == 1).all()
    if distance == 2.0:
        assert own.all() and not merged.any()  # near: exact
    if distance == 400.0:
        assert not own.any() and merged.sum() < len(tree) / 4  # far: a few coarse cubes


def _members(tree, node: int) -> np.ndarray:
    """The Gaussians in ``node``'s cube: those whose level-1 cube's ancestor at its level it is."""
    cube = tree.leaf
    for _ in range(tree.node_level[node] - 1):
        cube = tree.parent[cube]
    return np.flatnonzero(cube == node)


def test_nothing_merged_is_the_exact_render(town):
    gaussians, tree = town
    exact_tree = lod.LodTree(**{**tree.__dict__, "config": lod.LodConfig(cell_m=0.5, levels=4, max_px=0.0)})
    camera = _camera(15.0)
    features = np.random.default_rng(4).normal(size=(len(gaussians), 8)).astype(np.float32)
    texts = np.eye(8, dtype=np.float32)[:3]
    table, rows = lod.with_node_features(features, None, lod.node_features(tree, features, None))
    drawn = lod.drawn(exact_tree, camera)
    assert drawn[: len(gaussians)].all() and not drawn[len(gaussians) :].any()
    exact = rasterize(gaussians, camera, features=features, want_topk=False, feature_queries=texts)
    both = rasterize(
        lod.with_nodes(gaussians, tree), camera, features=table, feature_rows=rows, want_topk=False,
        feature_queries=texts, active=drawn,
    )  # fmt: skip
    np.testing.assert_array_equal(both.alpha, exact.alpha)
    np.testing.assert_array_equal(both.features, exact.features)


def test_active_draws_the_subset():
    gaussians = random_gaussians(400, 1, seed=9)
    camera = _camera(4.0)
    keep = np.random.default_rng(0).random(len(gaussians)) < 0.5
    got = rasterize(gaussians, camera, active=keep)
    expected = rasterize(gaussians.subset(keep), camera)
    np.testing.assert_array_equal(got.rgb, expected.rgb)
    assert got.n_visible == expected.n_visible
    ids = np.flatnonzero(keep)
    np.testing.assert_array_equal(got.topk_ids, np.where(expected.topk_ids >= 0, ids[expected.topk_ids], -1))
    with pytest.raises(ValueError, match="active must be"):
        rasterize(gaussians, camera, active=keep[:10])


def test_a_far_view_of_a_town_stays_close_to_the_exact_heatmap():
    """The simulator's town from 120 m: ground cells of 6 m carry one of 12 features; the merged
    render picks the same best text on all but the pixels along the cells' edges."""
    from olsplat_sim import generate_scene

    gaussians = generate_scene(60_000, size_m=60.0, seed=2).gaussians
    rng = np.random.default_rng(5)
    cells = np.floor(gaussians.means[:, :2] / 6.0).astype(np.int64)
    rows = ((cells[:, 0] * 7 + cells[:, 1] * 13) % 12).astype(np.int32)
    table = rng.normal(size=(12, 16)).astype(np.float32)
    table /= np.linalg.norm(table, axis=1, keepdims=True)
    pose = look_at([0.0, -90.0, 80.0], [0.0, 0.0, 0.0])
    camera = Camera("far", 320, 240, intrinsics(300.0, 300.0, 160.0, 120.0), pose)
    tree = lod.build_lod(gaussians, lod.LodConfig(cell_m=0.25, levels=5, max_px=2.0))
    table_c, rows_c = lod.with_node_features(table, rows, lod.node_features(tree, table, rows))
    drawn = lod.drawn(tree, camera)
    assert drawn[len(gaussians) :].any(), "the view must be far enough for cubes to merge"
    exact = rasterize(gaussians, camera, features=table, feature_rows=rows, want_topk=False, feature_queries=table)
    merged = rasterize(
        lod.with_nodes(gaussians, tree), camera, features=table_c, feature_rows=rows_c, want_topk=False,
        feature_queries=table, active=drawn,
    )  # fmt: skip
    assert merged.n_visible < 0.8 * exact.n_visible
    covered = exact.alpha > 0.5
    same = exact.features.argmax(-1) == merged.features.argmax(-1)
    assert same[covered].mean() > 0.95  # 96.5 % here: cells 6 m wide are 15 px, their edges blur by ~2 px
    assert np.abs(exact.features - merged.features)[covered].mean() < 0.02
    assert np.abs(exact.alpha - merged.alpha).mean() < 0.02
