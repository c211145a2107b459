"""Region-level zero-shot accuracy of encoders on held-out simulator views.

Regions of views of evaluation seeds (never used for training) that mostly carry one label
are embedded; each is classified by the nearest query text among one query per label (the
evaluation queries' own wording: "white buildings", "trees", ...). Reported: accuracy over
regions, balanced accuracy (mean over labels), and per-label accuracy.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from olsplat_nodes.encoders import CropConfig, FusedEncoder

from .labels import LABELS, QUERIES
from .region_samples import TRAINING_SEED_BASE, collect


def label_queries() -> list[str]:
    """One query text per label, in LABELS order: the evaluation query targeting just that label."""
    by_label = {labels[0]: text for text, labels, _ in QUERIES if len(labels) == 1}
    return [by_label.get(label, label) for label in LABELS]


def evaluate(encoders: Mapping[str, Any], seeds: list[int], views: int) -> dict[str, Any]:
    """name -> {"accuracy", "balanced", "per_label" [L], "n"} for each encoder (or FusedEncoder)."""
    if any(seed >= TRAINING_SEED_BASE for seed in seeds):
        raise ValueError(f"evaluation seeds must be below {TRAINING_SEED_BASE} (the training seeds), got {seeds}")
    styles: dict[str, Any] = {}
    for encoder in encoders.values():
        for m in encoder.encoders if isinstance(encoder, FusedEncoder) else [encoder]:
            style = (m.input_size, getattr(m, "crop_config", None) or CropConfig())
            if styles.setdefault(m.name, style) != style:  # the crops are collected per encoder name
                raise ValueError(f"two encoders named {m.name!r} crop their regions differently: rename one")
    samples = collect(seeds, views, styles)
    texts = label_queries()
    results: dict[str, Any] = {}
    for name, encoder in encoders.items():
        if isinstance(encoder, FusedEncoder):
            images = encoder.encode_crops([samples.crops[m.name] for m in encoder.encoders])
        else:
            images = encoder.encode_images(samples.crops[encoder.name])
        predicted = (images @ encoder.encode_text(texts).T).argmax(1)
        right = predicted == samples.labels
        per_label = np.array(
            [right[samples.labels == i].mean() if (samples.labels == i).any() else np.nan for i in range(len(LABELS))]
        )
        results[name] = {
            "accuracy": float(right.mean()),
            "balanced": float(np.nanmean(per_label)),
            "per_label": per_label,
            "n": len(right),
        }
    results["_counts"] = np.bincount(samples.labels, minlength=len(LABELS))
    return results
