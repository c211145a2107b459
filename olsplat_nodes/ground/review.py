"""What the ground page shows, read from a run folder: the prior map, the views aggregated so
far, the newest language map, and the answers to the operator's queries (computed here by the
query server's own ``query.service.MapService``). A finished run gives a post-flight review; a
run folder a graph is still writing gives a live page on the machine that holds it.

Nothing here touches a socket or the browser (``page`` draws what this returns).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError
from ..query.geojson import GeoInstance, dumps_geojson, feature_collection, locate
from ..query.localize import Instance3D
from ..query.negatives import AERIAL_VOCABULARY
from ..query.service import MAX_NEGATIVES, MAX_TEXT_CHARS, MapService, MapState, text_problem
from ..query.splats import BrowserSplats
from ..scene import Camera

DEFAULT_NEGATIVES = AERIAL_VOCABULARY  # as the query server's (the page shows them; the operator may edit)


def query_text_problem(text: str, negatives: list[str]) -> str | None:
    """Why the page cannot ask this query (one sentence for the operator), or None: the query
    server's limits (``query.service.text_problem``), and no control characters."""
    problem = text_problem(text, negatives, MAX_TEXT_CHARS, MAX_NEGATIVES, control=True)
    if problem is None:
        return None
    subject = "the query" if problem.subject == "query" else "a negative"
    if problem.kind == "empty":
        return "the query is empty: type what to look for, e.g. red roof buildings"
    if problem.kind == "long":
        return f"{subject} is {problem.size:,} characters long; at most {problem.limit}"
    if problem.kind == "control":
        return f"{subject} contains control characters; type plain text"
    return f"{problem.size} negatives; at most {problem.limit}"


def prepared_query(text: str, negatives: list[str]) -> tuple[str, list[str], str | None]:
    """(text stripped, negatives without the text itself (the aerial vocabulary without it when
    none is left), the reason the page cannot ask it or None): what both page sources ask."""
    text = text.strip()
    negatives = [n for n in negatives if n.lower() != text.lower()]
    negatives = negatives or [n for n in DEFAULT_NEGATIVES if n.lower() != text.lower()]
    return text, negatives, query_text_problem(text, negatives)


def split_negatives(text: str) -> list[str]:
    """The negatives box's comma-separated texts, empty ones dropped."""
    return [n.strip() for n in text.split(",") if n.strip()]


def view_pictures(photo, heatmap, valid, mask, boxes, text: str, view: str, version: int):
    """(heatmap picture, mask picture) as [H', W, 3] uint8 RGB: the pictures ``olsplat ground
    query --out`` writes, for the page (photo [H, W, 3] RGB, heatmap [H, W] cosine, valid and
    mask [H, W] bool, boxes (x0, y0, x1, y1) end exclusive)."""
    from ..viz import query_pictures

    caption = f'"{text}" on {Path(view).name}, map v{version}; mask: beats every negative'
    heat, masked = query_pictures(photo, heatmap, valid, np.asarray(mask, bool), boxes, caption)
    return np.ascontiguousarray(heat[..., ::-1]), np.ascontiguousarray(masked[..., ::-1])  # BGR -> RGB


def map_row(state: MapState, where: str) -> tuple[str, str, str]:
    """The status panel's map row; ``where`` says where the first map is awaited."""
    if state.version == 0:
        return ("map", "WARN", f"no map yet: waiting for the first refinement {where}")
    ended = "final (the flight ended)" if state.final else "the flight goes on"
    text = f"version {state.version}, {state.views_in_map} views, {state.observed:,} Gaussians observed; {ended}"
    return ("map", "OK", text)


@dataclass
class WebAnswer:
    """One query as the page shows it."""

    status: str  # "ok", "bad_request" (the operator's input), "no_map"
    message: str
    text: str = ""
    map_version: int = 0
    margin: np.ndarray | None = None  # [M] per browser splat: cos(query) - max cos(negatives); NaN: unobserved
    instances: list[Instance3D] = field(default_factory=list)  # world metres, largest first
    view: str = ""
    located: list[GeoInstance] = field(default_factory=list)  # ``instances`` on the Earth (NaN: no georeference)
    height_ref: str = ""  # the map's georeference's height reference; "": none (no GeoJSON)
    heatmap_picture: np.ndarray | None = None  # [H', W, 3] uint8 RGB: photo + heatmap + legend
    mask_picture: np.ndarray | None = None  # [H', W, 3] uint8 RGB: photo + mask + legend
    seconds: float = 0.0
    since: str = ""  # a change query's earlier flight; "" an ordinary query
    preview: bool = False  # the view's pictures alone, small (``ask(preview=True)``): the full answer follows


def change_margin(change, ids: np.ndarray, span: float = 0.2) -> np.ndarray:
    """[M] float32 per browser splat (``ids`` into the prior map): a change query's score as the
    page's relevance margin, the candidate cut at 0, score 0 at -``span`` and twice the cut at
    +``span`` (``relevance_colours``); with a text, a Gaussian that did not move towards it (away,
    for gone) at most 0. NaN: not scored."""
    cut = change.params.candidate
    margin = (change.scores[ids].astype(np.float32) - cut) * np.float32(span / cut)
    if change.moved is not None:
        margin = np.where(change.moved[ids], margin, np.minimum(margin, 0.0)).astype(np.float32)
    return margin


def answer_geojson(answer: WebAnswer) -> str | None:
    """The answer's 3D instances as GeoJSON text (``query.geojson``), or None when the map has no
    georeference or the answer no instance: what the page offers for download."""
    if not answer.height_ref or not answer.located:
        return None
    return dumps_geojson(feature_collection(answer.located, answer.text, answer.map_version, answer.height_ref))


class RunReview:
    """A run folder (``map/``, ``views/``) and its prior map, as the page reads them."""

    def __init__(
        self,
        run_dir: str | Path,
        prior_map: str | Path,
        max_splats: int,
        heatmap_cache_mb: int = 320,
        change_cuts: str = "",  # "since flight" answers' rule, "C,O,N[,A]" (ChangeParams.with_cuts); "": defaults
    ):
        self.run_dir, self.prior_map = Path(run_dir), Path(prior_map)
        if not self.run_dir.is_dir():
            raise OlsplatInputError(f"{self.run_dir}: no such run folder")
        self.service = MapService(
            prior_map,
            self.run_dir / "map",
            self.run_dir / "views",
            heatmap_cache_mb=heatmap_cache_mb,
            flights_dir=self.run_dir / "flights",  # an aggregate's per-flight maps, when it has them
            change_cuts=change_cuts,
            name="ground",
        )
        self.max_splats = max_splats
        self.splats: BrowserSplats = self.service.splats(max_splats)
        # views the page was told of: a query re-reads a grown views folder too, and the page must
        # still hear of those views from the next refresh (it draws their frustums then)
        self.views_told = 0

    @property
    def state(self) -> MapState:
        return self.service.state

    def refresh(self) -> bool:
        """Read a newer map and new views if the run wrote any; True when something changed.
        Raises OlsplatInputError while the newest map does not match the prior map."""
        changed = self.service.refresh()
        if self.service.refusal is not None:
            raise OlsplatInputError(f"{self.service.refusal}: give the prior map this run was made with (--map)")
        views, self.views_told = self.views_told, len(self.service.cameras())
        return changed or views != self.views_told

    def cameras(self) -> list[Camera]:
        return self.service.cameras()

    def close(self) -> None:
        """Wait for the service's background work (the kernels' warm-up, the warm query)."""
        self.service.close()

    def flights(self) -> list[str]:
        """The earlier flights a change query may name (``RUN/flights`` of olsplat aggregate
        --per-flight; the newest one is "now"); [] without per-flight maps."""
        return self.service.flights()[:-1]

    def ask(
        self,
        text: str,
        negatives: list[str],
        view: str = "",
        since: str = "",
        gone: bool = False,
        preview: bool = False,
    ) -> WebAnswer:
        """The query's relevance on the browser splats, its 3D instances and, with ``view`` (a
        view's exact name; another is ignored), the view's heatmap and mask pictures; with
        ``since`` (a flight of ``flights()``) what changed since it instead (``ask_change``);
        with ``preview`` (and a view) the view's pictures alone, small (``MapService.answer``).
        Bad input and a missing map come back as a status."""
        if since:
            return self.ask_change(text, negatives, view, since, gone)
        start = time.perf_counter()
        text, negatives, problem = prepared_query(text, negatives)
        if problem:
            return WebAnswer("bad_request", problem, text)
        view = view if view in {c.name for c in self.cameras()} else ""
        preview = preview and bool(view)
        result = self.service.answer(text, negatives, view, heatmap=bool(view), splats=self.max_splats, preview=preview)
        answer = result.answer
        if answer is None:
            return WebAnswer(result.status, result.message, text)
        outcome = WebAnswer(
            "ok",
            f"{answer.chosen_count:,} Gaussians pick it over {len(answer.negatives)} negatives; "
            f"{len(answer.instances)} instances in 3D",
            text,
            result.version,
            result.margin,
            answer.instances,
            preview=preview,
        )
        if preview:
            assert result.camera is not None
            outcome.message = f"preview at {result.camera.width}x{result.camera.height}; the full answer follows"
        georef = self.service.georef
        outcome.located, outcome.height_ref = locate(answer.instances, georef), georef.height_ref if georef else ""
        if result.photo is not None and answer.heatmap is not None and answer.mask is not None:
            assert answer.alpha is not None
            outcome.view = view
            outcome.heatmap_picture, outcome.mask_picture = view_pictures(
                result.photo,
                answer.heatmap,
                np.asarray(answer.alpha > 0.5),
                answer.mask,
                [r.box for r in answer.regions],
                text,
                view,
                result.version,
            )
        outcome.seconds = time.perf_counter() - start
        return outcome

    def ask_change(self, text: str, negatives: list[str], view: str, since: str, gone: bool) -> WebAnswer:
        """What changed since flight ``since`` (``MapService.answer_change``; an empty ``text``:
        every change instance, else what appeared, or with ``gone`` went, for it over
        ``negatives``): the change instances, the change score as the splats' margin
        (``change_margin``) and, with ``view``, its change heatmap and mask pictures."""
        from ..viz import query_pictures

        start = time.perf_counter()
        text = text.strip()
        negatives = [n for n in negatives if n.lower() != text.lower()] if text else []
        view = view if view in {c.name for c in self.cameras()} else ""
        result = self.service.answer_change(text, since, gone, negatives, view)
        change = result.change
        if change is None:
            return WebAnswer(result.status, result.message, text, since=since)
        outcome = WebAnswer(
            "ok",
            f"{change.title} since flight {since} (now {result.now}): {change.candidates:,} candidates; "
            f"{len(change.instances)} change instances",
            text,
            result.version,
            change_margin(change, self.splats.ids),
            list(change.instances),
            since=since,
        )
        georef = self.service.georef
        outcome.located, outcome.height_ref = locate(outcome.instances, georef), georef.height_ref if georef else ""
        if result.photo is not None and change.heatmap is not None and result.change_mask is not None:
            assert change.alpha is not None
            outcome.view = view
            caption = f"{change.title} since {since} on {Path(view).name}; mask: score > {change.params.candidate:g}"
            heat, masked = query_pictures(
                result.photo,
                np.nan_to_num(change.heatmap, nan=0.0),
                (change.alpha > 0.5) & np.isfinite(change.heatmap),
                result.change_mask,
                [r.box for r in result.change_regions],
                caption,
                scale=(0.0, 2.0 * change.params.object_score),
                unit="score",
            )
            outcome.heatmap_picture = np.ascontiguousarray(heat[..., ::-1])  # BGR -> RGB
            outcome.mask_picture = np.ascontiguousarray(masked[..., ::-1])
        outcome.seconds = time.perf_counter() - start
        return outcome

    def status_rows(self) -> list[tuple[str, str, str]]:
        """(what, level, text) rows of the status panel: OK / WARN / ERROR / STALE levels."""
        views = len(self.cameras())
        return [
            map_row(self.state, f"in {self.run_dir / 'map'}"),
            ("views", "OK" if views else "WARN", f"{views} aggregated"),
            ("nodes", "OK", f"reading the run folder {self.run_dir} (no node link: node health is not shown)"),
        ]
