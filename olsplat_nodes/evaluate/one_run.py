"""One evaluation run: aggregate a scene into a language map and score it on the scene's
annotations, as ``olsplat eval`` and ``olsplat bench tune`` both do (and the run ledger keeps)."""

from __future__ import annotations

import functools
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path


def aggregate_and_score(
    scene, method, encoder, structure=None, out: Path | None = None, label: str | None = None, keep: list | None = None
) -> dict:
    """Aggregate ``scene`` (a ``pipeline.Scene``) with ``method`` (resolved ``MethodParams``),
    ``encoder`` and the 3D branch ``structure`` (None: without) into ``out`` (emptied first;
    None: a temporary folder, removed after), and score the map (``evaluate_map``).

    Returns the scores with ``seconds`` (aggregation), ``score_seconds`` and ``peak_rss_mb``
    (this run's peak: aggregation and scoring). ``label``: show progress bars under that
    name. ``keep``: append the map to it (figures need every method's map at the end;
    otherwise a map goes once scored, so memory does not grow with the number of methods)."""
    if out is None:
        with tempfile.TemporaryDirectory() as tmp:
            return aggregate_and_score(scene, method, encoder, structure, Path(tmp), label, keep)

    from ..memory import peak_rss_mb, reset_peak_rss
    from ..pipeline import aggregate_scene
    from ..storage.snapshot import LanguageMap
    from .scene_eval import evaluate_map

    progress: Callable | None = None
    scoring: Callable | None = None
    if label is not None:
        from tqdm import tqdm

        progress = functools.partial(tqdm, desc=label, unit="view")
        scoring = functools.partial(tqdm, desc=f"{label} scoring")
    shutil.rmtree(out, ignore_errors=True)
    reset_peak_rss()  # each run's own peak, not the process's
    stats = aggregate_scene(scene, method, encoder, out, progress, structure=structure)
    started = time.perf_counter()
    language_map = LanguageMap.load(out / "language_map.npz")
    scores = evaluate_map(scene, language_map, encoder, progress=scoring)
    timing = {"seconds": stats["seconds"], "score_seconds": time.perf_counter() - started, "peak_rss_mb": peak_rss_mb()}
    if keep is not None:
        keep.append(language_map)
    return {**scores, **timing}
