"""A text change query against the simulator's truth: does "new vehicles" find the cars that
arrived between two flights, and stay silent when nothing changed?

The query is the one an operator types, ``olsplat query --map f1 --since f0 "new vehicles"``:
``query.change.text_change`` with the default negatives of ``query.change.change_negatives``.
Its truth (``arrival_truth``) is narrower than the change instances': only the cars added or
moved in, and of them only the Gaussians under the car's new footprint. A cluster on a moved
car's old place (the road it left) is a change, but not a new vehicle, so it counts false.

The text's cuts are tuned on the training seeds by the rule of ``change_metrics.choose`` over
``GRID`` (docs/evaluation-protocol.md, "A text change query"); only ours has a text rule, so no
baseline is scored here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from . import change_metrics as metrics

TEXT = "new vehicles"
ARRIVALS = ("car_added", "car_moved")  # the changes "new vehicles" names: a car where there was none
# the text's settings tried on the training seeds: candidate cut, object cut = candidate x ratio,
# members; larger members first so that, at equal figures, the choice takes the stricter one
CANDIDATES = (0.4, 0.6, 0.8)
RATIOS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
MEMBERS = (32, 16, 8)
GRID = tuple((c, c * r, m) for m in MEMBERS for c in CANDIDATES for r in RATIOS)


@dataclass
class TextTruth:
    """One seed's text query: the moved Gaussians of each pair and the arrivals' truth."""

    moved: dict[str, np.ndarray]  # "changed" (a -> b) / "unchanged" (a -> c) -> [N] bool, moved towards TEXT
    arrival_id: np.ndarray  # [N] int32 the arrival record under whose new footprint a Gaussian lies, -1 none
    visible: np.ndarray  # [K] bool: arrivals flight b shows (the change masks), False for other records


def arrival_truth(means: np.ndarray, change_id: np.ndarray, records: list[dict]) -> np.ndarray:
    """[N] int32: the record id of an added or moved car (``ARRIVALS``) when Gaussian i (centre
    ``means`` [N, 3], map metres) is one of its changed Gaussians (``change_id``) and lies inside
    its new footprint in x, y; -1 elsewhere (its old place included)."""
    from olsplat_sim.change_spec import inside_polygon

    out = np.full(len(means), -1, np.int32)
    xy = np.asarray(means, np.float64)[:, :2]
    for record in records:
        if record["kind"] in ARRIVALS:
            mine = np.flatnonzero(change_id == record["id"])
            out[mine[inside_polygon(xy[mine], record["footprint"])]] = record["id"]
    return out


def text_truth(maps: dict[str, Any], means: np.ndarray, change_id: np.ndarray, records, visible) -> TextTruth:
    """The seed's moves towards ``TEXT`` (``maps``: flight "f0", "f1", "f2" -> its per-flight
    ``LanguageMap`` of ours) and the arrivals' truth."""
    from ..query.answer import encoder_for_map
    from ..query.change import change_negatives, text_moves

    encoder = encoder_for_map(maps["f1"])
    embeddings = np.asarray(encoder.encode_text([TEXT, *change_negatives(TEXT, encoder)]), np.float32)
    moved = {"changed": text_moves(maps["f0"], maps["f1"], embeddings, "appeared"),
             "unchanged": text_moves(maps["f0"], maps["f2"], embeddings, "appeared")}  # fmt: skip
    arrivals = np.array([r["kind"] in ARRIVALS for r in records], bool)
    return TextTruth(moved, arrival_truth(means, change_id, records), np.asarray(visible, bool) & arrivals)


def score_text(means: np.ndarray, scores: dict[str, np.ndarray], truth: TextTruth, params) -> dict[str, Any]:
    """The text query's figures on one seed with ``params`` (``ChangeParams``): ours' change
    scores ``scores`` ("changed", "unchanged" -> [N]) restricted to the moved Gaussians, as
    ``query.change.text_change`` does, matched against the arrivals."""
    from ..query.change import change_instances

    found = change_instances(means, scores["changed"], params, among=truth.moved["changed"])
    alarms = change_instances(means, scores["unchanged"], params, among=truth.moved["unchanged"])
    row = metrics.detections([inst.members for inst in found], truth.arrival_id, truth.visible)
    row["unchanged_instances"] = len(alarms)
    return row


def params_of(candidate: float, object_score: float, members: int):
    from ..query.change import ChangeParams

    # the text's size rule is the member count alone (its grid's third axis), not ChangeParams' area
    return ChangeParams(candidate=candidate, object_score=object_score, min_gaussians=members, min_area_m2=0.0)


def tune_text(train: list[tuple[np.ndarray, dict[str, np.ndarray], TextTruth]]) -> dict[str, Any]:
    """The text's cuts by ``change_metrics.choose`` over ``GRID`` on the training seeds (each:
    means, ours' scores, its ``TextTruth``): {"rows": [...], "chosen": row}."""
    rows = []
    for candidate, object_score, members in GRID:
        figures = [score_text(m, s, t, params_of(candidate, object_score, members)) for m, s, t in train]
        f1 = [f["f1"] for f in figures if f["f1"] == f["f1"]]
        rows.append({"candidate": candidate, "object_score": object_score, "members": members,
                     "alarms": sum(f["unchanged_instances"] for f in figures),
                     "f1": sum(f1) / len(f1) if f1 else float("nan"),
                     "instances": sum(f["instances"] for f in figures)})  # fmt: skip
    return {"rows": rows, "chosen": metrics.choose(rows)}
