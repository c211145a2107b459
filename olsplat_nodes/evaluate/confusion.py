"""Look-alike feature errors for the robustness stress test (``olsplat bench robustness --mode
lookalike``): errors shaped like a real encoder's, correlated across the views that see the
same piece of the world.

What a confused region gets. The scene's encoder is measured on the scene's annotations: for
every annotated region of the finest level, its true label (the annotation's majority, as the
diagnostics take it: ``diagnose.flight.region_truth``) against its predicted label (the nearest
label text to its feature). The off-diagonal of those counts, each row normalised, gives
P(read as k | true t), the encoder's own look-alikes (``lookalike_rows``). A confused region
takes the feature of a random region of the same view and level whose true label is the drawn
look-alike k: a real feature of the thing it is mistaken for, seen under the same light and
camera. When the view has no such region it takes the mean feature of the flight's regions of
label k at that level (``Lookalikes.prototypes``, unit length), and when the flight has none
either, k's text embedding (the only stand-in left; it reads as k more cleanly than any image
feature would).

Where the errors fall. The decision "this piece of the world is confused, and as what" is made
per surface, as the diagnostics define surfaces: an annotated instance, or one stuff label
within one 8 m x 8 m cell of the ground plane (``diagnose.flight.surface_ids``). Each region
follows the surface most of its pixels belong to. Every surface has one world draw (confused
with probability ``p``, and its look-alike label); each view that sees it follows that draw with
probability ``rho`` and otherwise makes its own draw of the same kind. So every observation is
confused with probability ``p`` whatever ``rho``; two views' decisions agree on the world draw
with probability ``rho``^2 (the correlation of their confusion indicators is ``rho``^2):
``rho`` = 1 is the same confusion in every view, ``rho`` = 0 independent views. Regions with no
annotated surface (unlabelled ground, or most pixels outside the annotation) are never
confused: the confusion matrix says nothing about them.

Randomness is keyed, not streamed: every draw is a hash of (seed, what is drawn, surface or
region, view) (``keyed_uniforms``, splitmix64), so it does not depend on the order of views or
methods, every method aggregates the same corrupted features, and a higher ``p`` confuses a
superset of what a lower one confuses.

Pure functions over arrays; the bench (``bench/robustness.py``) reads the scene and calls them.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..scene import Camera
from .diagnose.flight import _INSTANCE_BASE, ground_cells, pixel_rays, region_truth, surface_ids

# streams of keyed_uniforms: one per kind of draw, so no two draws share a hash
_FOLLOW, _CONFUSE, _LABEL, _DONOR = 1, 2, 3, 4
_WORLD = 0  # the view key of a surface's world draw (views are keyed index + 1)


@dataclass(frozen=True)
class LevelTruth:
    """What the annotation says about the regions of one level of one view, one row each."""

    truth: np.ndarray  # [R] int: the region's majority true label, -1 when impure or unlabelled
    surface: np.ndarray  # [R] int64: the surface most of its pixels belong to, -1 for none
    surface_label: np.ndarray  # [R] int: that surface's true label, -1 for none


@dataclass(frozen=True)
class Lookalikes:
    """The scene encoder's look-alikes and the stand-in features for a confused region."""

    counts: np.ndarray  # [K, K] int64: regions of true label t (row) predicted as k (column)
    rows: np.ndarray  # [K, K] float64: P(read as k | true t), zero diagonal, rows sum to 1
    prototypes: np.ndarray  # [L, K, D] float32: unit mean feature of true-k regions per level
    has_prototype: np.ndarray  # [L, K] bool: the level has any region of true label k
    texts: np.ndarray  # [K, D] float32: unit text embedding of each label


def keyed_uniforms(*keys) -> np.ndarray:
    """Uniforms in [0, 1), one per element of the broadcast integer ``keys`` (each an int or an
    int array; non-negative): splitmix64 of the keys folded in turn, the top 53 bits. The same
    keys give the same number in any order of calls."""
    arrays = np.broadcast_arrays(*[np.atleast_1d(np.asarray(k, np.int64)) for k in keys])
    h = np.zeros(arrays[0].shape, np.uint64)
    with np.errstate(over="ignore"):
        for key in arrays:
            h = h ^ key.astype(np.uint64)
            h = h + np.uint64(0x9E3779B97F4A7C15)
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(11)).astype(np.float64) * 2.0**-53


def draw_labels(rows: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """[N] int: label drawn from each distribution ``rows`` ([N, K], non-negative, each with
    some mass) by its uniform ([N] in [0, 1)), by the inverse of the cumulative distribution;
    a label of zero mass is never drawn."""
    cdf = np.cumsum(rows, axis=1)
    cdf = cdf / cdf[:, -1:]
    cdf[:, -1] = 1.0
    return (cdf <= uniforms[:, None]).sum(1)


def confusion_counts(truth: np.ndarray, predicted: np.ndarray, n_labels: int) -> np.ndarray:
    """[K, K] int64 counts of (true label, predicted label) over regions ([R] int each, >= 0)."""
    counts = np.zeros((n_labels, n_labels), np.int64)
    np.add.at(counts, (truth, predicted), 1)
    return counts


def lookalike_rows(counts: np.ndarray) -> np.ndarray:
    """[K, K] P(read as k | true t) from confusion ``counts`` ([K, K], K >= 2): the off-diagonal,
    each row normalised. A label the encoder never gets wrong falls back to "a random region of
    another label": the other labels weighted by how many regions have them (uniform when
    there are none at all)."""
    k = len(counts)
    if k < 2:
        raise ValueError(f"look-alikes need at least two labels, got {k}")
    off = counts.astype(np.float64) * (1 - np.eye(k))
    regions = np.broadcast_to(counts.sum(1).astype(np.float64), (k, k)) * (1 - np.eye(k))
    uniform = 1 - np.eye(k)
    rows = np.where(off.sum(1, keepdims=True) > 0, off, np.where(regions.sum(1, keepdims=True) > 0, regions, uniform))
    return rows / rows.sum(1, keepdims=True)


def region_majority(region_map: np.ndarray, values: np.ndarray, regions: int) -> np.ndarray:
    """[regions] the most frequent of ``values`` ([H, W] int, -1 counts as a value too) over
    each region's pixels of ``region_map`` ([H, W] ids, -1 outside any); ties go to the smaller
    value; -1 for a region with no pixel."""
    inside = region_map >= 0
    pairs, sizes = np.unique(
        np.stack([region_map[inside].astype(np.int64), values[inside].astype(np.int64)]), axis=1, return_counts=True
    )
    order = np.lexsort((pairs[1], -sizes, pairs[0]))  # by region, then most pixels, then smaller value
    region, value = pairs[0][order], pairs[1][order]
    first = np.ones(len(region), bool)
    first[1:] = region[1:] != region[:-1]
    out = np.full(regions, -1, np.int64)
    out[region[first]] = value[first]
    return out


def measure_view(
    label_maps: np.ndarray,
    rows_per_level: Sequence[int],
    truth_labels: np.ndarray,
    instances: np.ndarray,
    camera: Camera,
    n_labels: int,
    *,
    cell_m: float = 8.0,
    min_purity: float = 0.5,
) -> list[LevelTruth]:
    """``LevelTruth`` of each level of one view: ``label_maps`` [L, H, W] region ids with
    ``rows_per_level[l]`` regions (the bank's rows), the view's annotation (``truth_labels``
    [H, W] label or -1, ``instances`` [H, W] instance or -1, as ``read_annotation`` gives), its
    camera (for the ground cells, ``cell_m`` metres), and regions kept as labelled when their
    majority label covers ``min_purity`` of them."""
    ids = surface_ids(truth_labels, instances, ground_cells(camera, pixel_rays(camera), cell_m))
    out = []
    for region_map, regions in zip(label_maps, rows_per_level, strict=True):
        truth = np.full(regions, -1, np.int64)
        measured = region_truth(region_map, truth_labels, n_labels, min_purity)[:regions]
        truth[: len(measured)] = measured
        surface = region_majority(region_map, ids, regions)
        out.append(LevelTruth(truth, surface, np.where(surface >= 0, surface // _INSTANCE_BASE - 1, -1)))
    return out


def measure_lookalikes(
    views: Iterable[tuple[Sequence[np.ndarray], Sequence[LevelTruth]]], texts: np.ndarray
) -> Lookalikes:
    """``Lookalikes`` from the annotated views, each (bank: per level [R, D] unit features, its
    ``LevelTruth`` per level), and the label texts' embeddings ``texts`` [K, D]. The confusion
    is counted on the finest (last) level, the regions the diagnostics count."""
    texts = np.asarray(texts, np.float32)
    texts = texts / np.maximum(np.linalg.norm(texts, axis=1, keepdims=True), 1e-12)
    k = len(texts)
    counts = np.zeros((k, k), np.int64)
    sums: np.ndarray | None = None
    for bank, levels in views:
        if sums is None:
            sums = np.zeros((len(bank), k, bank[0].shape[1]), np.float64)
        labelled = levels[-1].truth >= 0
        predicted = np.argmax(bank[-1][labelled] @ texts.T, axis=1)
        counts += confusion_counts(levels[-1].truth[labelled], predicted, k)
        for level, (features, truth) in enumerate(zip(bank, levels, strict=True)):
            keep = truth.truth >= 0
            np.add.at(sums[level], truth.truth[keep], features[keep])
    if sums is None:
        raise ValueError("look-alikes need at least one annotated view")
    norms = np.linalg.norm(sums, axis=2, keepdims=True)
    has = norms[..., 0] > 0
    prototypes = np.where(has[..., None], sums / np.maximum(norms, 1e-12), 0.0).astype(np.float32)
    return Lookalikes(counts, lookalike_rows(counts), prototypes, has, texts)


def confuse_lookalike(
    bank: Sequence[np.ndarray],
    levels: Sequence[LevelTruth],
    view: int,
    looks: Lookalikes,
    p: float,
    rho: float,
    seed: int,
) -> list[np.ndarray]:
    """The view's bank (per level [R, D]) with look-alike errors (module docstring): view index
    ``view`` (>= 0), confusion probability ``p`` per (surface, view), correlation ``rho`` across
    views, ``seed`` >= 0. Donors are taken from the uncorrupted bank; the input is not changed."""
    out = []
    key_view = view + 1
    for level, (features, truth) in enumerate(zip(bank, levels, strict=True)):
        if len(truth.surface) != len(features):
            raise ValueError(f"level {level}: {len(features)} feature rows but {len(truth.surface)} regions")
        confused = features.copy()
        regions = np.flatnonzero(truth.surface >= 0)
        surfaces, labels = truth.surface[regions], truth.surface_label[regions]
        follows = keyed_uniforms(seed, _FOLLOW, surfaces, key_view) < rho
        keys = np.where(follows, _WORLD, key_view)
        hit = keyed_uniforms(seed, _CONFUSE, surfaces, keys) < p
        regions, surfaces, labels, keys = regions[hit], surfaces[hit], labels[hit], keys[hit]
        lookalike = draw_labels(looks.rows[labels], keyed_uniforms(seed, _LABEL, surfaces, keys))
        # donors: regions of this level and view whose true label is the look-alike
        order = np.argsort(truth.truth, kind="stable")
        start = np.searchsorted(truth.truth[order], lookalike, side="left")
        count = np.searchsorted(truth.truth[order], lookalike, side="right") - start
        pick = (keyed_uniforms(seed, _DONOR, key_view, level, regions) * count).astype(np.int64)
        in_view = count > 0
        confused[regions[in_view]] = features[order[start[in_view] + pick[in_view]]]
        flight = ~in_view & looks.has_prototype[level, lookalike]
        confused[regions[flight]] = looks.prototypes[level, lookalike[flight]]
        text = ~in_view & ~flight
        confused[regions[text]] = looks.texts[lookalike[text]]
        out.append(confused)
    return out


def _confuse_lookalike_reference(
    bank: Sequence[np.ndarray],
    levels: Sequence[LevelTruth],
    view: int,
    looks: Lookalikes,
    p: float,
    rho: float,
    seed: int,
) -> list[np.ndarray]:
    """``confuse_lookalike`` with plain loops, one region at a time: the test oracle."""

    def u(*keys) -> float:
        return float(keyed_uniforms(*keys)[0])

    out = []
    for level in range(len(bank)):
        features, truth = bank[level], levels[level]
        confused = features.copy()
        for r in range(len(features)):
            surface = int(truth.surface[r])
            if surface < 0:
                continue
            key = _WORLD if u(seed, _FOLLOW, surface, view + 1) < rho else view + 1
            if not u(seed, _CONFUSE, surface, key) < p:
                continue
            row = looks.rows[int(truth.surface_label[r])]
            draw, total, lookalike = u(seed, _LABEL, surface, key) * row.sum(), 0.0, len(row) - 1
            for k in range(len(row)):
                total += row[k]
                if row[k] > 0 and draw < total:
                    lookalike = k
                    break
            donors = [j for j in range(len(features)) if truth.truth[j] == lookalike]
            if donors:
                confused[r] = features[donors[int(u(seed, _DONOR, view + 1, level, r) * len(donors))]]
            elif looks.has_prototype[level, lookalike]:
                confused[r] = looks.prototypes[level, lookalike]
            else:
                confused[r] = looks.texts[lookalike]
        out.append(confused)
    return out
