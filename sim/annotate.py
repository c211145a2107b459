"""Ground-truth annotations of a rendered view, in the LabelMe polygon format.

From the truth render's Top-K lists, each pixel gets the label holding most of its weight
(unlabelled where less than half the pixel is covered) and, for instance labels, the
instance of its strongest Gaussian of that label. Each (label, instance) region becomes
polygons: outer boundaries, and holes marked ``"flags": {"hole": true}`` (a lawn around a
tree's crown, say). The format is described in sim/README.md; the core's
``olsplat_nodes.evaluate.annotations.read_annotation`` turns a file back into label and instance
maps, whoever wrote it (``rasterize_annotation`` here: with the simulator's labels).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from olsplat_nodes.evaluate.annotations import read_annotation

from .labels import LABELS

MIN_REGION_PX = 12  # smaller specks are not annotated (a person would not draw them)
SIMPLIFY_PX = 0.7  # polygon simplification tolerance (Douglas-Peucker), pixels


def label_maps(
    topk_ids: np.ndarray,  # [H, W, K] int32 Gaussian ids, -1 padded
    topk_weights: np.ndarray,  # [H, W, K] float32
    alpha: np.ndarray,  # [H, W]
    gaussian_label: np.ndarray,  # [N] int label index, -1 for none
    gaussian_instance: np.ndarray,  # [N] int instance id, -1 for stuff
) -> tuple[np.ndarray, np.ndarray]:
    """(labels [H, W] int16, -1 unlabelled; instances [H, W] int32, -1 for stuff/unlabelled)."""
    valid = topk_ids >= 0
    ids = np.where(valid, topk_ids, 0)
    labels_k = np.where(valid, gaussian_label[ids], -1)
    weight_per_label = np.stack([np.where(labels_k == i, topk_weights, 0.0).sum(-1) for i in range(len(LABELS))], -1)
    best = weight_per_label.argmax(-1)
    covered = weight_per_label.max(-1) >= 0.5 * np.maximum(alpha, 1e-6)
    labels = np.where((alpha > 0.5) & covered, best, -1).astype(np.int16)
    # strongest Gaussian (lists are sorted by weight) carrying the pixel's label
    match = labels_k == labels[..., None]
    first = np.argmax(match, axis=-1)
    strongest = np.take_along_axis(ids, first[..., None], -1)[..., 0]
    instances = np.where(match.any(-1) & (labels >= 0), gaussian_instance[strongest], -1).astype(np.int32)
    return labels, instances


def _polygons(mask: np.ndarray) -> list[tuple[list[list[float]], bool]]:
    """[(points, is_hole)] of a binary mask; points are continuous pixel coordinates."""
    contours, hierarchy = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for contour, info in zip(contours, hierarchy[0] if hierarchy is not None else [], strict=True):
        if cv2.contourArea(contour) < MIN_REGION_PX:
            continue
        simple = cv2.approxPolyDP(contour, SIMPLIFY_PX, True)[:, 0, :]
        if len(simple) < 3:
            continue
        # contour points are pixel indices; +0.5 puts them on pixel centres (x + 0.5, y + 0.5)
        out.append(((simple + 0.5).round(2).tolist(), info[3] >= 0))
    return out


def annotate_view(labels: np.ndarray, instances: np.ndarray, image_path: str) -> dict:
    """A LabelMe document for one view's label and instance maps."""
    shapes = []
    for label in np.unique(labels[labels >= 0]):
        in_label = labels == label
        for instance in np.unique(instances[in_label]):
            mask = in_label & (instances == instance)
            for points, hole in _polygons(mask):
                shapes.append(
                    {
                        "label": LABELS[label],
                        "points": points,
                        "group_id": int(instance) if instance >= 0 else None,
                        "shape_type": "polygon",
                        "flags": {"hole": bool(hole)},
                        "description": "",
                    }
                )
    return {
        "version": "5.4.1",
        "flags": {},
        "shapes": shapes,
        "imagePath": image_path,
        "imageData": None,
        "imageHeight": int(labels.shape[0]),
        "imageWidth": int(labels.shape[1]),
    }


def rasterize_annotation(doc: dict | str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(labels [H, W] int16 index into LABELS or -1, instances [H, W] int32) of a LabelMe file
    with the simulator's label vocabulary (the reader itself lives in the core)."""
    return read_annotation(doc, LABELS)
