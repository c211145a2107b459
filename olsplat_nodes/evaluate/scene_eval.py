"""Score a language map on a scene's annotated views with the scene's queries.

Every annotation label competes through one text: the query that targets exactly that label
(its own wording, e.g. "white buildings"), else the label itself. Each pixel goes to the label
whose rendered heatmap is highest (``argmax_masks``); a query's predicted mask is the union of
its labels' pixels ("buildings" = all four roof colours). Views are rendered at the scene's
SfM cameras, the poses the map was built with.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError
from ..query import argmax_masks
from ..query.answer import QueryFeatures
from ..query.heatmap import render_heatmaps
from ..scene import read_ply
from ..storage.snapshot import LanguageMap
from .annotations import read_annotation
from .metrics import QueryScore, summarize


def load_queries(folder: Path) -> tuple[list[str], list[dict]]:
    path = folder / "queries.json"
    try:
        data = json.loads(path.read_text())
        return list(data["labels"]), list(data["queries"])
    except FileNotFoundError:
        raise OlsplatInputError(f"{path}: missing (the scene's evaluation queries)") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise OlsplatInputError(f"{path}: not a queries file ({type(exc).__name__}: {exc})") from None


def label_texts(labels: list[str], queries: list[dict]) -> list[str]:
    own = {q["labels"][0]: q["text"] for q in queries if len(q["labels"]) == 1}
    return [own.get(label, label) for label in labels]


def evaluate_map(
    scene, language_map: LanguageMap, encoder, views: int | None = None, progress: Callable | None = None
) -> dict:
    """Scores of ``language_map`` (dense or codebook form) on the scene's annotated views (the
    first ``views`` of them, or all). One view at a time, and each view's heatmaps are taken in
    the compositing kernel (``render_heatmaps``): neither the [H, W, D] feature image nor a
    codebook map's [N, D] rows are ever made, so memory does not grow with views or D.
    ``progress`` wraps the list of views (e.g. tqdm: views done and time left)."""
    labels, queries = load_queries(scene.folder)
    gaussians = read_ply(scene.ply)
    if len(language_map) != len(gaussians):
        raise OlsplatInputError(f"the language map has {len(language_map)} Gaussians, the scene's map {len(gaussians)}")
    texts = encoder.encode_text(label_texts(labels, queries))
    scores = {q["text"]: QueryScore() for q in queries}
    label_index = {name: i for i, name in enumerate(labels)}
    cameras = [c for c in scene.cameras if (scene.folder / "annotations" / f"{Path(c.name).stem}.json").exists()][
        :views
    ]
    if not cameras:
        raise OlsplatInputError(f"{scene.folder / 'annotations'}: no annotation for any view of sparse/0")
    features = QueryFeatures.of(language_map)
    for camera in progress(cameras) if progress else cameras:
        truth, instances = read_annotation(scene.folder / "annotations" / f"{Path(camera.name).stem}.json", labels)
        maps, alpha = render_heatmaps(gaussians, features.table, texts, camera, rows=features.rows)
        winners = argmax_masks(maps, alpha)
        labelled = truth >= 0
        for q in queries:
            ids = [label_index[name] for name in q["labels"]]
            predicted = np.asarray(winners[ids].any(0))
            target = np.isin(truth, ids)
            scores[q["text"]].add_view(predicted, target, labelled, instances if q["instances"] else None)
    out = summarize(scores)
    out["views"] = len(cameras)
    return out
