"""The paper's metrics: mIoU, mAcc, Loc@40/50/60, per-query IoU and accuracy.

Per query, pixel counts are summed over all annotated views (unlabelled pixels ignored):
IoU = TP / (TP + FP + FN), accuracy = TP / (TP + FN) (the share of the target found); mIoU and
mAcc average them over queries. Loc@θ: every annotated instance of an instance query in every
view counts once; it is localised when the predicted mask covers more than θ of its annotated
area. Figures are percentages.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

THRESHOLDS = (0.4, 0.5, 0.6)
MIN_INSTANCE_PX = 50  # smaller annotated pieces (slivers behind trees) are not localisation targets


@dataclass
class QueryScore:
    tp: int = 0
    fp: int = 0
    fn: int = 0
    located: dict[float, int] = field(default_factory=lambda: {t: 0 for t in THRESHOLDS})
    instances: int = 0

    def add_view(
        self, predicted: np.ndarray, target: np.ndarray, labelled: np.ndarray, instances: np.ndarray | None
    ) -> None:
        predicted = predicted & labelled
        self.tp += int((predicted & target).sum())
        self.fp += int((predicted & ~target).sum())
        self.fn += int((~predicted & target).sum())
        if instances is None:
            return
        for instance in np.unique(instances[target & (instances >= 0)]):
            area = target & (instances == instance)
            if area.sum() < MIN_INSTANCE_PX:
                continue
            covered = (predicted & area).sum() / area.sum()
            self.instances += 1
            for t in THRESHOLDS:
                self.located[t] += int(covered > t)

    @property
    def iou(self) -> float:
        return 100.0 * self.tp / max(self.tp + self.fp + self.fn, 1)

    @property
    def accuracy(self) -> float:
        return 100.0 * self.tp / max(self.tp + self.fn, 1)


def summarize(scores: dict[str, QueryScore]) -> dict:
    """{"mIoU", "mAcc", "loc40", "loc50", "loc60", "per_query": {text: {"IoU", "acc"}}} in %.

    A query whose target appears in no annotated view (no blue roof in this town, say) has no
    IoU: it is left out of the means and of per_query, and listed under "absent".
    """
    present = {q: s for q, s in scores.items() if s.tp + s.fn > 0}
    out = {
        "mIoU": float(np.mean([s.iou for s in present.values()])) if present else 0.0,
        "mAcc": float(np.mean([s.accuracy for s in present.values()])) if present else 0.0,
        "per_query": {q: {"IoU": s.iou, "acc": s.accuracy} for q, s in present.items()},
        "absent": [q for q in scores if q not in present],
    }
    total = sum(s.instances for s in scores.values())
    for t in THRESHOLDS:
        out[f"loc{int(t * 100)}"] = 100.0 * sum(s.located[t] for s in scores.values()) / max(total, 1)
    out["instances"] = total
    return out
