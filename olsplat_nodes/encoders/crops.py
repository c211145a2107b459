"""Region crops as CLIP-style methods make them: the region's box with some context around
it, made square, pixels outside the region faded towards grey, resized to the encoder input.

Fading (not blacking out) keeps a hint of the surroundings, which tells a roof from a
pavement of the same colour, while the region itself dominates the crop.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

GREY = np.array([124, 116, 104], np.float32)  # CLIP's mean pixel: what "nothing" looks like to it


@dataclass(frozen=True)
class CropConfig:
    context: float = 0.25  # box grown by this fraction of its size on every side
    fade: float = 0.7  # outside the region: 0 = untouched, 1 = plain grey
    min_box_px: int = 16  # tiny regions get at least this much image around them


@njit(cache=True)
def _boxes(label_map, n):
    """[n, 4] int64 (y0, y1, x0, x1) bounding box of each region (end exclusive); y0 = -1 if empty."""
    boxes = np.empty((n, 4), np.int64)
    boxes[:, 0] = -1
    for y in range(label_map.shape[0]):
        for x in range(label_map.shape[1]):
            r = label_map[y, x]
            if r < 0:
                continue
            if boxes[r, 0] < 0:
                boxes[r, 0], boxes[r, 1], boxes[r, 2], boxes[r, 3] = y, y + 1, x, x + 1
            else:
                boxes[r, 1] = max(boxes[r, 1], y + 1)
                boxes[r, 2] = min(boxes[r, 2], x)
                boxes[r, 3] = max(boxes[r, 3], x + 1)
    return boxes


@njit(cache=True)
def _faded_box(image, label_map, r, top, left, side, keep, fade, grey):
    """[side, side, 3] float32: the square at (top, left), region r as is, the rest faded
    towards grey (value * keep + grey * fade, float32 as numpy computes it), grey outside."""
    box = np.empty((side, side, 3), np.float32)
    height, width = label_map.shape
    for by in range(side):
        y = top + by
        for bx in range(side):
            x = left + bx
            if y < 0 or y >= height or x < 0 or x >= width:
                for c in range(3):
                    box[by, bx, c] = grey[c]
            elif label_map[y, x] == r:
                for c in range(3):
                    box[by, bx, c] = image[y, x, c]
            else:
                for c in range(3):
                    box[by, bx, c] = keep * np.float32(image[y, x, c]) + fade * grey[c]
    return box


def region_crops(
    image_rgb: np.ndarray, label_map: np.ndarray, size: int, config: CropConfig = CropConfig()
) -> np.ndarray:
    """[H, W, 3] uint8 image, [H, W] int region ids 0..R-1 -> [R, size, size, 3] uint8 crops.

    Region r's crop: its bounding box grown by ``context`` on every side (at least
    ``min_box_px``), made square around the box centre, pixels of other regions faded,
    resized to ``size`` (area averaging when shrinking). ``_reference.region_crops_reference``
    is the same in plain numpy."""
    if image_rgb.shape[:2] != label_map.shape:
        raise ValueError(f"image {image_rgb.shape[:2]} and label map {label_map.shape} differ in size")
    labels = np.ascontiguousarray(label_map, np.int64)
    n = int(labels.max()) + 1
    crops = np.empty((n, size, size, 3), np.uint8)
    boxes = _boxes(labels, n)
    image = np.ascontiguousarray(image_rgb, np.uint8)
    # the scalars as numpy's float32 arithmetic of the reference uses them
    keep, fade = np.float32(1 - config.fade), np.float32(config.fade)
    for r in range(n):
        y0, y1, x0, x1 = (int(v) for v in boxes[r])
        if y0 < 0:
            crops[r] = GREY.astype(np.uint8)
            continue
        side_f = max(y1 - y0, x1 - x0, config.min_box_px) * (1 + 2 * config.context)
        cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
        top, left = int(round(cy - side_f / 2)), int(round(cx - side_f / 2))
        side = int(round(side_f))
        box = _faded_box(image, labels, r, top, left, side, keep, fade, GREY)
        resized = cv2.resize(box, (size, size), interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)
        crops[r] = resized.round().clip(0, 255)
    return crops
