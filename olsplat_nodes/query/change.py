"""What changed between two flights over one prior map, as objects: change instances.

A Gaussian's change score (``aggregate.change.change_score``, [N] float32, NaN: not seen well
enough by both flights) is a weak witness on its own: two unchanged flights give single
Gaussians up to ~2.6, real changes a median of 1-2 per Gaussian. An object's change shows in
its Gaussians together, so (``change_instances``):

1. candidates: the Gaussians scoring above ``ChangeParams.candidate``;
2. clusters: the candidates' centres clustered exactly as an ordinary query's chosen Gaussians
   (``localize``'s voxel DBSCAN, radius ``cluster_radius``, ``min_points``);
3. a cluster is a change when its members' median score is above ``ChangeParams.object_score``
   and it is large enough: at least ``min_gaussians`` members and at least ``min_area_m2`` of
   ground's worth of them at the map's density (``ChangeParams.min_members``; a count alone is a
   different size on every map: 10 Gaussians are ~4 m² of the tiny preset's map, 0.4 m² of the
   small one's);
4. ranked by median score x members (a large, clear change first).

A text's change (``text_change``) asks the same of the Gaussians whose feature moved towards
the text: the ordinary query's rule (the text beats every negative) applied to the move F_b - F_a
instead of to F ("appeared": the cosine with the text rose, and rose more than with every
negative; "gone": it fell most). Why the move and not the two verdicts: over a prior map that
does not hold the new object, a later flight paints a new car onto the old ground's Gaussians
between ground and car, and on the tiny preset they seldom pick "cars" outright (0-2 of an added
car's 12-19 scored Gaussians) while 77-95 % of them moved towards "cars" more than towards
anything else named. Only Gaussians both flights saw well enough carry a score, so only they
count. The defaults were chosen on training seeds
(docs/method.md, "Maps per flight and what changed").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Literal

import numpy as np

from ..aggregate.change import FlightFeatures, feature_rows
from .heatmap import CANONICAL_NEGATIVES
from .localize import Instance3D, _cluster_points, _touching_pairs, _voxelise, ground_density, radius_for_density
from .negatives import AERIAL_VOCABULARY, vocabulary_negatives

_ROWS = 32_768  # Gaussians per chunk of ``text_moves``: [rows, D] float32 differences, a few MB

Direction = Literal["appeared", "gone"]
DIRECTIONS: tuple[Direction, ...] = ("appeared", "gone")


@dataclass(frozen=True)
class ChangeParams:
    """The cuts and sizes that make change instances out of per-Gaussian change scores."""

    # the defaults: ours' choice by `olsplat bench change --preset small` on training seeds 1001-1003
    # (60-view flights over ~390,000 Gaussians; docs/evaluation-protocol.md, the amendment of 2026-11-28)
    candidate: float = 1.654  # a Gaussian scoring above this is clustered (the no-change pairs' 99.9th percentile)
    object_score: float = 2.48  # a cluster is a change when its members' median score is above this
    min_gaussians: int = 10  # ... and it has at least this many members
    cluster_radius: float = 0.0  # DBSCAN radius, metres; 0: the ordinary query's, from the map's density
    min_points: int = 5  # DBSCAN: candidates within the radius (itself included) that make a core point
    min_area_m2: float = 2.0  # ... and at least this much ground's worth of Gaussians (``min_members``)

    def __post_init__(self) -> None:
        if not (self.candidate >= 0.0 and self.object_score >= self.candidate):
            raise ValueError(f"need 0 <= candidate <= object_score, got {self}")
        if self.min_gaussians < 1 or self.min_points < 1 or not self.cluster_radius >= 0.0:
            raise ValueError(f"need min_gaussians >= 1, min_points >= 1 and cluster_radius >= 0, got {self}")
        if not (0.0 <= self.min_area_m2 < math.inf):
            raise ValueError(f"need a finite min_area_m2 >= 0 (square metres), got {self.min_area_m2}")

    def with_cuts(self, text: str) -> ChangeParams:
        """These params with the cuts of ``text`` = "C,O,N[,A]" (candidate cut, object cut, fewest
        Gaussians, least ground area in m², 0 when left out: the given values are the whole size
        rule), as ``olsplat query --change-cuts`` and the query server's ``change_cuts`` take
        them. ValueError naming the text and the expected form."""
        parts = [p.strip() for p in text.split(",")]
        try:
            if len(parts) not in (3, 4):
                raise ValueError("three or four values")
            values = {"candidate": float(parts[0]), "object_score": float(parts[1]), "min_gaussians": int(parts[2]),
                      "min_area_m2": float(parts[3]) if len(parts) == 4 else 0.0}  # fmt: skip
            return ChangeParams(**{**asdict(self), **values})
        except ValueError:
            raise ValueError(
                f"{text}: expected CANDIDATE,OBJECT,GAUSSIANS[,AREA_M2] with 0 <= candidate <= object, an integer "
                ">= 1 and an area >= 0, e.g. 0.8,1.6,32 or 1.4,1.8,10,0"
            ) from None

    def min_members(self, means: np.ndarray) -> int:
        """The fewest members a change instance of a map with centres ``means`` [N, 3] may have:
        ``min_gaussians``, or ``min_area_m2`` times the map's Gaussians per m² of ground
        (``localize.ground_density``) rounded up, whichever is more."""
        return self.for_map(means).min_gaussians

    def for_map(self, means: np.ndarray) -> ChangeParams:
        """These params resolved for a map with centres ``means`` [N, 3] (map metres): the
        clustering radius (``cluster_radius`` or the ordinary query's, ``localize.
        default_cluster_radius``) and the least area as a member count (``min_gaussians`` becomes
        the larger of itself and ``min_area_m2`` x the ground density, rounded up; the area 0).
        The density is computed once, and not at all when nothing needs it; resolving twice changes
        nothing. A query server resolves its rule once for its prior map, not per request."""
        if self.cluster_radius > 0 and self.min_area_m2 == 0:
            return self
        return self.for_density(ground_density(np.asarray(means)))

    def for_density(self, density: float) -> ChangeParams:
        """``for_map`` of a map with ``density`` Gaussians per m² of ground (``ground_density``)."""
        by_area = math.ceil(self.min_area_m2 * density) if self.min_area_m2 > 0 else 0
        return replace(
            self,
            cluster_radius=self.cluster_radius or radius_for_density(density),
            min_gaussians=max(self.min_gaussians, by_area),
            min_area_m2=0.0,
        )


@dataclass
class ChangeInstance(Instance3D):
    """A 3D instance of changed Gaussians (box and centre in map metres, as ``Instance3D``)."""

    score: float = float("nan")  # the members' median change score
    members: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)  # [gaussians] ids

    @property
    def rank_value(self) -> float:
        """What ranks instances, highest first: median score x members."""
        return self.score * self.gaussians


# a text's changes: a move towards the text is evidence too, so its candidates may score lower.
# Chosen by `olsplat bench change --preset small` on training seeds 1001-1003 (its tune.json;
# docs/evaluation-protocol.md, "A text change query"): 60-view flights over 390,678 Gaussians; its
# size rule is the count alone (the least area came later, for "what changed" only)
TEXT_PARAMS = ChangeParams(candidate=0.8, object_score=1.6, min_gaussians=32, min_area_m2=0.0)


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
    rule = params.for_map(means)
    clusters = change_clusters(means, score, rule.candidate, rule.cluster_radius, rule.min_points, among,
                               rule.min_gaussians)  # fmt: skip
    return changes_among(means, clusters, rule.object_score, rule.min_gaussians)


def change_clusters(
    means: np.ndarray,
    score: np.ndarray,
    candidate: float,
    radius: float,
    min_points: int,
    among: np.ndarray | None = None,
    fewest: int = 1,
) -> list[tuple[np.ndarray, float]]:
    """Steps 1-2 of ``change_instances``: the clusters (DBSCAN ``radius`` metres, ``min_points``)
    of the Gaussians scoring above ``candidate`` (and in ``among`` when given), each as (member
    ids [M] int64, the members' median score). None when fewer than ``fewest`` Gaussians are
    candidates (no cluster could be kept). means [N, 3] map metres, score [N] (NaN: unknown)."""
    means = np.asarray(means)
    score = np.asarray(score, np.float32)
    if means.ndim != 2 or means.shape[1] != 3 or score.shape != (len(means),):
        raise ValueError(f"need means [N, 3] and score [N], got {means.shape} and {score.shape}")
    with np.errstate(invalid="ignore"):
        chosen = score > candidate  # NaN compares False: unknown is never a candidate
    chosen &= np.isfinite(means).all(1)
    if among is not None:
        chosen &= np.asarray(among, bool)
    ids = np.flatnonzero(chosen)
    if len(ids) < fewest:
        return []
    labels = cluster_labels(means[ids], radius, min_points)
    clusters = []
    for label in np.unique(labels[labels >= 0]):
        members = ids[labels == label]
        clusters.append((members, float(np.median(score[members]))))
    return clusters


def changes_among(
    means: np.ndarray, clusters: Sequence[tuple[np.ndarray, float]], object_score: float, fewest: int
) -> list[ChangeInstance]:
    """Steps 3-4 of ``change_instances``: the clusters (``change_clusters``) whose median score
    is above ``object_score`` and that have at least ``fewest`` members, as instances ranked by
    median score x members."""
    found: list[ChangeInstance] = []
    for members, median in clusters:
        if len(members) < fewest or not median > object_score:
            continue
        points = np.asarray(means)[members].astype(np.float64)
        found.append(
            ChangeInstance(
                _xyz(points.min(0)), _xyz(points.max(0)), _xyz(points.mean(0)), len(members), median, members
            )
        )
    found.sort(key=lambda inst: -inst.rank_value)
    return found


def _xyz(row: np.ndarray) -> tuple[float, float, float]:
    return (float(row[0]), float(row[1]), float(row[2]))


def text_moves(
    map_a: FlightFeatures, map_b: FlightFeatures, embeddings: np.ndarray, direction: Direction = "appeared"
) -> np.ndarray:
    """[N] bool: the Gaussians whose feature moved towards the text between flight a and the
    later flight b, by the ordinary query's rule applied to the move: with embeddings [Q, D]
    (unit rows, the text first, then its negatives), "appeared" where the cosine with the text
    rose (F_b - F_a) . e_0 > 0 and rose more than with every negative, "gone" where it fell and
    fell more than with every negative. Unobserved rows (zero) never move."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    n = len(map_a.observed)
    if len(map_b.observed) != n:
        raise ValueError(f"maps of {n} and {len(map_b.observed)} Gaussians: not two flights of one prior map")
    texts = np.asarray(embeddings, np.float32).T  # [D, Q]
    sign = np.float32(1.0 if direction == "appeared" else -1.0)
    moved = np.zeros(n, bool)
    both = np.asarray(map_a.observed, bool) & np.asarray(map_b.observed, bool)
    for lo in range(0, n, _ROWS):
        hi = min(n, lo + _ROWS)
        rise = sign * (
            (feature_rows(map_b, lo, hi, np.float32) - feature_rows(map_a, lo, hi, np.float32)) @ texts
        )  # [rows, Q]
        moved[lo:hi] = (rise[:, 0] > 0) & (rise.argmax(1) == 0) & both[lo:hi]
    return moved


def text_change(
    means: np.ndarray,
    score: np.ndarray,
    map_a: FlightFeatures,
    map_b: FlightFeatures,
    embeddings: np.ndarray,
    direction: Direction = "appeared",
    params: ChangeParams = TEXT_PARAMS,
) -> list[ChangeInstance]:
    """The change instances of a text: ``change_instances`` over the Gaussians whose feature
    moved towards it (``text_moves``, ``direction``). means [N, 3] map metres, score [N] change
    scores of a to b, map_a / map_b the two flights' language maps, embeddings [Q, D] unit rows
    of the text and its negatives (as the ordinary query's)."""
    return change_instances(means, score, params, among=text_moves(map_a, map_b, embeddings, direction))


STANDS_FOR = 0.5  # a named class this close to a text that is not itself one is what the text names


def change_negatives(
    text: str, encoder, vocabulary: Sequence[str] = AERIAL_VOCABULARY, stands_for: float = STANDS_FOR
) -> list[str]:
    """The texts a change query's move must beat when the operator names none: the ordinary
    query's (``negatives.vocabulary_negatives``), less the entry nearest to ``text`` when the text
    is not itself an entry and their cosine is >= ``stands_for``: that entry is what the text
    names ("new vehicles" stands for "cars", cosine 0.56 with the shipped encoder, below the
    ordinary query's 0.9 near-duplicate cut), and a move towards a car must not have to favour
    the words "new vehicles" over "cars" to count."""
    negatives = vocabulary_negatives(text, encoder, vocabulary)
    if text.strip().lower() in {v.strip().lower() for v in vocabulary} or negatives == list(CANONICAL_NEGATIVES):
        return negatives
    embeddings = np.asarray(encoder.encode_text([text.strip(), *negatives]), np.float32)
    cosines = embeddings[1:] @ embeddings[0]
    nearest = int(np.argmax(cosines))
    if cosines[nearest] >= stands_for and len(negatives) > 1:
        del negatives[nearest]
    return negatives


def render_change(
    gaussians, score: np.ndarray, camera, among: np.ndarray | None = None, min_known: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """A view's change heatmap, rendered as a query's heatmap is (the rasterizer's
    alpha-blending weights w): per pixel, the weighted mean change score of the scored Gaussians
    it shows, sum w s / sum w over those with a finite score ([H, W] float32, NaN where less than
    ``min_known`` of the pixel's weight comes from scored Gaussians); with ``among`` ([N] bool,
    a text's moved Gaussians) the others count as score 0. Returns (heatmap, alpha [H, W])."""
    from .heatmap import render_feature_map

    known = np.isfinite(score)
    values = np.where(known, score, 0.0)
    if among is not None:
        values = np.where(np.asarray(among, bool), values, 0.0)
    columns = np.stack([values, known.astype(np.float64)], 1).astype(np.float32)  # [N, 2]
    image, alpha = render_feature_map(gaussians, columns, camera)  # [H, W, 2]: each sum w x / (sum w + eps)
    share = image[..., 1]  # the share of the pixel's weight from scored Gaussians
    with np.errstate(invalid="ignore", divide="ignore"):
        heat = np.where(share >= min_known, image[..., 0] / share, np.nan)
    heat[alpha < 1e-6] = np.nan
    return heat.astype(np.float32), alpha
