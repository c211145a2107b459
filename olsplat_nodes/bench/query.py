"""``olsplat bench query``: query latency against a language map.

Two figures, p50/p95 over ``--repeats`` queries (texts cycled from the scene's queries):
- relevance: text -> embedding (the encoders' text towers) -> cosine with every Gaussian's feature;
- heatmap: the same plus rendering the feature map of one view and its cosine heatmap;
- answer: what the query server computes without a view (relevance against the scene's other
  queries as negatives, the Gaussians that pick the query, and their 3D instances);
- preview: a view at the preview's size (``query.service.PREVIEW_MAX_SIDE``) drawn from the
  map's ``PREVIEW_MAX_GAUSSIANS`` most opaque and largest Gaussians, against the same view drawn
  from all of them: the render's milliseconds of each and the IoU of their masks (the query
  against the scene's other queries), over ``--preview-views`` views spread over the flight.
The map's features are converted to float32 once, at load, as the query server does.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("query", help="query latency: relevance for all Gaussians, heatmap of one view")
    parser.add_argument("--map", required=True, type=Path, help="language_map.npz")
    parser.add_argument("--scene", required=True, type=Path, help="a scene folder")
    parser.add_argument("--repeats", type=int, default=100, help="relevance queries timed")
    parser.add_argument("--heatmap-repeats", type=int, default=20, help="heatmap queries timed")
    parser.add_argument("--preview-views", type=int, default=6, help="views the preview is compared on")
    parser.set_defaults(run=run)


def _line(name: str, seconds: list[float]) -> str:
    ms = 1000 * np.asarray(seconds)
    return f"  {name:10s} p50 {np.percentile(ms, 50):7.1f} ms  p95 {np.percentile(ms, 95):7.1f} ms  ({len(ms)} queries)"


def run(args: argparse.Namespace) -> int:
    from ..encoders.spec import encoder_from_spec
    from ..evaluate.scene_eval import load_queries
    from ..pipeline import Scene
    from ..query import heatmaps, render_feature_map
    from ..query.answer import answer_query
    from ..scene import read_ply
    from ..storage.snapshot import LanguageMap

    scene = Scene.open(args.scene)
    language_map = LanguageMap.load(args.map)
    encoder = encoder_from_spec()
    gaussians = read_ply(scene.ply)
    features = language_map.features.astype(np.float32)
    texts = [q["text"] for q in load_queries(scene.folder)[1]]
    camera = scene.cameras[len(scene.cameras) // 2]
    render_feature_map(gaussians, features, camera)  # warm-up
    relevance, heat = [], []
    for i in range(args.repeats):
        t0 = time.perf_counter()
        embedding = encoder.encode_text([texts[i % len(texts)]])
        scores = features @ embedding[0]
        relevance.append(time.perf_counter() - t0)
        assert scores.shape == (len(features),)
    for i in range(args.heatmap_repeats):
        t0 = time.perf_counter()
        embedding = encoder.encode_text([texts[i % len(texts)]])
        feature_map, _ = render_feature_map(gaussians, features, camera)
        heatmaps(feature_map, embedding)
        heat.append(time.perf_counter() - t0)
    language_map.features = features
    answer_query(language_map, gaussians, encoder, texts[0], texts[1:])  # warm-up (numba)
    answers = []
    for i in range(args.repeats):
        text = texts[i % len(texts)]
        t0 = time.perf_counter()
        answer_query(language_map, gaussians, encoder, text, [t for t in texts if t != text])
        answers.append(time.perf_counter() - t0)
    print(
        f"map {args.map}: {len(features):,} Gaussians x {features.shape[1]} dims; view {camera.name} "
        f"{camera.width}x{camera.height}"
    )
    print(_line("relevance", relevance))
    print(_line("heatmap", heat))
    print(_line("answer 3D", answers))
    picked = [scene.cameras[round(k * (len(scene.cameras) - 1) / max(args.preview_views - 1, 1))]
              for k in range(min(args.preview_views, len(scene.cameras)))]  # fmt: skip
    exact, drawn, ious = preview_figures(gaussians, features, encoder.encode_text(texts), picked)
    print(_line("preview, all Gaussians", exact))
    print(_line("preview, decimated", drawn))
    print(f"  preview masks, decimated vs all: IoU {', '.join(f'{x:.2f}' for x in ious)} over {len(picked)} views")
    return 0


def preview_figures(gaussians, features: np.ndarray, texts: np.ndarray, cameras) -> tuple[list, list, list]:
    """(seconds of each view's preview render from all Gaussians, the same from the preview's
    decimated map, IoU of the two masks, 1 when both are empty) per camera; features [N, D], texts [Q, D] unit rows (the
    query first, the negatives after)."""
    from ..query.heatmap import relevancy_mask, render_heatmaps
    from ..query.service import PREVIEW_MAX_GAUSSIANS, PREVIEW_MAX_SIDE
    from ..query.splats import decimate

    ids = decimate(gaussians, PREVIEW_MAX_GAUSSIANS)
    subset, rows = gaussians.subset(ids), features[ids]
    exact: list[float] = []
    drawn: list[float] = []
    ious: list[float] = []
    for camera in cameras:
        side = max(camera.width, camera.height)
        camera = camera.scaled(PREVIEW_MAX_SIDE / side) if side > PREVIEW_MAX_SIDE else camera
        masks = []
        for source, rows_of, seconds in ((gaussians, features, exact), (subset, rows, drawn)):
            render_heatmaps(source, rows_of, texts, camera)  # compiled and culled once, then timed
            t0 = time.perf_counter()
            maps, alpha = render_heatmaps(source, rows_of, texts, camera)
            seconds.append(time.perf_counter() - t0)
            masks.append(relevancy_mask(maps[0], maps[1:], alpha))
        union = (masks[0] | masks[1]).sum()
        ious.append(float((masks[0] & masks[1]).sum() / union) if union else 1.0)  # both empty: they agree
    return exact, drawn, ious
