"""3D instances: the voxel-grid DBSCAN against its brute-force oracle, and what it means."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.query._reference import instances_in_3d_bfs
from olsplat_nodes.query.localize import Instance3D, instances_in_3d


def assert_same_instances(fast: list[Instance3D], slow: list[Instance3D]) -> None:
    assert [i.gaussians for i in fast] == [i.gaussians for i in slow]
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(a.box_min, b.box_min)  # min and max pick points: exact
        np.testing.assert_array_equal(a.box_max, b.box_max)
        np.testing.assert_allclose(a.centre, b.centre, rtol=1e-12, atol=1e-9)


def lattice(rng) -> tuple[np.ndarray, float, int]:
    """0-9 points in a third of the voxels of a 9^3 lattice (eps = 1): dense and sparse voxels
    side by side, clusters touching by faces, edges and corners only, border points between."""
    counts = rng.integers(0, 10, (9, 9, 9)) * (rng.random((9, 9, 9)) < 0.35)
    cells = np.repeat(np.argwhere(counts), counts[counts > 0], axis=0)
    points = cells + rng.uniform(0.01, 0.99, cells.shape)
    return np.vstack([[0.0, 0.0, 0.0], points]), 1.0, 10  # the origin point pins the grid


def diagonal(rng) -> tuple[np.ndarray, float, int]:
    """Blobs in voxels along a staircase that touch only at edges or corners, some steps skipped."""
    steps = [(0, 0, 0), (1, 1, 1), (2, 2, 1), (3, 3, 2), (5, 5, 3), (6, 6, 4), (6, 7, 5), (9, 0, 0), (10, 1, 0)]
    blobs = [np.array(s) + rng.uniform(0.0, 1.0, (rng.integers(3, 12), 3)) for s in steps]
    return np.vstack([[0.0, 0.0, 0.0], *blobs]) * 2.0, 2.0, 12


def road(rng) -> tuple[np.ndarray, float, int]:
    """A 400 m road 3 m wide whose density varies along it, with two breaks, plus parked blobs."""
    x = rng.uniform(0, 400, 6000)
    x = x[((x < 140) | (x > 143.5)) & ((x < 300) | (x > 301))]  # a 3.5 m gap, then a 1 m gap
    keep = rng.random(len(x)) < 0.5 + 0.5 * np.sin(x / 17.0) ** 2
    strip = np.c_[x[keep], rng.uniform(0, 3, keep.sum()), rng.normal(0, 0.05, keep.sum())]
    blobs = rng.normal(0, 0.4, (300, 3)) + np.repeat(rng.uniform((0, 5, 0), (400, 8, 2), (10, 3)), 30, axis=0)
    return np.vstack([strip, blobs]), 1.5, 20


def noise(rng) -> tuple[np.ndarray, float, int]:
    """Sparse noise everywhere, a few tight blobs of different sizes, isolated points near them."""
    scatter = rng.uniform((-50, -50, 0), (50, 50, 20), (1500, 3))
    blobs = [rng.normal(rng.uniform(-40, 40, 3), rng.uniform(0.3, 2.0), (rng.integers(5, 400), 3)) for _ in range(6)]
    return np.vstack([scatter, *blobs]), 1.5, 20


def roofs(rng) -> tuple[np.ndarray, float, int]:
    """Dense roofs (40-70 centres per m^2, as a survey map's) with sparse fringes: many half-side
    cells of a voxel hold min_points centres (all core at once), many hold a few less."""
    parts = []
    for _ in range(4):
        corner, size = rng.uniform(0, 30, 2), rng.uniform(4, 9, 2)
        n = int(rng.uniform(40, 70) * size.prod())
        xy = corner + rng.uniform(0, 1, (n, 2)) * size
        parts.append(np.c_[xy, rng.uniform(5, 10) + rng.normal(0, 0.1, n)])
        fringe = corner + rng.uniform(-1, 1, (n // 10, 2)) * size
        parts.append(np.c_[fringe, rng.uniform(0, 12, n // 10)])
    return np.vstack(parts), 1.5, 20


@pytest.mark.parametrize("scene", [lattice, diagonal, road, noise, roofs])
@pytest.mark.parametrize("seed", range(5))
def test_matches_the_reference(scene, seed):
    points, eps, min_points = scene(np.random.default_rng(seed))
    rng = np.random.default_rng(100 + seed)
    means = np.vstack([points, rng.uniform(-100, 100, (500, 3))])  # unselected Gaussians elsewhere
    selected = np.zeros(len(means), bool)
    selected[: len(points)] = True
    fast = instances_in_3d(means, selected, eps, min_points)
    assert_same_instances(fast, instances_in_3d_bfs(means, selected, eps, min_points))
    assert [i.gaussians for i in fast] == sorted((i.gaussians for i in fast), reverse=True)
    assert all(i.gaussians >= min_points for i in fast)
    assert_same_instances(instances_in_3d(means, np.flatnonzero(selected), eps, min_points), fast)  # indices select too


@pytest.mark.parametrize("min_points", [1, 3, 5, 20, 60])
def test_matches_the_reference_over_min_points(min_points):
    points, eps, _ = lattice(np.random.default_rng(7))
    selected = np.ones(len(points), bool)
    assert_same_instances(
        instances_in_3d(points, selected, eps, min_points), instances_in_3d_bfs(points, selected, eps, min_points)
    )


def test_empty_and_too_small_selections():
    means = np.random.default_rng(0).normal(0, 0.1, (50, 3))
    assert instances_in_3d(means, np.zeros(50, bool)) == []
    assert instances_in_3d(means, np.arange(19)) == []  # 19 points in one tight blob, fewer than min_points
    assert instances_in_3d_bfs(means, np.arange(19)) == []
    assert [i.gaussians for i in instances_in_3d(means, np.arange(20))] == [20]


def test_two_separated_boxes_are_two_instances_with_their_boxes():
    rng = np.random.default_rng(3)
    big = rng.uniform((0, 0, 0), (4, 3, 2), (2000, 3))
    small = rng.uniform((20, 5, 0), (23, 9, 1), (700, 3))
    means = np.vstack([small, rng.uniform(-50, 50, (100, 3)), big]).astype(np.float32)
    selected = np.ones(len(means), bool)
    selected[len(small) : len(small) + 100] = False
    instances = instances_in_3d(means, selected)
    assert [i.gaussians for i in instances] == [2000, 700]
    for instance, box in zip(instances, (big, small), strict=True):
        box = box.astype(np.float32).astype(np.float64)
        assert instance.box_min == tuple(box.min(0)) and instance.box_max == tuple(box.max(0))
        np.testing.assert_allclose(instance.centre, box.mean(0), atol=1e-9)
        assert all(isinstance(x, float) for x in (*instance.box_min, *instance.box_max, *instance.centre))


@pytest.mark.parametrize("gap, expected", [(0.6, 1), (1.4, 1), (1.6, 2), (10.0, 2)])
def test_objects_closer_than_eps_merge_and_farther_stay_separate(gap, expected):
    rng = np.random.default_rng(5)
    left = rng.uniform((0, 0, 0), (6, 6, 0.2), (3000, 3))
    right = rng.uniform((6 + gap, 0, 0), (12 + gap, 6, 0.2), (3000, 3))
    for shift in (0.0, 0.37, 0.81, 1.22):  # a lone noise point sets the grid's corner: wherever it falls
        means = np.vstack([[[-20.0 - shift, -20.0, -20.0]], left, right])
        assert len(instances_in_3d(means, np.ones(len(means), bool), eps=1.5)) == expected


def test_sparse_noise_forms_no_instances():
    rng = np.random.default_rng(11)
    scatter = rng.uniform((-150, -150, 0), (150, 150, 50), (5000, 3))  # ~0.001 points per cubic metre
    assert instances_in_3d(scatter, np.ones(len(scatter), bool)) == []
    blob = rng.normal((10, 10, 10), 0.5, (200, 3))
    means = np.vstack([scatter, blob])
    assert [i.gaussians for i in instances_in_3d(means, np.ones(len(means), bool))] == [200]


def dbscan_sizes(points: np.ndarray, eps: float, min_points: int) -> list[int]:
    """Cluster sizes, largest first, from the rule this replaced: open3d's DBSCAN."""
    open3d = pytest.importorskip("open3d")
    cloud = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(points))
    labels = np.asarray(cloud.cluster_dbscan(eps=eps, min_points=min_points, print_progress=False))
    return sorted(np.bincount(labels[labels >= 0]).tolist(), reverse=True) if (labels >= 0).any() else []


def test_agrees_with_dbscan_on_surfaces_and_noise():
    rng = np.random.default_rng(2)
    parts = [
        np.c_[rng.uniform(0, 40, 4000), rng.uniform(0, 4, 4000), rng.normal(0, 0.05, 4000)],  # road
        np.c_[rng.uniform(0, 8, 2000), rng.uniform(10, 16, 2000), 6 + rng.normal(0, 0.05, 2000)],  # roof
        np.c_[rng.uniform(20, 30, 1500), np.full(1500, 12.0), rng.uniform(0, 5, 1500)],  # wall
        rng.normal((35, 20, 3), 1.0, (600, 3)),  # tree
        rng.uniform((-20, -20, 0), (60, 40, 20), (400, 3)),  # noise
    ]
    points = np.vstack(parts)
    ours = [i.gaussians for i in instances_in_3d(points, np.ones(len(points), bool))]
    assert ours == dbscan_sizes(points, 1.5, 20) and len(ours) == 4


@pytest.mark.parametrize("seed", range(5))
def test_agrees_with_dbscan_on_blobs_in_noise(seed):
    points, eps, min_points = noise(np.random.default_rng(seed))
    ours = [i.gaussians for i in instances_in_3d(points, np.ones(len(points), bool), eps, min_points)]
    assert ours == dbscan_sizes(points, eps, min_points)


def test_the_documented_departure_core_points_sharing_a_voxel_link():
    """Two tight blobs 1.4 m apart inside one 1 m voxel: DBSCAN (eps 1 m) finds two clusters, the
    voxel grid one; with the blobs in neighbouring voxels, two here as well."""
    rng = np.random.default_rng(0)
    blobs = [rng.normal(0.1, 0.02, (30, 3)), rng.normal(0.9, 0.02, (30, 3))]
    corner = np.zeros((1, 3))  # pins the grid: both blobs in voxel (0, 0, 0)
    points = np.vstack([corner, *blobs])
    assert dbscan_sizes(points, 1.0, 20) == [31, 30]  # the corner point joins the nearer blob
    assert [i.gaussians for i in instances_in_3d(points, np.ones(len(points), bool), 1.0, 20)] == [61]
    apart = np.vstack([corner, blobs[0], blobs[1] + [0.5, 0.0, 0.0]])  # 1.8 m apart, voxels (0,0,0) and (1,0,0)
    assert sorted(i.gaussians for i in instances_in_3d(apart, np.ones(len(apart), bool), 1.0, 20)) == [30, 31]


def test_non_finite_centres_are_noise():
    rng = np.random.default_rng(4)
    means = np.vstack([rng.normal(0, 0.3, (50, 3)), [[np.nan, 0, 0], [0, np.inf, 0]], rng.normal(9, 0.3, (30, 3))])
    instances = instances_in_3d(means, np.ones(len(means), bool))
    assert [i.gaussians for i in instances] == [50, 30]
    assert all(np.isfinite([*i.box_min, *i.box_max, *i.centre]).all() for i in instances)


def test_rejects_a_bad_eps():
    with pytest.raises(ValueError, match="eps=0"):
        instances_in_3d(np.zeros((30, 3)), np.ones(30, bool), eps=0)


def test_four_planes_in_130k_points_with_noise():
    """A selection the size of a real query's (speed is measured by ``olsplat bench query``, not
    here: open3d's DBSCAN took 1-8 s on selections like this, the voxel grid about 20 ms)."""
    rng = np.random.default_rng(0)
    planes = [
        np.c_[rng.uniform(x, x + 30, 30000), rng.uniform(0, 20, 30000), rng.normal(h, 0.05, 30000)]
        for x, h in ((0, 0), (40, 6), (80, 9), (120, 3))
    ]
    means = np.vstack([*planes, rng.uniform((0, 0, 0), (150, 20, 20), (10000, 3))])
    selected = np.ones(len(means), bool)
    instances = instances_in_3d(means, selected)
    assert len(instances) == 4, "four planes; the noise forms nothing on its own"
    assert all(30000 <= i.gaussians < 30600 for i in instances), "each plane with the noise points right against it"


@pytest.mark.parametrize("scene", [lattice, diagonal])
@pytest.mark.parametrize("seed", range(3))
def test_the_maps_voxel_index_gives_the_references_instances(scene, seed):
    """With the map's VoxelIndex the selection is not sorted again; on the same grid (both pinned
    at the origin point) the instances are the reference's exactly."""
    from olsplat_nodes.query.localize import VoxelIndex

    points, eps, min_points = scene(np.random.default_rng(seed))
    rng = np.random.default_rng(200 + seed)
    means = np.vstack([points, rng.uniform(150, 300, (500, 3))])  # unselected, above the origin
    selected = np.zeros(len(means), bool)
    selected[: len(points)] = True
    index = VoxelIndex.build(means, eps)
    fast = instances_in_3d(means, selected, eps, min_points, index=index)
    assert [i.gaussians for i in fast] == sorted((i.gaussians for i in fast), reverse=True)
    assert_same_instances(fast, instances_in_3d_bfs(means, selected, eps, min_points))
    assert_same_instances(instances_in_3d(means, np.flatnonzero(selected), eps, min_points, index=index), fast)


@pytest.mark.parametrize("seed", range(3))
def test_on_another_grid_the_index_moves_only_border_points(seed):
    """Anchored at the map's lowest centre instead of the selection's, the grid changes only the
    documented approximations: the same instances, each within a few border points."""
    from olsplat_nodes.query.localize import VoxelIndex

    points, eps, min_points = road(np.random.default_rng(seed))
    means = np.vstack([points, [[-7.3, -4.1, -2.2]], np.full((3, 3), np.nan)])  # another origin; NaN is noise
    selected = np.ones(len(means), bool)
    selected[len(points)] = False
    plain = instances_in_3d(means, selected, eps, min_points)
    indexed = instances_in_3d(means, selected, eps, min_points, index=VoxelIndex.build(means, eps))
    assert len(indexed) == len(plain) > 5
    for a in plain:  # each instance has its counterpart: nearest centre, nearly the same size
        b = min(indexed, key=lambda i: float(np.linalg.norm(np.subtract(i.centre, a.centre))))
        assert np.linalg.norm(np.subtract(a.centre, b.centre)) < 0.5
        assert abs(a.gaussians - b.gaussians) <= max(10, 0.03 * a.gaussians)


def test_a_crowded_half_cell_makes_core_points_and_a_spread_voxel_does_not():
    """The core shortcut (every point of a half-side cell holding min_points is core) holds
    only because such a cell is less than eps across: 20 points split between opposite corners
    of one voxel, more than eps apart, are not core; 20 points in one half-side cell are."""
    rng = np.random.default_rng(3)
    eps = 1.0
    low_corner = rng.uniform(0.0, 0.05, (10, 3))
    far_corner = rng.uniform(0.66, 0.7, (10, 3))  # more than eps from every low-corner point
    spread = np.vstack([low_corner, far_corner])
    assert instances_in_3d(spread, np.arange(20), eps, 20) == []
    assert instances_in_3d_bfs(spread, np.arange(20), eps, 20) == []
    crowded = np.vstack([[0.0, 0.0, 0.0], rng.uniform(0.0, 0.49, (19, 3))])
    (one,) = instances_in_3d(crowded, np.arange(20), eps, 20)
    assert one.gaussians == 20


def test_touching_voxel_pairs_are_the_binary_searches():
    """The merge walk finds the pairs 13 binary searches per voxel find, in the same order."""
    from olsplat_nodes.query.localize import _HALF_NEIGHBOURS, _touching_pairs

    rng = np.random.default_rng(8)
    dims = np.array([40, 50, 12])
    ijk = rng.integers(1, dims - 1, (3000, 3))
    keys = np.unique((ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2])
    firsts, seconds = [], []
    for i, j, k in _HALF_NEIGHBOURS:
        wanted = keys + (i * dims[1] + j) * dims[2] + k
        at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
        hit = keys[at] == wanted
        firsts.append(np.flatnonzero(hit))
        seconds.append(at[hit])
    first, second = _touching_pairs(keys, dims)
    assert len(first) > 1000
    np.testing.assert_array_equal(first, np.concatenate(firsts))
    np.testing.assert_array_equal(second, np.concatenate(seconds))


def lawn(rng) -> tuple[np.ndarray, float, int]:
    """Flat patches whose density (4-40 centres per m^2) straddles the core test's threshold at
    eps = 1.5 m, min_points = 20, some tilted, with a few points lifted off them: many voxels
    where whole half-side cells, single points against cells, or only distances decide."""
    parts = []
    for _ in range(6):
        corner, size = rng.uniform(0, 40, 2), rng.uniform(3, 10, 2)
        n = int(rng.uniform(4, 40) * size.prod())
        xy = corner + rng.uniform(0, 1, (n, 2)) * size
        tilt = rng.uniform(-0.5, 0.5, 2)
        parts.append(np.c_[xy, rng.uniform(0, 5) + (xy - corner) @ tilt + rng.normal(0, 0.02, n)])
    parts.append(rng.uniform((0, 0, 0), (50, 50, 8), (200, 3)))
    return np.vstack(parts), 1.5, 20


def clumps(rng) -> tuple[np.ndarray, float, int]:
    """Isolated voxels (eps = 1, 3 m apart, so no neighbour adds to a count) each holding 2-4
    tight blobs of 15-30 points in all at random places in the voxel: whether a point is core
    turns on exactly which blobs of its voxel lie within eps, the case where a wrong bound on a
    half-side cell's box would count a blob too many."""
    parts = [np.zeros((1, 3))]  # pins the grid at the origin
    for i in range(1, 9):
        for j in range(1, 9):
            sizes = rng.multinomial(int(rng.integers(15, 31)), np.ones(int(rng.integers(2, 5))) / 4)
            for size in sizes[sizes > 0]:
                centre = np.array([3.0 * i, 3.0 * j, 0.0]) + rng.uniform(0.06, 0.94, 3)
                parts.append(centre + rng.uniform(-0.05, 0.05, (size, 3)))
    return np.vstack(parts), 1.0, 12


@pytest.mark.parametrize("scene", [lattice, road, noise, roofs, lawn, clumps])
@pytest.mark.parametrize("seed", range(4))
def test_core_points_are_dbscans(scene, seed):
    """The core test with its shortcuts (whole half-side cells, a point against a cell's box)
    gives every point DBSCAN's verdict: min_points within eps, counted by brute force."""
    from olsplat_nodes.query.localize import _core, _neighbourhoods, _touching_pairs, _voxelise

    points, eps, min_points = scene(np.random.default_rng(seed))
    points, keys, start, dims, lowest = _voxelise(points.astype(np.float64), eps)
    begin, around = _neighbourhoods(len(keys), *_touching_pairs(keys, dims))
    core = _core(points, start, begin, around, eps * eps, min_points, lowest, eps)
    within = np.stack([((points - p) ** 2).sum(1) <= eps * eps for p in points]).sum(1)
    np.testing.assert_array_equal(core, within >= min_points)
    assert 0 < core.sum() < len(points)  # both verdicts occur


@pytest.mark.parametrize("seed", range(6))
def test_a_selection_in_index_order_is_grouped_by_voxel(seed):
    """``_grouped`` (two parallel passes over chunks of the index's voxels) against numpy: the
    taken rows in order, widened to float64, and each voxel that holds one once."""
    from olsplat_nodes.query.localize import _grouped

    rng = np.random.default_rng(seed)
    n = int(rng.choice([1, 7, 63, 64, 65, 1000, 5000]))
    keys = np.sort(rng.integers(0, max(2, n // int(rng.choice([1, 5, 200]))), n)).astype(np.int64)
    voxel_keys, voxel_start = np.unique(keys, return_index=True)
    points = rng.normal(size=(n, 3)).astype(rng.choice([np.float32, np.float64]))
    take = rng.random(n) < rng.choice([0.0, 0.05, 0.5, 1.0])
    out, distinct, start = _grouped(take, points, voxel_keys, np.append(voxel_start, n))
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, points[take])
    expected_keys, first = np.unique(keys[take], return_index=True)
    np.testing.assert_array_equal(distinct, expected_keys)
    np.testing.assert_array_equal(start, np.append(first, take.sum()))
