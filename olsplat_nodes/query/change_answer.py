"""A change query's answer between two flights' maps of one prior map (``olsplat aggregate
--per-flight``): what ``olsplat query --since`` prints and what the query service replies. The
rule is ``query/change.py``'s; here the pair is loaded, checked and asked.

Coordinates are the prior map's (world metres); a heatmap is the later flight's view of
``scene.Camera`` (OpenCV axes), its pixels the change score."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import OlsplatInputError

if TYPE_CHECKING:
    from ..storage import LanguageMap
    from .change import ChangeInstance, ChangeParams


@dataclass
class ChangeAnswer:
    """A change query's outcome."""

    text: str | None  # None: what changed, every change instance
    direction: str  # "appeared" or "gone" (with a text), "changed" (without)
    negatives: list[str]
    scored: int  # Gaussians both flights saw well enough
    candidates: int  # of them, the candidates that were clustered
    instances: list[ChangeInstance]  # ranked
    params: ChangeParams
    heatmap: np.ndarray | None = None  # [H, W] float32 change score, NaN: not scored
    alpha: np.ndarray | None = None  # [H, W]
    scores: np.ndarray | None = None  # [N] float32 change score per Gaussian, NaN: not scored
    moved: np.ndarray | None = None  # [N] bool: moved in the text's direction (with a text), else None

    @property
    def title(self) -> str:
        return "what changed" if self.text is None else f'"{self.text}" {self.direction}'


def check_flight_map(language_map: LanguageMap, where: str, prior_gaussians: int) -> LanguageMap:
    """``language_map`` when it can take part in a change query (the evidence fields of a
    per-flight map, the prior map's Gaussian count); else one error naming ``where``."""
    if not language_map.has_evidence():
        raise OlsplatInputError(
            f"{where}: a map without the evidence a change needs (strength_sum, view_count, "
            "effective_views, view_spread): give a flight's map of olsplat aggregate --per-flight "
            "(OUT/flights/f0/language_map.npz)"
        )
    if len(language_map) != prior_gaussians:
        raise OlsplatInputError(
            f"{where}: a map of {len(language_map):,} Gaussians, the scene's prior map has "
            f"{prior_gaussians:,}: not a map of this prior map"
        )
    return language_map


def flight_ids(flights_dir: Path) -> list[str]:
    """The flights of an aggregate's ``OUT/flights`` folder in flight order (``flights.json``);
    [] when there is no such index."""
    index = Path(flights_dir) / "flights.json"
    if not index.is_file():
        return []
    try:
        return [str(r["flight"]) for r in json.loads(index.read_text(encoding="utf-8"))["flights"]]
    except (ValueError, KeyError, TypeError) as exc:
        raise OlsplatInputError(f"{index}: not a flights index ({exc})") from exc


def answer_change(
    map_a, map_b, gaussians, text: str | None, gone: bool, negatives: list[str] | None, vocabulary, params, camera=None
) -> ChangeAnswer:
    """The change instances from flight a's map to flight b's (``query.change``), with the text's
    direction when ``text`` is given, and with ``camera`` the change heatmap of that view."""
    from ..aggregate.change import change_score
    from .answer import encoder_for_map
    from .change import change_instances, change_negatives, render_change, text_change, text_moves

    if map_a.encoder != map_b.encoder:
        raise OlsplatInputError(f"the flights' maps come from other encoders ({map_a.encoder}, {map_b.encoder})")
    score = change_score(map_a, map_b)
    means = gaussians.means
    moved = None
    if text is None:
        direction, used = "changed", []
        instances = change_instances(means, score, params)
    else:
        direction = "gone" if gone else "appeared"
        encoder = encoder_for_map(map_b)
        used = negatives or change_negatives(text, encoder, vocabulary)
        used = [n for n in used if n != text]
        if not used:
            raise OlsplatInputError("no negatives left once the query itself is removed: give other texts to compare")
        embeddings = encoder.encode_text([text, *used])
        moved = text_moves(map_a, map_b, embeddings, direction)  # type: ignore[arg-type]
        instances = text_change(means, score, map_a, map_b, embeddings, direction, params)  # type: ignore[arg-type]
    with np.errstate(invalid="ignore"):
        candidates = score > params.candidate
    if moved is not None:
        candidates &= moved
    answer = ChangeAnswer(
        text, direction, used, int(np.isfinite(score).sum()), int(candidates.sum()), instances, params
    )
    answer.scores, answer.moved = score, moved
    if camera is not None:
        answer.heatmap, answer.alpha = render_change(gaussians, score, camera, moved)
    return answer
