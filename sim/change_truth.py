"""The truth of what changed between flights, for the prior map and for each view.

``mark_map`` says which Gaussians of the prior map (map/point_cloud.ply, made from the unchanged
truth) change appearance in the later flight; ``change_mask`` which pixels of a view show a
change; ``write_changes`` writes truth/changes/ (sim/README.md, "Changes between flights").
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from .change_spec import GROUND_CATEGORIES, ChangedTruth, ChangeRecord, ChangeSpec, inside_polygon
from .layout import Layout


def mark_map(
    changed: ChangedTruth,
    layout: Layout,
    means: np.ndarray,  # [M, 3] prior map Gaussian centres, world metres
    instance: np.ndarray,  # [M] int32 their truth instance (truth/map_labels.npz), -1 stuff
    category: np.ndarray,  # [M] int16 their truth category
) -> np.ndarray:
    """[M] int32 change_id per prior Gaussian, -1 unchanged; the lowest record id wins. A Gaussian
    belongs to record k when (a) it lies inside k's footprint (or, for a moved car, its old
    footprint) in x, y and inside k's z range, or (b) k removes its instance (a removed or moved
    car, a felled tree), or (c) it is a ground Gaussian (category bare ground .. pavement, z below
    0.5 m) on a ground cell whose baked sun shadow k changed by more than 3 %."""
    change = np.full(len(means), -1, np.int32)
    xy, z = means[:, :2].astype(np.float64), means[:, 2].astype(np.float64)
    for rec in changed.records:
        hit = np.zeros(len(means), bool)
        for polygon in (rec.footprint, rec.footprint_before):
            if polygon is not None:
                hit |= inside_polygon(xy, polygon) & (z >= rec.z_range[0]) & (z <= rec.z_range[1])
        if rec.kind in ("car_removed", "car_moved", "tree_felled"):
            hit |= instance == rec.instance
        change[hit & (change < 0)] = rec.id
    ground = np.flatnonzero(np.isin(category, GROUND_CATEGORIES) & (z < 0.5) & (change < 0))
    row, col = layout.cell(xy[ground])
    change[ground] = changed.shadow_owner[row, col]
    return change


def change_mask(
    topk_before: np.ndarray | None,  # [H, W, K] Gaussian ids of the unchanged truth's render, -1 padded
    topk_after: np.ndarray | None,  # [H, W, K] of the changed truth's render at the same camera
    before_ids: np.ndarray,  # [N before] ChangedTruth.before_ids
    after_ids: np.ndarray,  # [N after] ChangedTruth.after_ids
) -> np.ndarray:
    """[H, W] uint8: 0 unchanged, k + 1 where the top Gaussian (the highest weight) after the change
    belongs to record k, else where the top Gaussian before it does."""
    if topk_before is None or topk_after is None:
        raise ValueError("change masks need the renders' top-K ids (rasterize with want_topk=True)")
    top_before, top_after = topk_before[..., 0], topk_after[..., 0]
    before = np.where(top_before >= 0, before_ids[np.maximum(top_before, 0)], -1)
    after = np.where(top_after >= 0, after_ids[np.maximum(top_after, 0)], -1)
    return (np.where(after >= 0, after, before) + 1).astype(np.uint8)


def write_changes(folder: Path, spec: ChangeSpec, records: list[ChangeRecord], map_change: np.ndarray) -> None:
    """truth/changes/changes.json and map_changed.npz (the masks are written frame by frame)."""
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"spec": spec.to_json(), "changes": [r.to_json() for r in records]}
    (folder / "changes.json").write_text(json.dumps(doc, indent=2))
    np.savez_compressed(folder / "map_changed.npz", change_id=map_change.astype(np.int32))


def write_mask(folder: Path, stem: str, mask: np.ndarray) -> None:
    (folder / "masks").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "masks" / f"{stem}.png"), mask)
