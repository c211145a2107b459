"""``olsplat bench regions``: how well and how fast the region proposer cuts a scene's views.

Against the annotations of a simulator (or hand-annotated) scene, per level:
- ASA (achievable segmentation accuracy): label each region with the annotation label most of
  its pixels carry; the fraction of annotated pixels that end up right. 1.0 = no region
  straddles two labels.
- best-IoU recall: the fraction of annotated segments (a label + instance, >= 200 px) that
  some region of the level matches with IoU >= 0.5, and over all levels together.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("regions", help="region quality (ASA, IoU recall) and speed on a scene")
    parser.add_argument("--scene", required=True, type=Path, help="folder with images/ and annotations/")
    parser.add_argument("--every", type=int, default=3, help="use every N-th view (default 3)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import cv2

    from ..errors import OlsplatInputError
    from ..evaluate.annotations import read_annotation
    from ..evaluate.scene_eval import load_queries
    from ..regions import RegionConfig, propose_regions

    files = sorted((args.scene / "annotations").glob("*.json"))[:: args.every]
    if not files:
        raise OlsplatInputError(f"{args.scene / 'annotations'}: no annotation files")
    names, _ = load_queries(args.scene)
    config = RegionConfig()
    n = len(config.level_counts)
    asa: list[list[float]] = [[] for _ in range(n)]  # per level, per view
    counts: list[list[int]] = [[] for _ in range(n)]
    best_iou: list[list[float]] = []
    seconds: list[float] = []
    for path in files:
        doc = json.loads(path.read_text())
        photo = (path.parent / doc["imagePath"]).resolve()
        bgr = cv2.imread(str(photo))
        if bgr is None:
            raise OlsplatInputError(f"{path}: its image {photo} is missing or unreadable")
        image = bgr[..., ::-1].copy()
        labels, instances = read_annotation(doc, names)
        start = time.perf_counter()
        levels = propose_regions(image, config)
        seconds.append(time.perf_counter() - start)
        valid = labels >= 0
        segment = np.where(valid, labels.astype(np.int64) * 100_003 + instances + 1, -1)
        for level, regions in enumerate(levels.label_maps):
            table = np.zeros((regions.max() + 1, labels.max() + 1))
            np.add.at(table, (regions[valid], labels[valid]), 1)
            asa[level].append(float(table.max(1).sum() / max(valid.sum(), 1)))
            counts[level].append(int(regions.max()) + 1)
        sizes = [np.bincount(r.ravel()) for r in levels.label_maps]
        for key in np.unique(segment[valid]):
            mask = segment == key
            if mask.sum() < 200:
                continue
            ious = []
            for regions, size in zip(levels.label_maps, sizes, strict=True):
                ids, overlap = np.unique(regions[mask], return_counts=True)
                ious.append(float((overlap / (size[ids] + mask.sum() - overlap)).max()))
            best_iou.append(ious)
    best = np.array(best_iou)
    h, w = image.shape[:2]
    print(f"{len(files)} views of {args.scene} ({w}x{h}), {len(best)} annotated segments of >= 200 px")
    print(f"{'level':>5} {'regions':>8} {'ASA':>6} {'IoU>=0.5':>9}")
    for level in range(len(asa)):
        print(
            f"{level:>5} {np.mean(counts[level]):>8.0f} {np.mean(asa[level]):>6.3f} "
            f"{np.mean(best[:, level] >= 0.5):>9.3f}"
        )
    print(f"{'any':>5} {'':>8} {'':>6} {np.mean(best.max(1) >= 0.5):>9.3f}")
    print(f"seconds per view: {np.median(seconds):.2f} (median)")
    return 0
