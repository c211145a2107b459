"""What the ground page shows, read from a run folder: the prior map, the views aggregated so
far, the newest language map, and the answers to the operator's queries (computed here, with
the same core functions as the query server). A finished run gives a post-flight review; a run
folder a graph is still writing gives a live page on the machine that holds it.

Nothing here touches a socket or the browser (``page`` draws what this returns).
"""

from __future__ import annotations

import time
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError
from ..query.answer import QueryFeatures
from ..query.localize import Instance3D, VoxelIndex, default_cluster_radius
from ..query.negatives import AERIAL_VOCABULARY
from ..query.splats import BrowserSplats, browser_splats, relevance_margin
from ..scene import Camera
from ..storage.snapshot import LanguageMap

MAX_TEXT_CHARS = 200  # as the query server's max_text_chars
MAX_NEGATIVES = 32  # as the query server's max_negatives
DEFAULT_NEGATIVES = AERIAL_VOCABULARY  # as the query server's (the page shows them; the operator may edit)
CLUSTER_MIN_POINTS = 20  # as the query server's cluster_min_points


def query_text_problem(text: str, negatives: list[str]) -> str | None:
    """Why the page cannot ask this query (one sentence for the operator), or None."""
    if not text.strip():
        return "the query is empty: type what to look for, e.g. red roof buildings"
    for label, value in [("the query", text), *(("a negative", n) for n in negatives)]:
        if len(value) > MAX_TEXT_CHARS:
            return f"{label} is {len(value):,} characters long; at most {MAX_TEXT_CHARS}"
        if any(unicodedata.category(c) in ("Cc", "Cf") for c in value):
            return f"{label} contains control characters; type plain text"
    if len(negatives) > MAX_NEGATIVES:
        return f"{len(negatives)} negatives; at most {MAX_NEGATIVES}"
    return None


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


@dataclass
class MapState:
    version: int  # 0: no map yet
    views_in_map: int  # views the newest map was refined from
    final: bool  # the refiner wrote its last map (the flight ended)
    observed: int  # Gaussians some view observed


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
    heatmap_picture: np.ndarray | None = None  # [H', W, 3] uint8 RGB: photo + heatmap + legend
    mask_picture: np.ndarray | None = None  # [H', W, 3] uint8 RGB: photo + mask + legend
    seconds: float = 0.0


class RunReview:
    """A run folder (``map/``, ``views/``) and its prior map, as the page reads them."""

    def __init__(self, run_dir: str | Path, prior_map: str | Path, max_splats: int, heatmap_cache_mb: int = 320):
        from ..query.heatmap import FeatureImages
        from ..scene import read_ply

        self.run_dir, self.prior_map = Path(run_dir), Path(prior_map)
        if not self.run_dir.is_dir():
            raise OlsplatInputError(f"{self.run_dir}: no such run folder")
        self.gaussians = read_ply(prior_map)
        self.splats: BrowserSplats = browser_splats(self.gaussians, max_splats)
        self.images = FeatureImages(heatmap_cache_mb * 2**20)
        # the 3D clustering's radius and voxel index, once per prior map (as the query server)
        self.cluster_radius = default_cluster_radius(self.gaussians.means, CLUSTER_MIN_POINTS)
        self.voxel_index = VoxelIndex.build(self.gaussians.means, self.cluster_radius)
        self.language_map: LanguageMap | None = None
        self.features: QueryFeatures | None = None
        self.state = MapState(0, 0, False, 0)
        self.encoders: dict = {}
        self._views: list = []

    def refresh(self) -> bool:
        """Read a newer map and new views if the run wrote any; True when something changed."""
        from ..storage import latest_map, load_views

        changed = False
        views_dir = self.run_dir / "views"
        if views_dir.is_dir() and sum(1 for _ in views_dir.glob("*.json")) != len(self._views):
            self._views = load_views(views_dir)
            changed = True
        record = latest_map(self.run_dir / "map")
        if record is not None and record["version"] > self.state.version:
            try:
                language_map = LanguageMap.load(record["path"], decode=False)
            except OlsplatInputError:  # replaced between latest.json and the file: next time
                return changed
            if len(language_map) != len(self.gaussians):
                raise OlsplatInputError(
                    f"{record['path']}: the map has {len(language_map)} Gaussians, the prior map "
                    f"{len(self.gaussians)}: give the prior map this run was made with (--map)"
                )
            self.features = QueryFeatures.of(language_map)
            self.language_map = language_map
            self.state = MapState(
                int(record["version"]),
                int(record.get("views", 0)),
                bool(record.get("final", False)),
                int(language_map.observed.sum()),
            )
            changed = True
        return changed

    def cameras(self) -> list[Camera]:
        return [v.camera for v in self._views]

    def ask(self, text: str, negatives: list[str], view: str = "") -> WebAnswer:
        """The query's relevance on the browser splats, its 3D instances and, with ``view``, the
        view's heatmap and mask pictures. Bad input and a missing map come back as a status."""
        from ..query.answer import CachedTexts, answer_query, encoder_for_map

        start = time.perf_counter()
        text, negatives, problem = prepared_query(text, negatives)
        if problem:
            return WebAnswer("bad_request", problem, text)
        if self.language_map is None or self.features is None:
            return WebAnswer("no_map", "no map yet: no view has been aggregated and refined", text)
        name = self.language_map.encoder
        if name not in self.encoders:
            self.encoders[name] = CachedTexts(encoder_for_map(self.language_map))
        encoder = self.encoders[name]
        cameras = self.cameras()
        camera = next((c for c in cameras if c.name == view), None) if view else None
        try:
            answer = answer_query(
                self.language_map,
                self.gaussians,
                encoder,
                text,
                negatives,
                camera,
                images=self.images,
                image_key=(self.state.version, view),
                cluster_radius=self.cluster_radius,
                min_points=CLUSTER_MIN_POINTS,
                features=self.features,
                voxel_index=self.voxel_index,
            )
        except OlsplatInputError as exc:
            return WebAnswer("bad_request", str(exc), text)
        embeddings = encoder.encode_text([text, *answer.negatives])
        margin = relevance_margin(self.features, self.language_map.observed, self.splats.ids, embeddings)
        result = WebAnswer(
            "ok",
            f"{answer.chosen_count:,} Gaussians pick it over {len(answer.negatives)} negatives; "
            f"{len(answer.instances)} instances in 3D",
            text,
            self.state.version,
            margin,
            answer.instances,
        )
        if camera is not None and answer.heatmap is not None and answer.mask is not None and answer.alpha is not None:
            photo = next(v for v in self._views if v.camera.name == view).image()
            boxes = [r.box for r in answer.regions]
            result.view = view
            result.heatmap_picture, result.mask_picture = view_pictures(
                photo,
                answer.heatmap,
                np.asarray(answer.alpha > 0.5),
                answer.mask,
                boxes,
                text,
                view,
                self.state.version,
            )
        result.seconds = time.perf_counter() - start
        return result

    def status_rows(self) -> list[tuple[str, str, str]]:
        """(what, level, text) rows of the status panel: OK / WARN / ERROR / STALE levels."""
        return [
            map_row(self.state, f"in {self.run_dir / 'map'}"),
            ("views", "OK" if self._views else "WARN", f"{len(self._views)} aggregated"),
            ("nodes", "OK", f"reading the run folder {self.run_dir} (no node link: node health is not shown)"),
        ]
