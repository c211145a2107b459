"""``olsplat bench change``: the metrics on hand-built cases (the >= 50 % rule at its edge, a
perfect and an empty detector, masks on disk), the intervals' verdicts, the tuning rule, the
baselines' scores from a real store, and the command end to end on the tiny preset."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from olsplat_nodes.aggregate.observe import ViewObservations
from olsplat_nodes.bench import change_metrics as metrics
from olsplat_nodes.bench.change import Seed, prepare, score_seed, tune
from olsplat_nodes.bench.change_scores import best_view_difference, best_view_features, feature_difference
from olsplat_nodes.cli import main
from olsplat_nodes.evaluate.statistics import bootstrap_interval
from olsplat_nodes.query.change import ChangeParams
from olsplat_nodes.storage.store import ObservationStore

# ten Gaussians: 0-4 belong to change 3, 5-9 to no change
HALF = np.array([3, 3, 3, 3, 3, -1, -1, -1, -1, -1])


def test_an_instance_is_true_at_half_its_gaussians_in_one_change_and_not_below():
    assert metrics.owner_of(np.arange(10), HALF) == 3  # 5 of 10: exactly half counts
    assert metrics.owner_of(np.arange(1, 10), HALF) == -1  # 4 of 9: below half
    assert metrics.owner_of(np.arange(5), HALF) == 3
    split = np.array([1, 1, 2, 2])  # half in each of two changes: the lower id
    assert metrics.owner_of(np.arange(4), split) == 1
    assert metrics.owner_of(np.arange(3), np.array([1, 2, -1])) == -1  # a third each: none
    assert metrics.owner_of(np.zeros(0, np.int64), HALF) == -1


def _truth(n_changes: int = 3, per: int = 20, unchanged: int = 40) -> np.ndarray:
    return np.concatenate([np.repeat(np.arange(n_changes), per), np.full(unchanged, -1)]).astype(np.int32)


def test_a_perfect_detector_scores_one_and_an_empty_one_recall_zero():
    change_id = _truth()
    visible = np.ones(3, bool)
    perfect = metrics.detections([np.flatnonzero(change_id == k) for k in range(3)], change_id, visible)
    assert (perfect["precision"], perfect["recall"], perfect["f1"]) == (1.0, 1.0, 1.0)
    empty = metrics.detections([], change_id, visible)
    assert math.isnan(empty["precision"]) and empty["recall"] == 0.0 and empty["f1"] == 0.0
    # one true instance, one of unchanged Gaussians, a duplicate of the first: 2 of 3 true, 1 of 3 found
    mixed = metrics.detections([np.arange(20), np.arange(60, 80), np.arange(5, 15)], change_id, visible)
    assert mixed["true_positives"] == 2 and mixed["found"] == 1 and mixed["owners"] == [0, -1, 0]
    assert mixed["precision"] == pytest.approx(2 / 3) and mixed["recall"] == pytest.approx(1 / 3)
    assert mixed["f1"] == pytest.approx(2 * (2 / 3) * (1 / 3) / (2 / 3 + 1 / 3))
    # a change the later flight did not show is not asked for: found or not, recall is over the others
    hidden = metrics.detections([np.arange(20)], change_id, np.array([False, True, True]))
    assert hidden["changes"] == 2 and hidden["found"] == 0 and hidden["true_positives"] == 1
    assert hidden["recall"] == 0.0 and hidden["precision"] == 1.0


def test_changes_in_view_come_from_the_mask_files(tmp_path):
    masks = tmp_path / "masks"
    masks.mkdir()
    first = np.zeros((20, 20), np.uint8)
    first[:5, :6] = 1  # change 0: 30 pixels here ...
    first[10:, :] = 3  # change 2: 200 pixels
    second = np.zeros((20, 20), np.uint8)
    second[:4, :5] = 1  # ... and 20 here: 50 in all
    second[19, 19] = 2  # change 1: one pixel
    for name, mask in (("frame_0000.png", first), ("frame_0001.png", second)):
        assert cv2.imwrite(str(masks / name), mask)
    assert metrics.visible_changes(masks, 4).tolist() == [True, False, True, False]
    assert metrics.visible_changes(masks, 4, min_pixels=51).tolist() == [False, False, True, False]
    from olsplat_nodes.errors import SceneFormatError

    with pytest.raises(SceneFormatError, match="no change masks"):
        metrics.visible_changes(tmp_path, 4)


def test_false_alarms_per_km2():
    assert metrics.per_km2(1, 10_000.0) == pytest.approx(100.0)  # the tiny town: 1 instance = 100 per km²
    assert metrics.per_km2(0, 16_900.0) == 0.0
    with pytest.raises(ValueError):
        metrics.per_km2(1, 0.0)


def test_paired_verdicts_need_both_intervals_on_one_side():
    ours, theirs = [0.6, 0.7, 0.65, 0.62, 0.68], [0.3, 0.35, 0.4, 0.33, 0.31]
    win = metrics.paired(ours, theirs)
    assert win["verdict"] == "win" and win["t95"][0] > 0 and win["bootstrap95"][0] > 0
    assert win["difference"] == pytest.approx(np.mean(ours) - np.mean(theirs))
    assert metrics.paired(theirs, ours)["verdict"] == "loss"
    assert metrics.paired([0.5, 0.2, 0.6, 0.1, 0.4], [0.3, 0.4, 0.2, 0.5, 0.3])["verdict"] == "tie"
    fewer_alarms = metrics.paired([0, 0, 0, 100, 0], [300, 400, 200, 500, 300], lower_is_better=True)
    assert fewer_alarms["verdict"] == "win"
    assert metrics.paired([0.5], [0.3])["verdict"] == "n/a"  # one seed: no interval, no claim
    two = metrics.paired([0.6, 0.7], [0.3, 0.31])  # two seeds: intervals, but no verdict
    assert two["verdict"] == "n/a" and two["t95"] is not None and two["seeds"] == 2
    # a seed where either side is undefined (a precision without instances) is left out of the pairs
    assert metrics.paired([0.5, math.nan, 0.6], [0.4, 0.3, math.nan])["seeds"] == 1
    assert bootstrap_interval([1.0, 2.0, 3.0]) == bootstrap_interval([1.0, 2.0, 3.0])
    assert bootstrap_interval([1.0]) is None
    low, high = bootstrap_interval([1.0, 2.0, 3.0, 4.0, 5.0])
    assert 1.0 < low < 3.0 < high < 5.0
    s = metrics.summary([0.5, math.nan, 0.7])
    assert s["seeds"] == 2 and s["mean"] == pytest.approx(0.6) and s["t95"] is not None


def test_the_tuning_rule_puts_no_false_alarm_before_f1():
    rows = [
        {"candidate": 1.0, "object_score": 1.0, "alarms": 1, "f1": 0.9},
        {"candidate": 1.0, "object_score": 2.0, "alarms": 0, "f1": 0.4},
        {"candidate": 2.0, "object_score": 2.0, "alarms": 0, "f1": 0.4},  # a tie on F1: the higher cuts
        {"candidate": 0.5, "object_score": 1.0, "alarms": 0, "f1": 0.3},
    ]
    assert metrics.choose(rows) is rows[2]
    assert metrics.choose(rows[:1])["alarms"] == 1  # none without alarms: the fewest
    cuts = metrics.candidate_cuts([np.array([np.nan, *range(100)], np.float32), np.arange(100, 200.0)])
    assert list(cuts) == list(metrics.QUANTILES) and cuts[0.95] == pytest.approx(np.quantile(np.arange(200.0), 0.95))
    assert set(metrics.candidate_cuts([np.full(5, np.nan)]).values()) == {math.inf}  # nothing compared: no cut


class _Map:
    def __init__(self, features, observed):
        self.features, self.observed = np.asarray(features, np.float32), np.asarray(observed, bool)


def test_the_projection_difference_is_one_minus_cosine_where_both_flights_saw_it():
    a = _Map([[1, 0], [1, 0], [0, 1], [1, 1]], [True, True, True, False])
    b = _Map([[2, 0], [0, 1], [0, -3], [1, 1]], [True, True, True, True])
    score = feature_difference(a, b)
    assert score[:3] == pytest.approx([0.0, 1.0, 2.0]) and math.isnan(score[3])


def _view(gaussians, strength, slots) -> ViewObservations:
    n = len(gaussians)
    offsets = np.arange(n + 1, dtype=np.int64)  # one mixture entry per Gaussian, weight 1
    ids, d = np.asarray(gaussians, np.int32), np.asarray(strength, np.float32)
    return ViewObservations(ids, d, offsets, np.asarray(slots, np.int32), np.ones(n, np.float32))


def test_the_heatmap_difference_takes_each_flights_best_view_from_a_real_store(tmp_path):
    """Two flights of a 4-Gaussian map in one store: each Gaussian takes the feature of the view
    of its flight with the largest d_iv, unaveraged; a Gaussian one flight never saw is NaN."""
    east, north, west = [1, 0, 0], [0, 1, 0], [-1, 0, 0]
    store = ObservationStore(tmp_path / "store", 4, writer=True)
    bank = np.array([east, north, west], np.float16)
    store.append("f0/frame_0000", _view([0, 1, 2], [0.9, 0.2, 0.5], [0, 0, 0]), bank)  # all east
    store.append("f0/frame_0001", _view([0, 1], [0.1, 0.8], [2, 1]), bank)  # 1 seen better: north
    store.append("f1/frame_0000", _view([0, 1, 3], [0.3, 0.3, 1.0], [1, 1, 1]), bank)  # north
    store.append("f1/frame_0001", _view([0], [0.6], [2]), bank)  # 0 seen better: west
    features, strength = best_view_features(tmp_path / "store", 4, "f0")
    assert features.tolist() == [east, north, east, [0, 0, 0]]
    assert strength.tolist() == pytest.approx([0.9, 0.8, 0.5, 0.0])
    score = best_view_difference(tmp_path / "store", 4, "f0", "f1")
    assert score[:2] == pytest.approx([2.0, 0.0])  # east vs west; north vs north
    assert math.isnan(score[2]) and math.isnan(score[3])  # 2 unseen by f1, 3 by f0


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "0,1000"], "--seeds: held-out seeds are < 1000"),
        (["--train-seeds", "1001,999"], "--train-seeds: training seeds are >= 1000"),
        (["--views", "1"], "--views must be >= 2"),
    ],
)
def test_bench_change_refuses_bad_seeds_before_any_work(tmp_path, capsys, argv, message):
    assert main(["bench", "change", "--work", str(tmp_path / "w"), *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "w").exists()


def test_bench_change_end_to_end_on_the_tiny_preset(tmp_path, capsys):
    """Training seed first, its tuning written before the held-out flights exist; every method's
    figures; the same command again reuses every flight and run; the truth as a detector scores
    precision 1 and finds no change between the unchanged flights."""
    work = tmp_path / "work"
    argv = ["bench", "change", "--preset", "tiny", "--seeds", "0", "--train-seeds", "1001", "--views", "3"]
    argv += ["--work", str(work), "--json", str(tmp_path / "c.json"), "--md", str(tmp_path / "c.md")]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert printed.count("  made ") == 6 and printed.count("  aggregated ") == 4
    assert printed.index("cuts chosen on the training seeds") < printed.index(f"made {work / 'tiny0' / 'a'}")
    assert (work / "tune.json").stat().st_mtime <= (work / "tiny0" / "a" / "scene.json").stat().st_mtime
    document = json.loads((tmp_path / "c.json").read_text())
    methods = [
        "ours",
        "projection difference",
        "heatmap difference",
        "ours, default cuts",
        "truth as the score",
        '"new vehicles" appeared (ours)',
        '"new vehicles" appeared (ours, default cuts)',
    ]
    assert list(document["per_seed"]) == methods and document["seeds"] == [0] and document["town_m2"] == 10_000.0
    for method in methods:
        row = document["per_seed"][method]["0"]
        assert row["false_alarms_per_km2"] == 100.0 * row["unchanged_instances"]
        assert row["changes"] >= 10 if "new vehicles" not in method else 1 <= row["changes"] <= 8  # cars arrived
    assert {"candidate", "object_score", "members"} <= set(document["tuned"][methods[5]])
    assert json.loads((work / "tune.json").read_text())["text"]["query"] == "new vehicles"
    assert {(r["baseline"], r["metric"]) for r in document["paired"]} == {
        (b, m) for b in methods[1:3] for m in ("precision", "recall", "f1", "false_alarms_per_km2")
    }
    markdown = (tmp_path / "c.md").read_text()
    assert markdown.startswith("`olsplat bench change --preset tiny --seeds 0 --train-seeds 1001`")
    assert "| heatmap difference | f1 |" in markdown

    assert main(argv[:-4]) == 0  # again, without --json and --md: everything reused
    again = capsys.readouterr().out
    assert "  made " not in again and "  aggregated " not in again

    # the truth as a detector: most instances true (two changes side by side make one instance that
    # neither holds half of), most changes found, nothing between the unchanged flights
    ceiling = document["per_seed"]["truth as the score"]["0"]
    assert ceiling["instances"] >= 10 and ceiling["precision"] >= 0.9 and ceiling["recall"] >= 0.6
    assert ceiling["unchanged_instances"] == 0
    data = prepare(work, "tiny", 3, 0)
    ten = np.where(data.change_id >= 0, 10.0, 0.0).astype(np.float32)  # the same on another scale
    oracle = Seed(data.seed, data.means, data.change_id, data.visible, data.area_m2,
                  {"ours": {"changed": ten, "unchanged": np.zeros_like(ten)}})  # fmt: skip
    row = score_seed(oracle, "ours", ChangeParams(candidate=5.0, object_score=5.0))
    assert {k: row[k] for k in ceiling} == ceiling

    # the tuning clusters once per candidate cut and filters: each setting's figures are those of
    # change_instances with that setting (every fifth setting of ours, checked)
    training = prepare(work, "tiny", 3, 1001)
    rows = tune([training])["ours"]["rows"]
    assert len(rows) == len(metrics.QUANTILES) * len(metrics.RATIOS) * len(metrics.AREAS)
    for r in rows[::5]:
        params = ChangeParams(candidate=r["candidate"], object_score=r["object_score"], min_area_m2=r["min_area_m2"])
        figures = score_seed(training, "ours", params)
        assert (r["alarms"], r["instances"]) == (figures["unchanged_instances"], figures["instances"])
        assert r["f1"] == pytest.approx(figures["f1"], nan_ok=True)

    scene = json.loads((work / "tiny0" / "c" / "scene.json").read_text())
    (work / "tiny0" / "c" / "scene.json").write_text(json.dumps({**scene, "flight_seed": 5}))
    assert main(argv) == 1
    assert "holds another scene than `olsplat sim make --preset tiny --seed 0 --flight-seed 2 --changes none`" in (
        capsys.readouterr().err
    )
