"""Qualitative figures like the paper's: per view and query, the methods' heatmaps side by side.

One PNG per (view, query): the photo with the annotated target tinted, then one panel per
method: its relevancy for the query over the photo (turbo colours, 0..1), with the method's
predicted mask (the evaluation's argmax rule) outlined in white. Relevancy, not the raw
cosine H_q: with compact encoders every text has a high cosine almost everywhere (roads light
up for "trees"), which hides what the evaluation sees; relevancy is the softmax share of the
query's labels among all the scene's label texts, softmax(RELEVANCY_SCALE * H), per pixel.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..query import argmax_masks, heatmaps, render_feature_map
from ..scene import read_ply
from ..viz import colorize, write_png
from .annotations import read_annotation
from .scene_eval import label_texts, load_queries

RELEVANCY_SCALE = 50.0  # inverse softmax temperature over cosines


def _caption(cv2, panel: np.ndarray, text: str) -> None:
    cv2.putText(panel, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.65, (0, 0, 0), 4, cv2.LINE_AA)
    cv2.putText(panel, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.65, (255, 255, 255), 1, cv2.LINE_AA)


def annotated_views(scene) -> list:
    return [c for c in scene.cameras if (scene.folder / "annotations" / f"{Path(c.name).stem}.json").exists()]


def qualitative_figures(scene, maps: dict, encoder, out: Path, n_views: int = 2) -> list[Path]:
    """Write the figures of ``n_views`` annotated views (first and evenly spread) to ``out``.

    ``maps``: method name -> LanguageMap, all of ``scene``'s map. Returns the files written.
    """
    import cv2

    labels, queries = load_queries(scene.folder)
    gaussians = read_ply(scene.ply)
    label_embeddings = encoder.encode_text(label_texts(labels, queries))
    label_index = {name: i for i, name in enumerate(labels)}
    views = annotated_views(scene)
    views = [views[i] for i in sorted(set(np.linspace(0, len(views) - 1, min(n_views, len(views))).astype(int)))]
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for camera in views:
        photo = scene.image(camera)[..., ::-1].astype(np.float32)  # BGR
        truth, _ = read_annotation(scene.folder / "annotations" / f"{Path(camera.name).stem}.json", labels)
        rendered = {}
        for name, language_map in maps.items():
            feature_map, alpha = render_feature_map(gaussians, language_map.features.astype(np.float32), camera)
            maps_ = heatmaps(feature_map, label_embeddings)  # [L, H, W]
            share = np.exp(RELEVANCY_SCALE * (maps_ - maps_.max(0)))
            rendered[name] = (share / share.sum(0), argmax_masks(maps_, alpha), alpha)
        for query in queries:
            ids = [label_index[n] for n in query["labels"]]
            target = np.isin(truth, ids)
            first = photo.copy()
            first[target] = 0.4 * first[target] + 0.6 * np.array([0, 220, 255])
            first = first.astype(np.uint8)
            _caption(cv2, first, f"annotated: {query['text']}")
            panels = [first]
            for name, (share, winners, alpha) in rendered.items():
                heat = colorize(share[ids].sum(0), alpha > 0.5, 0.0, 1.0).astype(np.float32)
                panel = (0.35 * photo + 0.65 * heat).astype(np.uint8)
                predicted = np.asarray(winners[ids].any(0), np.uint8)
                contours, _ = cv2.findContours(predicted, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
                cv2.drawContours(panel, contours, -1, (255, 255, 255), 1)
                _caption(cv2, panel, name)
                panels.append(panel)
            path = out / f"{Path(camera.name).stem}_{'_'.join(query['text'].split())}.png"
            write_png(path, np.concatenate(panels, axis=1))
            written.append(path)
    return written
