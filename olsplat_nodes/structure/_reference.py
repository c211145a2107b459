"""Slow, obviously-correct oracle of the region pooling (tests compare the fast path with it)."""

from __future__ import annotations

import numpy as np


def pool_regions_reference(positions, features, camera, depth, label_maps, n_regions, voxel, relative=0.02, voxels=2.0):
    """Per level, per region: the mean feature of the visible points projecting into it (0 if none)."""
    R, t = camera.camera_from_world[:3, :3], camera.camera_from_world[:3, 3]
    members: list[list[list[np.ndarray]]] = [[[] for _ in range(n)] for n in n_regions]
    for k in range(len(positions)):
        x, y, z = R @ positions[k] + t
        if z <= 1e-6:
            continue
        u, v = camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy
        if not (0 <= u < camera.width and 0 <= v < camera.height):
            continue
        row, col = int(v), int(u)
        if depth[row, col] <= 0 or z > depth[row, col] * (1 + relative) + voxels * voxel:
            continue
        for level, labels in enumerate(label_maps):
            if labels[row, col] >= 0:
                members[level][labels[row, col]].append(features[k])
    out = []
    for level in range(len(n_regions)):
        out.append(
            np.array([np.mean(m, axis=0) if m else np.zeros(features.shape[1]) for m in members[level]], np.float32)
        )
    return out
