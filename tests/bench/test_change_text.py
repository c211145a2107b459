"""The text change query's truth and scoring in ``olsplat bench change`` (bench/change_text.py)."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.bench.change_text import GRID, TextTruth, arrival_truth, score_text, tune_text

SQUARE = [[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]]


def _records():
    moved = {"id": 0, "kind": "car_moved", "footprint": SQUARE}
    felled = {"id": 1, "kind": "tree_felled", "footprint": [[10.0, 0.0], [14.0, 0.0], [14.0, 4.0], [10.0, 4.0]]}
    added = {"id": 2, "kind": "car_added", "footprint": [[30.0, 40.0], [34.0, 40.0], [34.0, 42.0], [30.0, 42.0]]}
    return [moved, felled, added]


def test_an_arrival_is_the_cars_new_place_not_its_old_one_nor_another_kind():
    means = np.array([[1, 1, 0], [30, 30, 0], [12, 2, 5], [32, 41, 0.5], [32, 41, 0]], np.float64)
    change_id = np.array([0, 0, 1, 2, -1], np.int32)  # the moved car's new and old place, a tree, a car, nothing
    assert arrival_truth(means, change_id, _records()).tolist() == [0, -1, -1, 2, -1]


def _town(rng):
    """Two arrived cars of 40 Gaussians each in a field of 2,000 unchanged ones."""
    field = np.c_[rng.uniform(-50, 50, (2000, 2)), np.zeros(2000)]
    car0 = np.c_[rng.uniform(0.2, 3.8, 40), rng.uniform(0.2, 1.8, 40), np.zeros(40)]
    car2 = np.c_[rng.uniform(30.2, 33.8, 40), rng.uniform(40.2, 41.8, 40), np.zeros(40)]
    means = np.r_[field, car0, car2]
    near = [((means[:, 0] > x0 - 1) & (means[:, 0] < x0 + 5) & (means[:, 1] > y0 - 1) & (means[:, 1] < y0 + 3))
            for x0, y0 in ((0, 0), (30, 40))]  # fmt: skip
    means = means[~(near[0] | near[1]) | (np.arange(len(means)) >= 2000)]
    change_id = np.full(len(means), -1, np.int32)
    change_id[-80:-40], change_id[-40:] = 0, 2
    return means, change_id


def test_a_detector_that_knows_the_arrivals_finds_both_and_nothing_else():
    means, change_id = _town(np.random.default_rng(0))
    arrival = arrival_truth(means, change_id, _records())
    truth = TextTruth({"changed": arrival >= 0, "unchanged": np.zeros(len(means), bool)}, arrival,
                      np.array([True, False, True]))  # fmt: skip
    scores = {"changed": np.where(arrival >= 0, 3.0, 0.1).astype(np.float32),
              "unchanged": np.full(len(means), 0.1, np.float32)}  # fmt: skip
    from olsplat_nodes.bench.change_text import params_of

    row = score_text(means, scores, truth, params_of(0.4, 1.0, 8))
    assert (row["instances"], row["true_positives"], row["changes"], row["found"]) == (2, 2, 2, 2)
    assert row["unchanged_instances"] == 0 and row["f1"] == 1.0
    # a move without a score is nothing; a score without a move is nothing
    none = TextTruth({"changed": np.zeros(len(means), bool), "unchanged": np.zeros(len(means), bool)}, arrival,
                     truth.visible)  # fmt: skip
    assert score_text(means, scores, none, params_of(0.4, 1.0, 8))["instances"] == 0
    # the tuning takes a setting without alarms; at equal figures the strictest members count
    tuned = tune_text([(means, scores, truth)])
    assert tuned["chosen"]["alarms"] == 0 and tuned["chosen"]["f1"] == 1.0 and tuned["chosen"]["members"] == 32
    assert len(tuned["rows"]) == len(GRID)


def test_the_text_rule_counts_members_and_asks_no_area():
    """The text's size rule is its member count alone (its tuning grid's third axis and the
    shipped TEXT_PARAMS): the least area of "what changed" must not raise it on a dense map."""
    from olsplat_nodes.bench.change_text import params_of
    from olsplat_nodes.query.change import TEXT_PARAMS

    dense = np.random.default_rng(0).uniform(0, 10, (10_000, 3))  # 100 Gaussians per m²
    assert params_of(0.8, 1.6, 8).min_members(dense) == 8
    assert TEXT_PARAMS.min_members(dense) == TEXT_PARAMS.min_gaussians == 32
