"""What changed between two flights over one prior map, as objects: change instances.

A Gaussian's change score (``aggregate.change.change_score``, [N] float32, NaN: not seen well
enough by both flights) is a weak witness on its own: two unchanged flights give single
Gaussians up to ~2.6, real changes a median of 1-2 per Gaussian. An object's change shows in
its Gaussians together, so (``change_instances``):

1. candidates: the Gaussians scoring above ``ChangeParams.candidate``;
2. clusters: the candidates' centres clustered exactly as an ordinary query's chosen Gaussians
   (``localize``'s voxel DBSCAN, radius ``cluster_radius``, ``min_points``);
3. a cluster is a change when its members' median score is above ``ChangeParams.object_score``
   and it has at least ``min_gaussians`` members;
4. ranked by median score x members (a large, clear change first).

A text's change (``text_change``) asks the same of the Gaussians whose verdict on the text
flipped: "appeared", chosen by the ordinary query's rule (the text beats every negative) in the
later flight b and not in the earlier flight a; "gone", the reverse. Only Gaussians both flights
saw well enough carry a score, so only they can flip. The defaults were chosen on training seeds
(docs/method.md, "Maps per flight and what changed").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .localize import Instance3D, _cluster_points, _touching_pairs, _voxelise, default_cluster_radius

Direction = Literal["appeared", "gone"]
DIRECTIONS: tuple[Direction, ...] = ("appeared", "gone")


@dataclass(frozen=True)
class ChangeParams:
    """The cuts and sizes that make change instances out of per-Gaussian change scores."""

    candidate: float = 1.0  # a Gaussian scoring above this is clustered (no-change flights: p99 ~1)
    object_score: float = 1.5  # a cluster is a change when its members' median score is above this
    min_gaussians: int = 10  # ... and it has at least this many members
    cluster_radius: float = 0.0  # DBSCAN radius, metres; 0: the ordinary query's, from the map's density
    min_points: int = 10  # DBSCAN: candidates within the radius (itself included) that make a core point

    def __post_init__(self) -> None:
        if not (self.candidate >= 0.0 and self.object_score >= self.candidate):
            raise ValueError(f"need 0 <= candidate <= object_score, got {self}")
        if self.min_gaussians < 1 or self.min_points < 1 or not self.cluster_radius >= 0.0:
            raise ValueError(f"need min_gaussians >= 1, min_points >= 1 and cluster_radius >= 0, got {self}")

    def radius(self, means: np.ndarray) -> float:
        """The clustering radius in metres for a map with centres ``means`` [N, 3]."""
        return self.cluster_radius or default_cluster_radius(means)


@dataclass
class ChangeInstance(Instance3D):
    """A 3D instance of changed Gaussians (box and centre in map metres, as ``Instance3D``)."""

    score: float = float("nan")  # the members' median change score
    members: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)  # [gaussians] ids

    @property
    def rank_value(self) -> float:
        """What ranks instances, highest first: median score x members."""
        return self.score * self.gaussians


def cluster_labels(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """[M] int64 cluster of each of points [M, 3] (finite, metres) under ``localize``'s voxel
    DBSCAN (radius ``eps``, ``min_points``), -1 for noise: the clusters ``instances_in_3d``
    reports, with their members. The clustering reorders points within their voxels; they are
    matched back by their coordinates (equal points share a neighbourhood, hence a label)."""
    points = np.ascontiguousarray(points, np.float64)
    if len(points) == 0:
        return np.zeros(0, np.int64)
    grouped, keys, start, dims, lowest = _voxelise(points, float(eps))
    first, second = _touching_pairs(keys, dims)
    labels = _cluster_points(grouped, start, first, second, float(eps), int(min_points), lowest)
    out = np.empty(len(points), np.int64)
    out[_by_coordinates(points)] = labels[_by_coordinates(grouped)]
    return out


def _by_coordinates(points: np.ndarray) -> np.ndarray:
    return np.lexsort((points[:, 2], points[:, 1], points[:, 0]))


def change_instances(
    means: np.ndarray, score: np.ndarray, params: ChangeParams = ChangeParams(), among: np.ndarray | None = None
) -> list[ChangeInstance]:
    """The change instances (``ChangeInstance``, ranked by median score x members) of a map with
    centres ``means`` [N, 3] (map metres) and change scores ``score`` [N] (NaN: unknown, never a
    candidate). ``among`` ([N] bool): only these Gaussians may be candidates (``text_change``)."""
    means = np.asarray(means)
    score = np.asarray(score, np.float32)
    if means.ndim != 2 or means.shape[1] != 3 or score.shape != (len(means),):
        raise ValueError(f"need means [N, 3] and score [N], got {means.shape} and {score.shape}")
    with np.errstate(invalid="ignore"):
        candidate = score > params.candidate  # NaN compares False: unknown is never a candidate
    candidate &= np.isfinite(means).all(1)
    if among is not None:
        candidate &= np.asarray(among, bool)
    ids = np.flatnonzero(candidate)
    if len(ids) < params.min_gaussians:
        return []
    labels = cluster_labels(means[ids], params.radius(means), params.min_points)
    found: list[ChangeInstance] = []
    for label in np.unique(labels[labels >= 0]):
        members = ids[labels == label]
        median = float(np.median(score[members]))
        if len(members) < params.min_gaussians or not median > params.object_score:
            continue
        points = means[members].astype(np.float64)
        found.append(
            ChangeInstance(
                _xyz(points.min(0)), _xyz(points.max(0)), _xyz(points.mean(0)), len(members), median, members
            )
        )
    found.sort(key=lambda inst: -inst.rank_value)
    return found


def _xyz(row: np.ndarray) -> tuple[float, float, float]:
    return (float(row[0]), float(row[1]), float(row[2]))


def text_flips(chosen_a: np.ndarray, chosen_b: np.ndarray, direction: Direction = "appeared") -> np.ndarray:
    """[N] bool: the Gaussians whose verdict on a text flipped between flight a and the later
    flight b (each [N] bool, the ordinary query's chosen Gaussians of that flight's map):
    "appeared" chosen in b and not in a, "gone" chosen in a and not in b."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    chosen_a, chosen_b = np.asarray(chosen_a, bool), np.asarray(chosen_b, bool)
    return chosen_b & ~chosen_a if direction == "appeared" else chosen_a & ~chosen_b


def text_change(
    means: np.ndarray,
    score: np.ndarray,
    chosen_a: np.ndarray,
    chosen_b: np.ndarray,
    direction: Direction = "appeared",
    params: ChangeParams = ChangeParams(),
) -> list[ChangeInstance]:
    """The change instances of a text: ``change_instances`` over the Gaussians whose verdict
    flipped in ``direction`` (``text_flips``). means [N, 3] map metres, score [N] change scores,
    chosen_a / chosen_b [N] bool: the text's chosen Gaussians in flight a's and flight b's maps
    (``QueryFeatures.winners`` with the same text and negatives)."""
    return change_instances(means, score, params, among=text_flips(chosen_a, chosen_b, direction))
