"""Spread over scenes: mean, standard deviation and a 95 % confidence interval of a figure, and
of the paired per-scene difference between two methods (Student's t; scenes are the samples);
and a percentile bootstrap interval of a mean over the scenes (``bootstrap_interval``).

A method "wins" against another only when the 95 % interval of the paired difference excludes
zero; with one scene there is no interval, so there is no win either (None).
"""

from __future__ import annotations

import math

import numpy as np

# two-sided 95 % quantiles of Student's t by degrees of freedom (no scipy on the drone)
_T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228,
        11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131, 16: 2.120, 17: 2.110, 18: 2.101, 19: 2.093,
        20: 2.086, 25: 2.060, 30: 2.042, 40: 2.021, 60: 2.000, 120: 1.980}  # fmt: skip


def t95(df: int) -> float:
    """The two-sided 95 % t quantile for ``df`` >= 1 degrees of freedom (the nearest tabulated df
    at or below it; 1.960 beyond 120)."""
    if df < 1:
        raise ValueError(f"need at least one degree of freedom, got {df}")
    if df > 120:
        return 1.960
    return _T95[max(k for k in _T95 if k <= df)]


def mean_ci(values) -> tuple[float, float, tuple[float, float] | None]:
    """(mean, sample standard deviation, 95 % interval of the mean) of ``values``; the spread is
    0 and the interval None for a single value."""
    x = np.asarray(values, np.float64)
    if x.size == 0:
        raise ValueError("no values")
    mean = float(x.mean())
    if x.size == 1:
        return mean, 0.0, None
    std = float(x.std(ddof=1))
    half = t95(x.size - 1) * std / math.sqrt(x.size)
    return mean, std, (mean - half, mean + half)


def paired(ours, theirs) -> tuple[float, tuple[float, float] | None]:
    """(mean, 95 % interval) of the per-scene difference ours - theirs (same scenes, same order)."""
    a, b = np.asarray(ours, np.float64), np.asarray(theirs, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"paired figures need the same scenes, got {a.shape} and {b.shape}")
    mean, _, interval = mean_ci(a - b)
    return mean, interval


def verdict(interval: tuple[float, float] | None) -> str:
    """'win' when the paired interval is above zero, 'loss' below, else 'tie' ('n/a': one scene)."""
    if interval is None:
        return "n/a"
    low, high = interval
    return "win" if low > 0 else "loss" if high < 0 else "tie"


BOOTSTRAP = 10_000  # resamples of the scenes


def bootstrap_interval(values, resamples: int = BOOTSTRAP) -> tuple[float, float] | None:
    """The percentile 95 % interval of the mean of ``values`` under resampling them with
    replacement (generator seeded 0: the same figures every run); None for fewer than two."""
    x = np.asarray(values, np.float64)
    if len(x) < 2:
        return None
    picks = np.random.default_rng(0).integers(0, len(x), (resamples, len(x)))
    means = x[picks].mean(1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(low), float(high)
