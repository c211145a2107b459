"""The obviously-correct region crops (numpy, region by region): the oracle of ``crops.py``."""

from __future__ import annotations

import cv2
import numpy as np

from .crops import GREY, CropConfig


def region_crops_reference(
    image_rgb: np.ndarray, label_map: np.ndarray, size: int, config: CropConfig = CropConfig()
) -> np.ndarray:
    """[H, W, 3] uint8 image, [H, W] int region ids 0..R-1 -> [R, size, size, 3] uint8 crops."""
    if image_rgb.shape[:2] != label_map.shape:
        raise ValueError(f"image {image_rgb.shape[:2]} and label map {label_map.shape} differ in size")
    height, width = label_map.shape
    n = int(label_map.max()) + 1
    crops = np.empty((n, size, size, 3), np.uint8)
    ys, xs = np.indices(label_map.shape)
    flat = label_map.ravel()
    valid = flat >= 0
    # pixels grouped by region: region r owns yy/xx[starts[r]:starts[r + 1]]
    order = np.argsort(flat[valid], kind="stable")
    ids = flat[valid][order]
    yy, xx = ys.ravel()[valid][order], xs.ravel()[valid][order]
    starts = np.searchsorted(ids, np.arange(n + 1))
    image = image_rgb.astype(np.float32)
    for r in range(n):
        sl = slice(starts[r], starts[r + 1])
        if starts[r] == starts[r + 1]:
            crops[r] = GREY.astype(np.uint8)
            continue
        y0, y1, x0, x1 = yy[sl].min(), yy[sl].max() + 1, xx[sl].min(), xx[sl].max() + 1
        side = max(y1 - y0, x1 - x0, config.min_box_px) * (1 + 2 * config.context)
        cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
        top, left = int(round(cy - side / 2)), int(round(cx - side / 2))
        side = int(round(side))
        # pad where the square leaves the image: grey, like faded context
        box = np.empty((side, side, 3), np.float32)
        box[:] = GREY
        sy0, sx0 = max(top, 0), max(left, 0)
        sy1, sx1 = min(top + side, height), min(left + side, width)
        inside = label_map[sy0:sy1, sx0:sx1] == r
        patch = image[sy0:sy1, sx0:sx1]
        patch = np.where(inside[..., None], patch, (1 - config.fade) * patch + config.fade * GREY)
        box[sy0 - top : sy1 - top, sx0 - left : sx1 - left] = patch
        crops[r] = (
            cv2.resize(box, (size, size), interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)
            .round()
            .clip(0, 255)
        )
    return crops
