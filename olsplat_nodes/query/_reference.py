"""Slow, obviously-correct versions of the query maths: the oracles of the fast ones.

Brute force over all pairs of points and breadth-first search over a dict of voxels, straight
from the rule in ``localize.py``'s docstring; use only on small inputs (a few thousand points).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .localize import Instance3D


def winners_reference(table: np.ndarray, embeddings: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """[N] bool, the relevance rule in numpy: argmax over the [rows, Q] products is the query
    (index 0). With ``rows`` ([N], -1 = none) the table is a codebook's centres."""
    wins = (np.asarray(table, np.float64) @ np.asarray(embeddings, np.float64).T).argmax(1) == 0
    return wins if rows is None else np.append(wins, False)[rows]


def _touching(voxel: tuple[int, int, int]):
    """The 26 voxels that share a face, an edge or a corner with ``voxel``."""
    i, j, k = voxel
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                if (di, dj, dk) != (0, 0, 0):
                    yield (i + di, j + dj, k + dk)


def _xyz(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def instances_in_3d_bfs(
    means: np.ndarray, selected: np.ndarray, eps: float = 1.5, min_points: int = 20
) -> list[Instance3D]:
    """``localize.instances_in_3d`` with every distance computed: O(M^2) time, M^2 bits of memory."""
    points = np.asarray(means)[selected].astype(np.float64)  # [M, 3]
    points = points[np.isfinite(points).all(1)]
    if len(points) == 0 or len(points) < min_points:
        return []
    within = np.stack([((points - p) ** 2).sum(1) <= eps * eps for p in points])  # [M, M] bool
    core = within.sum(1) >= min_points  # DBSCAN's test; each point is within eps of itself
    voxel = [(int(i), int(j), int(k)) for i, j, k in np.floor((points - points.min(0)) / eps).astype(np.int64)]
    core_in: dict[tuple[int, int, int], list[int]] = {}  # voxel -> its core points
    for index in np.flatnonzero(core):
        core_in.setdefault(voxel[index], []).append(int(index))

    cluster_of: dict[tuple[int, int, int], tuple[int, int, int]] = {}  # voxel -> its cluster's lowest voxel
    for start in sorted(core_in):
        if start in cluster_of:
            continue
        cluster_of[start] = start
        queue = deque([start])
        while queue:
            here = queue.popleft()
            for there in _touching(here):
                if there in core_in and there not in cluster_of and within[np.ix_(core_in[here], core_in[there])].any():
                    cluster_of[there] = start
                    queue.append(there)

    members: dict[tuple[int, int, int], list[int]] = {}  # cluster -> its points
    for n in range(len(points)):
        if core[n]:
            members.setdefault(cluster_of[voxel[n]], []).append(n)
            continue
        near = {voxel[m] for m in np.flatnonzero(within[n] & core)}  # voxels with a core point within eps
        if near:  # border point: the voxel with the most core points, ties to the lowest voxel
            best = min(near, key=lambda v: (-len(core_in[v]), v))
            members.setdefault(cluster_of[best], []).append(n)

    out = []
    for cluster in sorted(members):
        inside = points[members[cluster]]
        if len(inside) >= max(min_points, 1):
            out.append(
                Instance3D(
                    _xyz(inside.min(0)),
                    _xyz(inside.max(0)),
                    _xyz(inside.mean(0)),
                    len(inside),
                )
            )
    return sorted(out, key=lambda instance: -instance.gaussians)  # stable: ties stay in lowest-voxel order
