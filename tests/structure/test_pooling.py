"""Region pooling of structural features against the brute-force reference, and visibility
with the real rasterizer's depth."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.raster import rasterize
from olsplat_nodes.scene import Camera, Gaussians, intrinsics, look_at
from olsplat_nodes.structure._reference import pool_regions_reference
from olsplat_nodes.structure.pooling import pool_regions, visible_pixels


def test_pooling_matches_the_reference():
    rng = np.random.default_rng(0)
    camera = Camera("c", 64, 48, intrinsics(50.0, 55.0, 31.0, 25.0), look_at([1.0, -2.0, 10.0], [0.0, 0.0, 0.0]))
    positions = rng.uniform([-5, -5, -1], [5, 5, 2], (3000, 3))
    features = rng.normal(size=(3000, 5))
    depth = rng.uniform(8.0, 12.0, (48, 64))
    depth[:5] = 0.0  # nothing rendered there
    label_maps = np.stack([rng.integers(-1, 4, (48, 64)), rng.integers(0, 30, (48, 64))])
    visible = visible_pixels(positions, camera, depth, voxel=0.1)
    assert 0 < len(visible[0]) < len(positions)  # some points are hidden or outside
    pooled, counts = pool_regions(features, visible, label_maps, [4, 30])
    reference = pool_regions_reference(positions, features, camera, depth, label_maps, [4, 30], voxel=0.1)
    for fast, slow, count in zip(pooled, reference, counts, strict=True):
        np.testing.assert_allclose(fast, slow, atol=1e-5)
        assert (count > 0).sum() == np.abs(slow).sum(1).astype(bool).sum()


def test_points_under_a_roof_do_not_pool_into_it():
    # an opaque "roof" square 5 m above a ground square, seen from 30 m straight above
    xs, ys = np.meshgrid(np.linspace(-4, 4, 33), np.linspace(-4, 4, 33))
    roof = np.c_[xs.ravel() * 0.5, ys.ravel() * 0.5, np.full(xs.size, 5.0)]
    ground = np.c_[xs.ravel() * 2, ys.ravel() * 2, np.zeros(xs.size)]
    means = np.concatenate([roof, ground])
    n = len(means)
    gaussians = Gaussians(
        means,
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.log(np.tile([0.3, 0.3, 0.02], (n, 1))),
        np.full(n, 6.0),
        np.zeros((n, 1, 3)),
    )
    camera = Camera(
        "top", 80, 80, intrinsics(100.0, 100.0, 40.0, 40.0), look_at([0.0, 0.0, 30.0], [0.0, 0.0, 0.0], (0.0, 1.0, 0.0))
    )
    depth = rasterize(gaussians, camera, want_topk=False).depth
    under = np.c_[np.zeros(4), np.linspace(-1, 1, 4), np.zeros(4)]  # ground points below the roof
    on_roof = np.c_[np.zeros(4), np.linspace(-1, 1, 4), np.full(4, 5.0)]
    points = np.concatenate([under, on_roof])
    index, _, _ = visible_pixels(points, camera, depth, voxel=0.25)
    assert set(index.tolist()) == {4, 5, 6, 7}
