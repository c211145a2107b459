"""How encoders err on a flight, as numbers: per-region accuracy, how two encoders' errors go
together, and whether a surface's errors repeat from view to view.

These statistics decide whether an evaluation world can tell the paper's parts apart: fusing
two encoders helps only where their errors differ (``pair_statistics``), and weighting views or
checking their consistency helps only where a surface is wrong in some views and right in
others (``surface_statistics``). Pure functions over label arrays; ``flight.py`` collects them.

Conventions: labels are ints (index into the scene's label list), ``truth`` is never -1 here
(unlabelled regions are left out before); an "error" is ``predicted != truth``.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np


def region_accuracy(truth: np.ndarray, predicted: np.ndarray) -> float:
    """Share of regions ([R] int each) whose predicted label is the truth; NaN for none."""
    return float(np.mean(truth == predicted)) if len(truth) else float("nan")


def accuracy_by_bins(
    truth: np.ndarray, predicted: np.ndarray, values: np.ndarray, edges: Sequence[float]
) -> dict[str, dict[str, float]]:
    """Accuracy per bin of ``values`` ([R], e.g. the off-nadir angle in degrees): bins are
    ``[edges[i], edges[i+1])``, named ``"lo-hi"``; each gives ``accuracy`` and ``regions``."""
    out = {}
    for lo, hi in itertools.pairwise(edges):
        inside = (values >= lo) & (values < hi)
        out[f"{lo:g}-{hi:g}"] = {
            "accuracy": region_accuracy(truth[inside], predicted[inside]),
            "regions": int(inside.sum()),
        }
    return out


def pair_statistics(truth: np.ndarray, a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """How two encoders' errors go together over the same regions ([R] int each).

    - ``phi``: the correlation of the two error indicators (Pearson on 0/1; 0 when either
      encoder is always right or always wrong, where it is undefined);
    - ``both_wrong``: share of regions both get wrong; ``both_wrong_if_independent``: what it
      would be if their errors were independent at the same rates (the product of the rates);
    - ``same_wrong_label``: among the regions both get wrong, the share where they pick the same
      wrong label (NaN when there is none): fusion cannot repair those.
    """
    wrong_a, wrong_b = truth != a, truth != b
    rate_a, rate_b = float(wrong_a.mean()), float(wrong_b.mean())
    both = wrong_a & wrong_b
    spread = np.sqrt(rate_a * (1 - rate_a) * rate_b * (1 - rate_b))
    phi = float((both.mean() - rate_a * rate_b) / spread) if spread > 0 else 0.0
    return {
        "phi": phi,
        "both_wrong": float(both.mean()),
        "both_wrong_if_independent": rate_a * rate_b,
        "same_wrong_label": float(np.mean(a[both] == b[both])) if both.any() else float("nan"),
    }


def icc_oneway(groups: np.ndarray, values: np.ndarray) -> float:
    """ICC(1), the one-way random-effects intraclass correlation of ``values`` ([M] float) within
    ``groups`` ([M] int ids), for unequal group sizes (Shrout & Fleiss; n0 as in Snedecor's
    unbalanced ANOVA): how much more alike two values of one group are than two values at random.
    Only groups with at least two values count; NaN when fewer than two such groups or no
    variance at all."""
    ids, inverse, sizes = np.unique(groups, return_inverse=True, return_counts=True)
    keep = sizes[inverse] >= 2
    if not keep.any():
        return float("nan")
    ids, inverse, sizes = np.unique(groups[keep], return_inverse=True, return_counts=True)
    y = values[keep].astype(np.float64)
    k, n = len(ids), len(y)
    if k < 2:
        return float("nan")
    means = np.bincount(inverse, weights=y, minlength=k) / sizes
    grand = y.mean()
    ms_between = float(np.sum(sizes * (means - grand) ** 2) / (k - 1))
    ms_within = float(np.sum((y - means[inverse]) ** 2) / (n - k)) if n > k else 0.0
    n0 = (n - np.sum(sizes.astype(np.float64) ** 2) / n) / (k - 1)
    denominator = ms_between + (n0 - 1) * ms_within
    return float((ms_between - ms_within) / denominator) if denominator > 0 else float("nan")


def surface_statistics(surfaces: np.ndarray, errors: np.ndarray) -> dict[str, float]:
    """Whether a surface's errors repeat over the views that see it.

    ``surfaces`` [M] int: the surface of each (surface, view) observation; ``errors`` [M] bool:
    that view's majority label of the surface was wrong. Only surfaces seen in at least two
    views count. ``wrong_every_view``: share of them wrong in every view (no view can outvote
    it: aggregation cannot help); ``wrong_some_views``: wrong in some views but not all (where
    weighting and consistency have work to do); ``error_icc``: ``icc_oneway`` of the errors
    within surfaces (0: errors strike views at random; 1: a surface is wrong everywhere or
    nowhere); ``surfaces``: how many counted; ``error_rate``: share of wrong observations.
    """
    ids, inverse, sizes = np.unique(surfaces, return_inverse=True, return_counts=True)
    wrong = np.bincount(inverse, weights=errors.astype(np.float64), minlength=len(ids))
    seen_twice = sizes >= 2
    every = (wrong == sizes) & seen_twice
    some = (wrong > 0) & (wrong < sizes) & seen_twice
    counted = int(seen_twice.sum())
    return {
        "surfaces": counted,
        "error_rate": float(errors.mean()) if len(errors) else float("nan"),
        "wrong_every_view": float(every.sum() / counted) if counted else float("nan"),
        "wrong_some_views": float(some.sum() / counted) if counted else float("nan"),
        "error_icc": icc_oneway(surfaces, errors.astype(np.float64)),
    }
