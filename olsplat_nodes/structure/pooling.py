"""Region-level pooling of 3D structural features (paper eq. region pooling), with visibility.

A point k projects to pixel (u, v) of view v with the ideal pinhole model (pixel centres at
+0.5, as the rasterizer); it counts for the region under that pixel only if it is visible:
in front of the camera and no deeper than the rendered depth there (expected camera z) plus a
tolerance, so points hidden behind a roof or under a crown do not pool into it. The region's
3D feature is the mean over its visible points; a region without any has count 0 (the fusion
then keeps its 2D feature alone).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import Camera


@dataclass(frozen=True)
class Visibility:
    relative: float = 0.02  # allowed depth excess, as a fraction of the rendered depth
    voxels: float = 2.0  # ... plus this many voxels (the point set's own resolution)


def visible_pixels(
    positions: np.ndarray, camera: Camera, depth: np.ndarray, voxel: float, visibility: Visibility = Visibility()
):
    """(point indices [V], rows [V], cols [V]) of the points visible in the view.

    positions [P, 3] world; depth [H, W] rendered expected camera z (0 = nothing rendered);
    voxel: the point set's voxel side (map units).
    """
    cam = positions @ camera.camera_from_world[:3, :3].T + camera.camera_from_world[:3, 3]
    z = cam[:, 2]
    ahead = np.flatnonzero(z > 1e-6)
    u = camera.fx * cam[ahead, 0] / z[ahead] + camera.cx
    v = camera.fy * cam[ahead, 1] / z[ahead] + camera.cy
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    index, rows, cols = ahead[inside], v[inside].astype(np.int64), u[inside].astype(np.int64)
    surface = depth[rows, cols]
    seen = (surface > 0) & (z[index] <= surface * (1.0 + visibility.relative) + visibility.voxels * voxel)
    return index[seen], rows[seen], cols[seen]


def pool_regions(
    features: np.ndarray,  # [P, D] per-point structural features
    visible: tuple[np.ndarray, np.ndarray, np.ndarray],  # from visible_pixels
    label_maps: np.ndarray,  # [L, H, W] region ids, -1 = none
    n_regions: list[int],  # regions per level
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(per level [R_l, D] float32 mean feature of the visible points in each region, per level
    [R_l] int64 point counts)."""
    index, rows, cols = visible
    pooled, counts = [], []
    for labels, n in zip(label_maps, n_regions, strict=True):
        region = labels[rows, cols]
        ok = region >= 0
        count = np.bincount(region[ok], minlength=n)
        total = np.zeros((n, features.shape[1]), np.float64)
        np.add.at(total, region[ok], features[index[ok]])
        pooled.append((total / np.maximum(count, 1)[:, None]).astype(np.float32))
        counts.append(count)
    return pooled, counts
