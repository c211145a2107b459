"""Spread over scenes and paired differences (issue 17, item 3): the arithmetic against values
worked by hand, and a win only where the paired interval excludes zero."""

from __future__ import annotations

import math

import numpy as np
import pytest

from olsplat_nodes.evaluate.statistics import mean_ci, paired, t95, verdict
from olsplat_nodes.evaluate.tables import paper_tables, spread


def test_mean_and_interval_worked_by_hand():
    mean, std, (low, high) = mean_ci([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5 and std == pytest.approx(math.sqrt(5 / 3))
    half = 3.182 * math.sqrt(5 / 3) / 2  # t(0.975, 3 df) * s / sqrt(n)
    assert (low, high) == pytest.approx((2.5 - half, 2.5 + half))
    assert mean_ci([7.0]) == (7.0, 0.0, None)
    assert t95(1) == 12.706 and t95(22) == 2.086 and t95(500) == 1.960
    with pytest.raises(ValueError):
        mean_ci([])


def test_paired_differences_decide_win_tie_loss():
    ours = [70.0, 72.0, 75.0, 71.0, 74.0]
    better = [x - 1.0 + d for x, d in zip(ours, [0.1, -0.1, 0.05, 0.0, -0.05], strict=True)]
    mean, interval = paired(ours, better)
    assert mean == pytest.approx(1.0) and verdict(interval) == "win"
    noisy = [x + d for x, d in zip(ours, [2.0, -2.0, 1.5, -1.5, 0.2], strict=True)]
    assert verdict(paired(ours, noisy)[1]) == "tie"
    assert verdict(paired(better, ours)[1]) == "loss"
    assert verdict(paired([1.0], [0.0])[1]) == "n/a"  # one scene: no interval, no claim


def _scores(v: float) -> dict:
    return {
        **{"mIoU": v, "mAcc": v, "loc40": v, "loc50": v - 5, "loc60": v - 10},
        **{"per_query": {"road": {"IoU": v, "acc": v}}, "seconds": 1.0, "peak_rss_mb": 1.0},
    }


def _results(values: dict[str, list[float]]) -> dict:
    scenes = len(next(iter(values.values())))
    out = {}
    for s in range(scenes):
        out[f"scene{s}"] = {
            name: {
                "mIoU": v[s],
                "mAcc": v[s],
                "loc40": v[s],
                "loc50": v[s] - 5,
                "loc60": v[s] - 10,
                "per_query": {"road": {"IoU": v[s], "acc": v[s]}},
                "seconds": 1.0,
                "peak_rss_mb": 1.0,
            }
            for name, v in values.items()
        }
    return out


def test_spread_and_the_table_mark_a_win_only_when_the_interval_excludes_zero():
    rng = np.random.default_rng(0)
    base = list(70 + rng.normal(0, 2, 5))
    results = _results(
        {
            "outlangsplat": [b + 1.0 + e for b, e in zip(base, rng.normal(0, 0.05, 5), strict=True)],
            "projection": base,
            "vala": [b + 1.0 + e for b, e in zip(base, rng.normal(0, 1.5, 5), strict=True)],
        }
    )
    figures = spread(results)
    assert set(figures["projection"]) >= {"mIoU", "loc50", "mIoU_ci95", "loc50_ci95", "mIoU_std"}
    pairs = figures["outlangsplat"]["paired"]
    assert set(pairs) == {"projection", "vala"}
    assert pairs["projection"]["mIoU_verdict"] == "win" and pairs["vala"]["mIoU_verdict"] == "tie"
    low, high = pairs["projection"]["dmIoU_ci95"]
    assert low < pairs["projection"]["dmIoU"] < high and low > 0
    text = paper_tables(results)
    assert "Over 5 scenes" in text and "(win)" in text and "(tie)" in text
