"""Slow, obviously-correct versions of the query maths: the oracles of the fast ones.

Plain Python over dicts and sets, straight from the rule in ``localize.py``'s docstring; use only
on small inputs (thousands of points).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from .localize import Instance3D


def _touching(voxel: tuple[int, int, int]):
    """The 26 voxels that share a face, an edge or a corner with ``voxel``."""
    i, j, k = voxel
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                if (di, dj, dk) != (0, 0, 0):
                    yield (i + di, j + dj, k + dk)


def instances_in_3d_bfs(means: np.ndarray, selected: np.ndarray, eps: float = 1.5, min_points: int = 20) -> list[Instance3D]:
    """``localize.instances_in_3d`` by breadth-first search over a dict of voxels."""
    points = np.asarray(means)[selected].astype(np.float64)  # [M, 3]
    if len(points) == 0 or len(points) < min_points:
        return []
    lowest = points.min(0)
    members: dict[tuple[int, int, int], list[int]] = {}  # voxel (i, j, k) -> point indices
    for n, cell in enumerate(np.floor((points - lowest) / eps).astype(np.int64)):
        members.setdefault((int(cell[0]), int(cell[1]), int(cell[2])), []).append(n)
    need = max(1, math.ceil(min_points / (4.0 * math.pi / 3.0)))
    dense = {voxel for voxel, inside in members.items() if len(inside) >= need}

    cluster_of: dict[tuple[int, int, int], tuple[int, int, int]] = {}  # voxel -> its cluster's lowest voxel
    for start in sorted(dense):
        if start in cluster_of:
            continue
        cluster_of[start] = start
        queue = deque([start])
        while queue:
            for other in _touching(queue.popleft()):
                if other in dense and other not in cluster_of:
                    cluster_of[other] = start
                    queue.append(other)
    for voxel in members:
        if voxel in dense:
            continue
        neighbours = [other for other in _touching(voxel) if other in dense]
        if neighbours:  # border: the most populated dense neighbour, ties to the lowest voxel
            best = min(neighbours, key=lambda other: (-len(members[other]), other))
            cluster_of[voxel] = cluster_of[best]

    points_of: dict[tuple[int, int, int], list[int]] = {}
    for voxel, cluster in cluster_of.items():
        points_of.setdefault(cluster, []).extend(members[voxel])
    out = []
    for cluster in sorted(points_of):
        inside = points[points_of[cluster]]
        dense_points = sum(len(members[voxel]) for voxel in dense if cluster_of[voxel] == cluster)
        if dense_points >= min_points:
            out.append(Instance3D(tuple(map(float, inside.min(0))), tuple(map(float, inside.max(0))), tuple(map(float, inside.mean(0))), len(inside)))
    return sorted(out, key=lambda instance: -instance.gaussians)  # stable: ties stay in lowest-voxel order
