"""The map a query reads, held between queries: what the query server answers from and what the
ground page's run-folder source answers from (``nodes/query_server.py`` puts the wire around it,
``ground/review.py`` the page).

A ``MapService`` reads the prior map (INRIA PLY) once and follows a run's folders: the newest
language map snapshot of ``map_dir`` (``storage.latest_map``; a snapshot whose Gaussian count is
not the prior map's is refused, with the reason kept in ``refusal``) and the saved views of
``views_dir`` (re-read when the folder grows: views are only ever added). It keeps what makes a
query fast once paid for: the map's ``QueryFeatures``, the 3D clustering's radius and voxel
index, the text encoders with their embedding caches, the rendered features of recent views
(``FeatureImages``) and the last browser decimation. Three background threads pay ahead of the
first query: the warm-up (compiles the numba kernels, builds the voxel index), the heatmap
cache's reservation (touches its memory) and the warm query (loads the text encoder, queries the
first map once); ``close()`` joins them.

Coordinates are the prior map's (world metres); ``georef`` places them on the Earth when the map
has a ``georef.json`` (beside the prior map's PLY, else in ``map_dir``: a run's, from its
source). Cameras follow ``scene.Camera`` (OpenCV axes: x
right, y down, z forward; pixels with the top-left pixel's centre at (0.5, 0.5)). No sockets
here: requests and replies are the caller's.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import OlsplatInputError

if TYPE_CHECKING:  # the heavy modules load at run time: a node class is imported by the launcher
    from ..scene import Camera, Gaussians
    from ..scene.geodesy import Georeference
    from ..storage import LanguageMap, SavedView
    from .answer import CachedTexts, QueryAnswer, QueryFeatures
    from .change_answer import ChangeAnswer
    from .localize import VoxelIndex
    from .splats import BrowserSplats

log = logging.getLogger(__name__)

MAX_TEXT_CHARS = 200  # per text, the query's and each negative's (the query server's max_text_chars)
MAX_NEGATIVES = 32  # each costs a text embedding and a cosine per Gaussian and pixel
CLUSTER_MIN_POINTS = 20  # a 3D instance has at least this many Gaussians
REPLY_BYTES_PER_PIXEL = 8  # a heatmap reply: float32 heatmap, uint8 mask, RGB photo
# a preview's longer side, pixels: a 1280x960 view's heatmap in 1/16 of its pixels, what a ground
# station shows at once while the full answer (and its 3D instances) is computed
PREVIEW_MAX_SIDE = 320
# ... drawn from at most this many of the map's Gaussians, the most opaque and largest (the
# browser's decimation, ``splats.decimate``): at 320 px the cost is the Gaussians projected, and
# a far view of the 5.2M-Gaussian map projects millions (p95 1.36 s); the top 500,000 take p95
# 0.16 s and their mask covers 0.88-0.93 of the exact one's (IoU; `olsplat bench query
# --preview-views 6`, docs/benchmarks.md "Scale"). The full answer stays exact.
PREVIEW_MAX_GAUSSIANS = 500_000
PREVIEW_CACHE_MB = 64  # previews' own feature images: a preview must not evict a full view's
NO_MAP = "no map yet: no view has been aggregated and refined"


@dataclass(frozen=True)
class TextProblem:
    """Why a query's texts cannot be asked, in parts: the query server and the page each word it
    for their reader (``message`` is the server's sentence)."""

    kind: str  # "empty", "long" (characters), "control" (control characters), "negatives" (too many)
    subject: str  # "query" or "negative": the text at fault
    size: int  # the text's characters ("long"), the number of negatives ("negatives"), else 0
    limit: int  # the limit broken ("long", "negatives"), else 0

    @property
    def message(self) -> str:
        """The query server's reply message."""
        subject = "the query text" if self.subject == "query" else "a negative"
        if self.kind == "empty":
            return "the query text is empty"
        if self.kind == "negatives":
            return f"{self.size} negatives; at most {self.limit} per query"
        if self.kind == "long":
            return f"{subject} is longer than {self.limit} characters"
        return f"{subject} contains control characters"


def text_problem(
    text: str,
    negatives: Sequence[str],
    max_chars: int = MAX_TEXT_CHARS,
    max_negatives: int = MAX_NEGATIVES,
    control: bool = False,
) -> TextProblem | None:
    """The first problem of a query's texts, or None. In order: an empty query (blank once
    stripped), a query over ``max_chars`` (stripped), with ``control`` one holding control or
    format characters (Unicode Cc, Cf: a terminal escape in a label), more than ``max_negatives``
    negatives, then each negative as the query (as given, not stripped)."""
    text = text.strip()
    if not text:
        return TextProblem("empty", "query", 0, 0)

    def fault(value: str, subject: str) -> TextProblem | None:
        if len(value) > max_chars:
            return TextProblem("long", subject, len(value), max_chars)
        if control and any(unicodedata.category(c) in ("Cc", "Cf") for c in value):
            return TextProblem("control", subject, 0, 0)
        return None

    problem = fault(text, "query")
    if problem is None and len(negatives) > max_negatives:
        problem = TextProblem("negatives", "negative", len(negatives), max_negatives)
    for negative in negatives:
        problem = problem or fault(negative, "negative")
    return problem


@dataclass
class MapState:
    """The loaded map as a status panel shows it."""

    version: int  # 0: no map yet
    views_in_map: int  # views the map was refined from
    final: bool  # the refiner wrote its last map (the flight ended)
    observed: int  # Gaussians some view observed


@dataclass
class LoadedMap:
    """One language map version, as queries read it."""

    version: int
    language_map: LanguageMap  # its ``features`` emptied: the rows are held once, in ``features``
    features: QueryFeatures
    record: dict  # latest.json's record of it (views, final, ...)
    observed: int  # Gaussians some view observed


@dataclass
class MapAnswer:
    """One query's outcome. ``status`` "ok": ``answer`` holds the core answer (3D instances in
    world metres; with a view, heatmap [H, W] cosine, mask [H, W], 2D regions in ``camera``'s
    pixels); else ``message`` says why ("bad_request": the asker's input, "no_map")."""

    status: str
    message: str
    version: int  # the map version answered from (0: none yet)
    answer: QueryAnswer | None = None
    camera: Camera | None = None  # the view as rendered: scaled to ``heatmap_max_side``
    photo: np.ndarray | None = None  # [H, W, 3] uint8 RGB at ``camera``'s size, when a heatmap was asked
    margin: np.ndarray | None = None  # [M] float32 per browser splat (``answer(splats=M)``), NaN: unobserved
    loaded: LoadedMap | None = field(default=None, repr=False)  # the map version it read
    encoder: CachedTexts | None = field(default=None, repr=False)
    change: ChangeAnswer | None = None  # a change query's answer (``answer_change``); ``answer`` is None
    since: str = ""  # a change query's earlier flight
    now: str = ""  # ... and its later one, the newest of ``flights_dir``
    change_mask: np.ndarray | None = None  # [H, W] bool: the change heatmap over the candidate cut
    change_regions: list = field(default_factory=list)  # its ``Region2D``s, largest first


class Background:
    """``fn(*args)`` in a daemon thread; ``result()`` waits for it and returns its value (or
    raises its exception)."""

    def __init__(self, name: str, fn, *args):
        self.done = threading.Event()
        self.value: Any = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(fn, args), name=name, daemon=True)
        self.thread.start()

    def _run(self, fn, args) -> None:
        try:
            self.value = fn(*args)
        except BaseException as exc:  # handed to whoever waits for the result
            self.error = exc
        finally:
            self.done.set()

    def result(self) -> Any:
        self.done.wait()
        if self.error is not None:
            raise self.error
        return self.value


class MapService:
    """The prior map, the newest language map of a run and everything a query reuses.

    ``prior_map``: the INRIA PLY the run was made over. ``map_dir``: the refiner's snapshots
    (``latest.json``); ``views_dir``: the run's saved views. ``cluster_radius`` (metres; 0: from
    the prior map's density) and ``cluster_min_points``: the 3D instances' DBSCAN.
    ``heatmap_cache_mb``: rendered features of recent views kept (0: none). ``negatives``: the
    texts a query must beat when it names none (empty: the aerial vocabulary without the query
    and its near-duplicates). ``max_text_chars``, ``max_negatives``: the query texts' limits.
    ``max_reply_mb``: a view whose heatmap, mask and photo (8 bytes a pixel) would exceed it is
    refused; ``heatmap_max_side``: a view is rendered at most this many pixels on its longer side
    (0: its own size). ``flights_dir``: an aggregate's ``OUT/flights`` (``olsplat aggregate
    --per-flight``), which change queries read (``answer_change``); "" none. ``name`` prefixes
    the background threads' names.

    Not thread-safe beyond its own background threads: one caller thread asks (the node's loop,
    or the page under its lock)."""

    def __init__(
        self,
        prior_map: str | Path,
        map_dir: str | Path,
        views_dir: str | Path,
        *,
        cluster_radius: float = 0.0,
        cluster_min_points: int = CLUSTER_MIN_POINTS,
        heatmap_cache_mb: float = 320,
        negatives: Sequence[str] = (),
        max_text_chars: int = MAX_TEXT_CHARS,
        max_negatives: int = MAX_NEGATIVES,
        max_reply_mb: float = math.inf,
        heatmap_max_side: int = 0,
        flights_dir: str | Path = "",
        change_cuts: str = "",
        text_change_cuts: str = "",
        name: str = "map",
    ):
        from ..scene import read_ply
        from .heatmap import FeatureImages
        from .localize import default_cluster_radius

        self.map_dir, self.views_dir, self.name = Path(map_dir), Path(views_dir), name
        self.flights_dir = Path(flights_dir) if flights_dir else None
        from .change import TEXT_PARAMS, ChangeParams

        # a change request's rule: "C,O,N[,A]" (ChangeParams.with_cuts) or "" for the defaults;
        # resolved for the prior map below (radius and least area from its density, once)
        change_rule = ChangeParams().with_cuts(change_cuts) if change_cuts else ChangeParams()
        text_change_rule = TEXT_PARAMS.with_cuts(text_change_cuts) if text_change_cuts else TEXT_PARAMS
        self._flight_maps: dict[tuple[str, float], LanguageMap] = {}  # (path, mtime) -> map: the last pair
        self.cluster_min_points, self.negatives = cluster_min_points, tuple(negatives)
        self.max_text_chars, self.max_negatives = max_text_chars, max_negatives
        self.max_reply_mb, self.heatmap_max_side = max_reply_mb, heatmap_max_side
        self.gaussians = read_ply(prior_map)
        self.prior_map = Path(prior_map)
        self.georef: Georeference | None = None  # None: answers stay in map coordinates
        self.georef_problem: str | None = None  # why a georef.json found could not be used
        self._find_georef()
        # from the prior map's density once (~30 ms for 390k Gaussians): not again for every query
        self.cluster_radius = cluster_radius or default_cluster_radius(self.gaussians.means, cluster_min_points)
        self.change_params = change_rule.for_map(self.gaussians.means)
        self.text_change_params = text_change_rule.for_map(self.gaussians.means)
        # the map's centres sorted by voxel once (~1.5 s for 5M, in the warm-up thread, not delaying
        # start-up): a query's clustering then skips its own sort; until then it sorts
        self.voxel_index: VoxelIndex | None = None
        self.loaded: LoadedMap | None = None
        self.refusal: str | None = None  # why the newest snapshot was refused, until a newer one loads
        self._refused_version = 0
        self.encoders: dict[str, CachedTexts] = {}  # encoder spec -> loaded encoder
        self.encoder_lock = threading.Lock()  # a query and the warm query may ask for the encoder at once
        self.feature_images = FeatureImages(int(heatmap_cache_mb * 2**20))
        self.preview_images = FeatureImages(PREVIEW_CACHE_MB * 2**20)
        self.heatmap_cache = heatmap_cache_mb > 0
        self._preview_map: tuple[Gaussians, np.ndarray] | None = None  # made by the warm-up (or a preview)
        self._preview_lock = threading.Lock()
        self._views: list[SavedView] = []
        self._splats: BrowserSplats | None = None  # the last decimation asked for ...
        self._splats_max = 0  # ... and its max_splats
        self.reservation: threading.Thread | None = None  # touches the heatmap cache, once views exist
        self.warm_query: Background | None = None  # the first map's query in the background, once
        self.closed = False
        self.warm_up = threading.Thread(target=self._warm_up, name=f"{name}-warm-up", daemon=True)
        self.warm_up.start()

    # -- the run's folders ------------------------------------------------------------------------
    @property
    def version(self) -> int:
        """The loaded map's version; 0 before any."""
        return 0 if self.loaded is None else self.loaded.version

    @property
    def language_map(self) -> LanguageMap | None:
        return None if self.loaded is None else self.loaded.language_map

    @property
    def state(self) -> MapState:
        if self.loaded is None:
            return MapState(0, 0, False, 0)
        record = self.loaded.record
        return MapState(
            self.loaded.version, int(record.get("views", 0)), bool(record.get("final", False)), self.loaded.observed
        )

    def refresh(self, views: bool = True) -> bool:
        """Load a newer map version if ``map_dir`` has one and, with ``views``, re-read the views
        if the folder grew; True when either changed. A snapshot that cannot be read yet (replaced
        between ``latest.json`` and the file) is tried again at the next call; one whose Gaussian
        count differs from the prior map's is refused (``refusal`` says why, logged once)."""
        changed = self._load_newer_map()
        if self.georef is None:  # a run's source may write one after the service started
            self._find_georef()
        if views:
            before = len(self._views)
            changed = len(self.views()) != before or changed
        return changed

    def _load_newer_map(self) -> bool:
        from ..storage import LanguageMap, latest_map
        from .answer import QueryFeatures

        record = latest_map(self.map_dir)
        if record is None or record["version"] <= max(self.version, self._refused_version):
            return False
        version = int(record["version"])
        try:
            language_map = LanguageMap.load(record["path"], decode=False)  # a codebook map stays codes
        except OlsplatInputError as exc:  # replaced between reading latest.json and the file: next time
            log.warning("map version %d not loaded: %s", version, exc)
            return False
        if len(language_map) != len(self.gaussians):
            # not read again every refresh (a large map takes seconds); the reason stays until a
            # newer version loads, so that a page can keep showing it
            self.refusal = (
                f"{record['path']}: the map has {len(language_map)} Gaussians, the prior map {len(self.gaussians)}"
            )
            self._refused_version = version
            log.error("map version %d ignored: %s", version, self.refusal)
            return False
        self.loaded = None  # the old version's rows go before the new ones are made (peak memory)
        features = QueryFeatures.of(language_map)  # once, not per query
        if self.voxel_index is not None:  # else the first query after the index makes them
            features.rows_in_order(self.voxel_index)
        language_map.features = np.zeros((0, features.table.shape[1]), np.float32)  # held once, above
        self.loaded = LoadedMap(version, language_map, features, record, int(np.count_nonzero(language_map.observed)))
        self.refusal = None
        log.info("map version %d loaded (%d views)", version, record.get("views", 0))
        if self.closed:
            return True
        if self.reservation is None and self.heatmap_cache:
            self._reserve_heatmap_cache(features.table.shape[1])
        if self.warm_query is None:
            self.warm_query = Background(f"{self.name}-warm-query", self._warm_query, self.loaded)
        return True

    def _find_georef(self) -> None:
        """Read the map's georeference: ``georef.json`` beside the prior map's PLY, else in
        ``map_dir``. A file that cannot be used is logged once and its one-line reason kept in
        ``georef_problem``; answers then stay in map coordinates."""
        from ..scene.geodesy import find_georef, read_georef

        path = find_georef(self.prior_map.parent, self.map_dir)
        if path is None:
            return
        try:
            self.georef = read_georef(path)
        except OlsplatInputError as exc:
            if self.georef_problem != str(exc):
                log.error("no georeference: %s", exc)
            self.georef_problem = str(exc)
            return
        self.georef_problem = None
        log.info("georeference %s: %s", path, self.georef)

    def views(self) -> list[SavedView]:
        """The run's saved views in index order, re-read when the folder has more view records
        than were read (views are only ever added)."""
        from ..storage import load_views

        if len(self._views) != sum(1 for _ in self.views_dir.glob("*.json")):
            self._views = load_views(self.views_dir)
        return self._views

    def cameras(self) -> list[Camera]:
        """The saved views' cameras, in index order."""
        return [v.camera for v in self.views()]

    # -- queries ----------------------------------------------------------------------------------
    def text_problem(self, text: str, negatives: Sequence[str]) -> TextProblem | None:
        """``text_problem`` with this service's limits (control characters allowed)."""
        return text_problem(text, negatives, self.max_text_chars, self.max_negatives)

    def answer(
        self,
        text: str,
        negatives: Sequence[str] = (),
        view: str = "",
        threshold: float | None = None,
        heatmap: bool = True,
        splats: int = 0,
        preview: bool = False,
    ) -> MapAnswer:
        """``query.answer.answer_query`` on the loaded map: relevance, 3D instances and, with
        ``view`` (a saved view's name, file name, stem or index: ``scene.select_view``), that
        view's heatmap, mask and 2D regions, rendered at most ``heatmap_max_side`` on its longer
        side. ``negatives``: empty for the service's (``negatives``, else the aerial vocabulary
        without the query's near-duplicates). ``threshold``: a cosine the heatmap must exceed
        instead of beating the negatives (None or NaN: beat them). ``heatmap``: False drops the
        heatmap and mask from the answer (the 2D regions stay) and reads no photo. ``splats``:
        M > 0 adds the relevance margin of the first M-splat browser decimation (``margin``).
        ``preview``: the view's pictures alone, at most ``PREVIEW_MAX_SIDE`` on the longer side
        (no 3D instances, no margin): what a ground station shows while the full answer comes.
        Refusals (texts, splats out of 0..MAX_SPLATS, an unknown view, a reply over
        ``max_reply_mb``, no map yet) come back as a status, never raised."""
        from ..scene import select_view
        from .answer import answer_query
        from .negatives import vocabulary_negatives
        from .splats import MAX_SPLATS

        loaded = self.loaded  # one version throughout, whatever a refresh does meanwhile

        def refuse(status: str, message: str) -> MapAnswer:
            return MapAnswer(status, message, self.version)

        problem = self.text_problem(text, negatives)
        if problem is not None:
            return refuse("bad_request", problem.message)
        if not 0 <= splats <= MAX_SPLATS:
            return refuse("bad_request", f"splats must be 0..{MAX_SPLATS:,}, got {splats:,}")
        if preview and not (view and heatmap):
            return refuse("bad_request", "a preview is a view's heatmap: give a view (and ask for its heatmap)")
        if loaded is None:
            return refuse("no_map", NO_MAP)
        text = text.strip()
        photo = None
        try:
            views = self.views()
            camera = select_view([v.camera for v in views], view) if view else None
            if camera is not None:
                saved = views[[v.camera for v in views].index(camera)]
                camera = self._reply_camera(camera, PREVIEW_MAX_SIDE if preview else 0)
                if heatmap:
                    reply_mb = camera.width * camera.height * REPLY_BYTES_PER_PIXEL / 2**20
                    if reply_mb > self.max_reply_mb:
                        return refuse(
                            "bad_request",
                            f"view {camera.name} is {camera.width}x{camera.height}: its heatmap reply would be "
                            f"{reply_mb:.1f} MB, over max_reply_mb {self.max_reply_mb:g}",
                        )
                    photo = self._photo(saved, camera)
            encoder = self._encoder(loaded.language_map)
            negatives = list(negatives or self.negatives) or vocabulary_negatives(text, encoder)
            answer = answer_query(
                loaded.language_map,
                self.gaussians,
                encoder,
                text,
                negatives,
                camera,
                threshold if threshold is not None and math.isfinite(threshold) else None,
                images=(self.preview_images if preview else self.feature_images) if self.heatmap_cache else None,
                # the width too: a view rendered at another size is another image
                image_key=(loaded.version, camera.name, camera.width) if camera is not None else None,
                cluster_radius=self.cluster_radius,
                min_points=self.cluster_min_points,
                features=loaded.features,
                voxel_index=self.voxel_index,
                locate=not preview,
                drawn=self.preview_map() if preview else None,
            )
        except OlsplatInputError as exc:
            return refuse("bad_request", str(exc))
        if not heatmap:
            answer.heatmap = answer.mask = None
        result = MapAnswer("ok", "", loaded.version, answer, camera, photo, loaded=loaded, encoder=encoder)
        if splats and not preview:  # the page's colours: per splat of its decimation, in its order
            result.margin = self.margin(result, self.splats(splats))
        return result

    def flights(self) -> list[str]:
        """The flights of ``flights_dir`` in flight order (``flights.json``); [] without one."""
        from .change_answer import flight_ids

        return flight_ids(self.flights_dir) if self.flights_dir is not None else []

    def answer_change(
        self, text: str, since: str, gone: bool = False, negatives: Sequence[str] = (), view: str = ""
    ) -> MapAnswer:
        """What changed from flight ``since`` (an id of ``flights()``, e.g. "f0") to the newest
        flight (``change_answer.answer_change``): without ``text`` ("") every change instance,
        with it what moved towards it (or away, ``gone``), its negatives ``negatives`` or the
        aerial vocabulary's. With ``view``, that view's change heatmap (score, NaN: not scored),
        its mask (score > the candidate cut) and 2D regions. Refusals come back as a status."""
        from ..scene import select_view
        from .change_answer import answer_change
        from .localize import regions_in_view
        from .negatives import AERIAL_VOCABULARY

        def refuse(status: str, message: str) -> MapAnswer:
            return MapAnswer(status, message, self.version, since=since)

        flights = self.flights()
        if not flights:
            return refuse("bad_request", f"since {since}: this map has no flights (olsplat aggregate --per-flight)")
        now = flights[-1]
        if since not in flights[:-1]:
            return refuse("bad_request", f"since {since}: not an earlier flight of {', '.join(flights)}")
        text = text.strip()
        if text:
            problem = self.text_problem(text, negatives)
            if problem is not None:
                return refuse("bad_request", problem.message)
        try:
            map_a, map_b = (self._flight_map(f) for f in (since, now))
            views = self.views()
            camera = select_view([v.camera for v in views], view) if view else None
            photo = None
            if camera is not None:
                saved = views[[v.camera for v in views].index(camera)]
                camera = self._reply_camera(camera)
                photo = self._photo(saved, camera)
            params = self.text_change_params if text else self.change_params
            vocabulary = tuple(self.negatives) or AERIAL_VOCABULARY
            change = answer_change(
                map_a, map_b, self.gaussians, text or None, gone, list(negatives) or None, vocabulary, params, camera
            )
        except OlsplatInputError as exc:
            return refuse("bad_request", str(exc))
        result = MapAnswer("ok", "", self.version, camera=camera, photo=photo, change=change, since=since, now=now)
        if change.heatmap is not None and change.alpha is not None:
            valid = (change.alpha > 0.5) & np.isfinite(change.heatmap)
            result.change_mask = valid & (np.nan_to_num(change.heatmap, nan=0.0) > params.candidate)
            result.change_regions = regions_in_view(result.change_mask)
        return result

    def _flight_map(self, flight: str) -> LanguageMap:
        """Flight ``flight``'s map, checked (``check_flight_map``); the last two read are kept."""
        from ..storage import LanguageMap
        from .change_answer import check_flight_map

        assert self.flights_dir is not None
        path = self.flights_dir / flight / "language_map.npz"
        if not path.is_file():
            raise OlsplatInputError(f"{path}: flight {flight}'s map is missing")
        key = (str(path), path.stat().st_mtime)
        if key not in self._flight_maps:
            language_map = check_flight_map(LanguageMap.load(path), str(path), len(self.gaussians))
            self._flight_maps = {k: v for k, v in list(self._flight_maps.items())[-1:]} | {key: language_map}
        return self._flight_maps[key]

    def margin(self, result: MapAnswer, splats: BrowserSplats) -> np.ndarray:
        """[M] float32 cos(query) - max cos(negatives) of ``splats`` (``splats.ids`` into the prior
        map) on the map version ``result`` was answered from; NaN where no view observed the
        Gaussian (``splats.relevance_margin``)."""
        from .splats import relevance_margin

        answer, loaded, encoder = result.answer, result.loaded, result.encoder
        if answer is None or loaded is None or encoder is None:
            raise ValueError(f"no relevance on a {result.status} answer")
        embeddings = encoder.encode_text([answer.text, *answer.negatives])  # cached since the query
        return relevance_margin(loaded.features, loaded.language_map.observed, splats.ids, embeddings)

    def splats(self, max_splats: int) -> BrowserSplats:
        """The prior map decimated to ``max_splats`` (``splats.browser_splats``). The last one is
        kept: a ground station asks for one size, then queries for it."""
        from .splats import browser_splats

        if self._splats is None or self._splats_max != max_splats:
            self._splats = browser_splats(self.gaussians, max_splats)
            self._splats_max = max_splats
        return self._splats

    def preview_map(self) -> tuple[Gaussians, np.ndarray] | None:
        """The Gaussians a preview is drawn from and their ids [M] in the map: the map's
        ``PREVIEW_MAX_GAUSSIANS`` most opaque and largest (``splats.decimate``), made once (~1 s
        for 5.2M, in the warm-up) and kept without their colours (~25 MB for 500,000); None for
        a map no larger (a preview draws all of it)."""
        from ..scene import Gaussians
        from .splats import decimate

        g = self.gaussians
        if len(g) <= PREVIEW_MAX_GAUSSIANS:
            return None
        with self._preview_lock:
            if self._preview_map is None:
                ids = decimate(g, PREVIEW_MAX_GAUSSIANS)
                kept = Gaussians(  # no colours: a preview renders features
                    g.means[ids], g.quats[ids], g.log_scales[ids], g.opacity_logits[ids], g.sh[ids, :1], {}
                )
                self._preview_map = (kept, ids)
            return self._preview_map

    def _reply_camera(self, camera: Camera, max_side: int = 0) -> Camera:
        """The view's camera scaled down to ``heatmap_max_side`` (and ``max_side`` when > 0) on its
        longer side, or as it is."""
        limits = [side for side in (self.heatmap_max_side, max_side) if side > 0]
        if not limits or max(camera.width, camera.height) <= min(limits):
            return camera
        return camera.scaled(min(limits) / max(camera.width, camera.height))

    @staticmethod
    def _photo(saved: SavedView, camera: Camera) -> np.ndarray:
        """The view's photo [H, W, 3] uint8 RGB at ``camera``'s size (area averaging when smaller)."""
        import cv2

        image = saved.image()
        if image.shape[:2] == (camera.height, camera.width):
            return image
        return cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)

    def _encoder(self, language_map: LanguageMap) -> CachedTexts:
        """The text encoder of a map's features, loaded once (``CachedTexts``)."""
        from .answer import CachedTexts, encoder_for_map

        with self.encoder_lock:
            if language_map.encoder not in self.encoders:
                self.encoders[language_map.encoder] = CachedTexts(encoder_for_map(language_map))
            return self.encoders[language_map.encoder]

    # -- status -----------------------------------------------------------------------------------
    def status_values(self) -> dict[str, float | int]:
        """Status figures: the heatmap cache (hits, misses, MB held), the loaded map (version,
        views it was refined from, Gaussians observed, final 0/1), ``query_index_ready`` (1 once
        the warm-up made the voxel index: 3D instances at full speed) and ``query_warm`` (1 once
        the first map was queried in the background: the first real query loads nothing)."""
        state = self.state
        return {
            "heatmap_cache_hits": self.feature_images.hits,
            "heatmap_cache_misses": self.feature_images.misses,
            "heatmap_cache_mb": round(self.feature_images.bytes / 2**20, 1),
            "map_version": state.version,
            "map_views": state.views_in_map,
            "map_observed": state.observed,
            "map_final": int(state.final),
            "query_index_ready": int(self.voxel_index is not None),
            "query_warm": int(self.warm_query is not None and self.warm_query.done.is_set()),
        }

    # -- background work --------------------------------------------------------------------------
    def close(self, timeout_s: float = 120.0) -> None:
        """Wait for the background threads (each at most ``timeout_s``) and start no new ones: the
        warm-up and the warm query run numba kernels for seconds (minutes on a cold cache), and a
        service that is done with must not leave them running in a process that goes on
        (composed launches, tests)."""
        self.closed = True
        self.warm_up.join(timeout_s)
        if self.reservation is not None:
            self.reservation.join(timeout_s)
        if self.warm_query is not None:
            self.warm_query.thread.join(timeout_s)

    def threads(self) -> list[threading.Thread]:
        """The background threads started so far (alive or not)."""
        started = [self.warm_up, self.reservation, self.warm_query.thread if self.warm_query else None]
        return [t for t in started if t is not None]

    def _warm_up(self) -> None:
        """Compile the query kernels (numba: 3D clustering, feature rendering) on small inputs
        while the caller already serves: on a fresh install the first real query would
        otherwise pay 10-40 s of compilation and time out at the ground station. Then build
        the voxel index."""
        from .heatmap import render_feature_map
        from .localize import VoxelIndex, instances_in_3d

        try:
            start = time.perf_counter()
            points = np.random.default_rng(0).uniform(0.0, 5.0, (500, 3))
            instances_in_3d(points, np.ones(len(points), bool))
            render_feature_map(self.gaussians, np.zeros((len(self.gaussians), 1), np.float32), self._warm_up_camera())
            index = VoxelIndex.build(self.gaussians.means, self.cluster_radius)
            # the index's own path (its centres in the map's float type) compiled before it serves
            instances_in_3d(
                self.gaussians.means, np.arange(min(1000, len(self.gaussians))), self.cluster_radius, index=index
            )
            self.voxel_index = index
            drawn = self.preview_map()  # and its culling index, by a render
            if drawn is not None:
                render_feature_map(drawn[0], np.zeros((len(drawn[0]), 1), np.float32), self._warm_up_camera())
            log.info("query kernels, the voxel index and the preview map ready in %.1f s", time.perf_counter() - start)
        except Exception:  # a warm-up failure must not take the caller down; the query will say more
            log.exception("warm-up failed")

    def _warm_up_camera(self) -> Camera:
        """A 32x24 camera 100 m above the map's median centre, looking down: the warm-ups' view."""
        from ..scene import Camera, intrinsics, look_at

        centre = np.median(self.gaussians.means, axis=0)
        return Camera(
            "warm-up",
            32,
            24,
            intrinsics(30.0, 30.0, 16.0, 12.0),
            look_at(centre + np.array([0.0, 0.0, 100.0]), centre, (0.0, 1.0, 0.0)),
        )

    def _reserve_heatmap_cache(self, dim: int) -> None:
        """Touch the heatmap cache's memory in the background, sized by the newest view: the
        first heatmap of a view then writes into memory already paged in (first-touched memory
        costs as much as the rendering on a small VM). Nothing before the first view."""
        views = self.views()
        if not views:
            return
        camera = self._reply_camera(views[-1].camera)
        self.reservation = threading.Thread(
            target=self.feature_images.reserve,
            args=(camera.width * camera.height, dim),
            name=f"{self.name}-reserve",
            daemon=True,
        )
        self.reservation.start()

    def _warm_query(self, loaded: LoadedMap) -> float:
        """A query on the first map loaded, in the background, once: the text encoder is loaded,
        the relevance and clustering kernels come out of numba's cache and the map's rows are
        paged in, so that the operator's first query is not the one that pays for it (~0.3 s on
        the large map: the encoder 0.12 s, the first relevance + instances 0.2 s against 0.08).
        It waits for the warm-up's voxel index, and also renders a small heatmap with the map's
        own feature table (the kernel a heatmap query takes). Returns its seconds."""
        from .answer import answer_query

        self.warm_up.join()
        start = time.perf_counter()
        try:
            answer_query(
                loaded.language_map,
                self.gaussians,
                self._encoder(loaded.language_map),
                "warm-up",
                ["object", "things"],
                camera=self._warm_up_camera(),
                features=loaded.features,
                cluster_radius=self.cluster_radius,
                min_points=self.cluster_min_points,
                voxel_index=self.voxel_index,
            )
        except Exception:  # the query itself will say more; a warm-up failure must not stop the caller
            log.exception("warm query failed")
        seconds = time.perf_counter() - start
        log.info("first map queried in the background in %.2f s", seconds)
        return seconds
