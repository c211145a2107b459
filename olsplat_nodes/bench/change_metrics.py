"""How change instances score against the simulator's truth, and how sure the figures are.

Definitions (docs/evaluation-protocol.md, "What changed since the last flight"):

- An instance (``query.change.ChangeInstance``, its ``members``: prior-map Gaussian ids) is a
  **true positive** when at least half of its Gaussians belong to one true change
  (``truth/changes/map_changed.npz``'s ``change_id``, -1 unchanged): overlap is counted in the
  map's Gaussians, not in footprint area.
- A true change is **in view** when the later flight's masks (``truth/changes/masks/``) show it
  on at least ``MIN_PIXELS`` pixels over all its views; it is **found** when a true-positive
  instance belongs to it.
- precision = true-positive instances / instances (NaN without instances); recall = changes in
  view found / changes in view (NaN without any); F1 = 2PR / (P + R), 0 when nothing is found.
- **false alarms per km²**: the instances of two flights with no change between them, per km²
  of the town.

Intervals over the held-out seeds: Student's t and a percentile bootstrap over the seeds (both
``evaluate.statistics``); a paired comparison is a win only when both intervals of the per-seed
difference lie on the better side of zero, over at least ``MIN_SEEDS`` paired seeds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

MIN_PIXELS = 50  # a change the later flight shows on fewer pixels (all views together) is not counted
MIN_SEEDS = 3  # paired seeds a verdict needs: two make a percentile bootstrap of two values
OVERLAP = 0.5  # an instance's share of Gaussians in one true change that makes it a true positive


def owner_of(members: np.ndarray, change_id: np.ndarray) -> int:
    """The true change an instance belongs to: the id holding >= ``OVERLAP`` of its Gaussians
    (``members`` [M] map ids; ``change_id`` [N] int, -1 unchanged), else -1."""
    members = np.asarray(members, np.int64)
    if not len(members):
        return -1
    ids = np.asarray(change_id)[members]
    ids = ids[ids >= 0]
    if not len(ids):
        return -1
    counts = np.bincount(ids)
    best = int(np.argmax(counts))  # the lowest id among equal counts
    return best if counts[best] >= OVERLAP * len(members) else -1


def visible_changes(masks: Path, records: int, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """[records] bool: the changes the flight's masks (``masks/<frame>.png``, uint8, k + 1 where
    change k shows) show on at least ``min_pixels`` pixels over all views."""
    import cv2

    from ..errors import SceneFormatError

    pixels = np.zeros(records + 1, np.int64)
    files = sorted(Path(masks).glob("*.png"))
    if not files:
        raise SceneFormatError(masks, "no change masks (*.png): not a flight made with --changes")
    for path in files:
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if mask is None or mask.ndim != 2:
            raise SceneFormatError(path, "not a single-channel change mask")
        pixels += np.bincount(mask.ravel(), minlength=records + 1)[: records + 1]
    return pixels[1:] >= min_pixels


def detections(members: Sequence[np.ndarray], change_id: np.ndarray, visible: np.ndarray) -> dict[str, Any]:
    """Counts and rates of the instances of a changed pair (each instance's member ids; the
    truth's ``change_id`` [N]; ``visible`` [K] bool per change): instances, true_positives,
    changes (in view), found (in view and matched), precision, recall, f1."""
    owners = [owner_of(m, change_id) for m in members]
    matched = {k for k in owners if k >= 0}
    in_view = set(np.flatnonzero(visible).tolist())
    tp, n, changes, found = sum(k >= 0 for k in owners), len(owners), len(in_view), len(matched & in_view)
    precision = tp / n if n else math.nan
    recall = found / changes if changes else math.nan
    f1 = 0.0 if not found or not tp else 2 * precision * recall / (precision + recall)
    return {"instances": n, "true_positives": tp, "changes": changes, "found": found, "owners": owners,
            "precision": precision, "recall": recall, "f1": f1 if changes else math.nan}  # fmt: skip


def per_km2(instances: int, area_m2: float) -> float:
    """Instances per km² of a town of ``area_m2`` square metres."""
    if not area_m2 > 0:
        raise ValueError(f"the town's area must be > 0 m², got {area_m2}")
    return instances / (area_m2 / 1e6)


def summary(values: Sequence[float]) -> dict[str, Any]:
    """Mean and both 95 % intervals of a figure over seeds (NaN seeds left out: a precision
    without instances), and how many seeds it rests on."""
    from ..evaluate.statistics import bootstrap_interval, mean_ci

    x = [float(v) for v in values if not math.isnan(v)]
    if not x:
        return {"mean": math.nan, "t95": None, "bootstrap95": None, "seeds": 0}
    mean, _, interval = mean_ci(x)
    return {"mean": mean, "t95": list(interval) if interval else None,
            "bootstrap95": _list(bootstrap_interval(x)), "seeds": len(x)}  # fmt: skip


def paired(ours: Sequence[float], theirs: Sequence[float], lower_is_better: bool = False) -> dict[str, Any]:
    """Ours − theirs per seed (seeds where either is NaN left out): the mean difference, its t and
    bootstrap 95 % intervals, and the verdict: "win" when both intervals lie on ours' better
    side of zero, "loss" when both lie on the other, "tie" otherwise, "n/a" under ``MIN_SEEDS`` seeds."""
    from ..evaluate.statistics import bootstrap_interval
    from ..evaluate.statistics import paired as t_paired

    pairs = [(a, b) for a, b in zip(ours, theirs, strict=True) if not (math.isnan(a) or math.isnan(b))]
    if not pairs:
        return {"difference": math.nan, "t95": None, "bootstrap95": None, "seeds": 0, "verdict": "n/a"}
    a, b = (list(side) for side in zip(*pairs, strict=True))
    mean, t_interval = t_paired(a, b)
    boot = bootstrap_interval([x - y for x, y in pairs])
    verdict = "n/a"
    if t_interval is not None and boot is not None and len(pairs) >= MIN_SEEDS:
        above = t_interval[0] > 0 and boot[0] > 0
        below = t_interval[1] < 0 and boot[1] < 0
        better, worse = (below, above) if lower_is_better else (above, below)
        verdict = "win" if better else "loss" if worse else "tie"
    return {"difference": mean, "t95": _list(t_interval), "bootstrap95": _list(boot), "seeds": len(pairs),
            "verdict": verdict}  # fmt: skip


def _list(interval: tuple[float, float] | None) -> list[float] | None:
    return list(interval) if interval is not None else None


# --- the tuning rule ---------------------------------------------------------------------------

QUANTILES = (0.95, 0.98, 0.99, 0.995, 0.998, 0.999)  # candidate cut: this quantile of the method's no-change scores
RATIOS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0)  # object cut: candidate cut x this
# an instance's fewest members as ground area at the map's density (ChangeParams.min_area_m2), m²;
# 0: ChangeParams' fixed count alone (the rule before 2026-11-28's amendment)
AREAS = (0.0, 0.5, 1.0, 2.0)


def candidate_cuts(no_change_scores: Sequence[np.ndarray]) -> dict[float, float]:
    """Each of ``QUANTILES`` -> that quantile of a method's per-Gaussian scores over the training
    seeds' no-change pairs (finite scores pooled): cuts in each method's own units. Without any
    finite score (flights too short for the method to compare anything) every cut is infinite:
    no instance."""
    pooled = np.concatenate([np.asarray(s, np.float64)[np.isfinite(s)] for s in no_change_scores])
    return {q: float(np.quantile(pooled, q)) if len(pooled) else math.inf for q in QUANTILES}


def choose(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The protocol's choice among a method's settings scored on the training seeds (each row:
    "alarms", the instances of all their no-change pairs, and "f1", the mean F1 of their changed
    pairs): the fewest alarms (zero when any setting gives none), then the highest F1, then the
    higher cuts (fewer instances), then the larger least size (``min_area_m2``, when rows have one)."""
    if not rows:
        raise ValueError("no setting to choose from")
    return min(rows, key=lambda r: (r["alarms"], -_finite(r["f1"]), -r["candidate"], -r["object_score"],
                                    -r.get("min_area_m2", 0.0)))  # fmt: skip


def _finite(value: float) -> float:
    return value if not math.isnan(value) else -1.0
