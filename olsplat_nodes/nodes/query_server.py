"""query_server: the ground station's endpoint. ``QueryRequest`` -> ``QueryReply``; ``StatusRequest``
-> ``StatusReply`` with every node's latest ``DiagnosticStatus``; for a browser ground station,
``SplatsRequest`` -> ``SplatsReply`` (the prior map decimated to what a browser draws) and
``ViewsRequest`` -> ``ViewsReply`` (the aggregated views' cameras), and a query's per-splat
relevance when it asks for it (``QueryRequest.splats``).

It loads the newest language map snapshot at start (late joiner: from ``MAP_DIR/latest.json``)
and again whenever the refiner announces a newer version. Before any map exists a query gets
``status: "no_map"`` at once. It owns the diagnostics collector (a bound SUB socket every
node's heartbeat connects to); a node silent for ``stale_after_s`` is reported STALE. The
query link may require CURVE with an allow-list of client keys (``server_secret`` +
``allow_dir``): other clients get no answer at all.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from olsplat_msgs import (
    MapUpdated,
    QueryReply,
    QueryRequest,
    SplatsReply,
    SplatsRequest,
    StatusReply,
    StatusRequest,
    ViewsReply,
    ViewsRequest,
)

from ..errors import OlsplatInputError
from ..transport import CONTROL_MAX_BYTES, REQUEST_MAX_BYTES, DiagnosticsCollector, QueryServer, Subscriber, curve
from ..transport.convert import reply_for, view_pose
from .base import Node

if TYPE_CHECKING:  # imported at run time inside methods: the launcher imports node classes
    from ..query.answer import QueryFeatures
    from ..query.localize import VoxelIndex
    from ..query.splats import BrowserSplats
    from ..storage import LanguageMap

log = logging.getLogger(__name__)
VIEWS_PER_REPLY = 500  # ViewPose records per ViewsReply (~150 kB): a long flight comes in pages


def is_public(endpoint: str) -> bool:
    """Whether a ZeroMQ bind endpoint can be reached from other computers: tcp on anything but a
    loopback address (``ipc://`` and ``inproc://`` are local)."""
    if not endpoint.startswith("tcp://"):
        return False
    host = endpoint[len("tcp://") :].rsplit(":", 1)[0].strip("[]")
    return not (host == "localhost" or host == "::1" or host.startswith("127."))


class Background:
    """``fn(*args)`` in a daemon thread; ``result()`` waits for it and returns its value (or
    raises its exception). A node that stops does not wait for it."""

    def __init__(self, name: str, fn, *args):
        self.done = threading.Event()
        self.value: Any = None
        self.error: BaseException | None = None
        threading.Thread(target=self._run, args=(fn, args), name=name, daemon=True).start()

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


class QueryServerNode(Node):
    @dataclass(frozen=True)
    class Params:
        map: str = ""  # the prior Gaussian map (INRIA PLY)
        map_dir: str = "{run_dir}/map"
        views: str = "{run_dir}/views"
        # texts a query must beat unless the request names its own; empty: the aerial vocabulary
        # (query/negatives.py) without the query itself and its near-duplicates
        negatives: tuple[str, ...] = ()
        query_endpoint: str = "tcp://127.0.0.1:5600"
        diagnostics_bind: str = "ipc://{run_dir}/diagnostics.sock"
        map_in: str = "ipc://{run_dir}/map.sock"
        topic_map: str = "map"
        topic_diagnostics: str = "diagnostics"
        stale_after_s: float = 5.0
        server_secret: str = ""  # CURVE: this server's secret key file ("" = no encryption)
        allow_dir: str = ""  # CURVE: folder of allowed client public keys
        max_text_chars: int = 200  # per text, the query's and each negative's
        max_negatives: int = 32  # each costs a text embedding and a cosine per Gaussian and pixel
        queries_per_s: float = 5.0  # per client (CURVE key, else connection), beyond query_burst: "busy"; 0 = no limit
        query_burst: int = 10
        threads: int = 2  # numba threads of heatmap rendering and clustering (0 = one per core)
        # rendered features of recent views, so that the next query on a view is not rendered again
        # (158 MB per 640x480 view at D = 128; a new map version renders anew); 0 = keep none
        heatmap_cache_mb: int = 320
        # a heatmap reply carries the view's heatmap (float32), mask (uint8) and photo (RGB): 8 bytes
        # per pixel, 8.8 MB at 1280x960; a view that would make a larger reply is refused
        max_reply_mb: float = 128.0
        # a view's heatmap, mask and photo are rendered and replied at most this many pixels on
        # their longer side (the view scaled down; box2d on that grid): 4x fewer pixels to render
        # and to send for a 1280x960 view at 640; 0 = the view's own size
        heatmap_max_side: int = 0
        cluster_radius: float = 0.0  # 3D instances: chosen Gaussians closer than this (m) join one; 0 = from the map
        cluster_min_points: int = 20  # ... and an instance has at least this many
        # a query_endpoint other computers can reach needs CURVE (server_secret, allow_dir);
        # true: serve it in clear anyway (a lab network), said in every status the server gives
        insecure: bool = False

    @classmethod
    def validate(cls, params: Params, where: str) -> None:
        from ..params import ParameterError
        from ..transport import curve

        if not (params.cluster_radius >= 0 and params.cluster_min_points >= 1 and params.max_reply_mb > 0):
            raise ParameterError(f"{where}: need cluster_radius >= 0, cluster_min_points >= 1 and max_reply_mb > 0")
        if params.heatmap_max_side < 0:
            raise ParameterError(
                f"{where}: heatmap_max_side must be >= 0 (0: the view's size), got {params.heatmap_max_side}"
            )
        if params.server_secret:
            try:
                curve.check_secret(params.server_secret)
            except (OSError, ValueError) as exc:
                raise ParameterError(f"{where}: server_secret: {exc}") from exc

        if not params.server_secret and is_public(params.query_endpoint) and not params.insecure:
            raise ParameterError(
                f"{where}: query_endpoint {params.query_endpoint} can be reached from other computers, and "
                "without server_secret the link is neither encrypted nor authenticated: set server_secret and "
                "allow_dir (CURVE keys, `olsplat keys`), bind to 127.0.0.1, or set insecure: true"
            )

    def setup(self) -> None:
        from ..query.heatmap import FeatureImages
        from ..query.localize import default_cluster_radius
        from ..scene import read_ply  # heavy imports here and below: the launcher imports node classes

        p = self.params
        self.limit_threads(p.threads)
        self.insecure = not p.server_secret and is_public(p.query_endpoint)  # allowed by `insecure: true` only
        if self.insecure:
            log.warning("INSECURE: %s is served without CURVE (insecure: true)", p.query_endpoint)
        self.gaussians = read_ply(p.map)
        # from the prior map's density once (~30 ms for 390k Gaussians): not again for every query
        self.cluster_radius = p.cluster_radius or default_cluster_radius(self.gaussians.means, p.cluster_min_points)
        # the map's centres sorted by voxel once (~1.5 s for 5M, in the warm-up thread, not delaying
        # start-up): a query's clustering then skips its own sort; until then it sorts
        self.voxel_index: VoxelIndex | None = None
        self.language_map: LanguageMap | None = None
        self.features: QueryFeatures | None = None  # the map's features as queries use them
        self.version = 0
        self.encoders: dict[str, Any] = {}  # encoder spec -> loaded encoder
        self.views: list = []  # aggregate.SavedView, re-read when the run's views folder grows
        self.browser_splats: BrowserSplats | None = None  # the last SplatsRequest's decimation
        self.browser_splats_max = 0  # ... and its max_splats
        self.map_record: dict = {}  # latest.json's record of the loaded map (views, final)
        self.map_observed = 0  # Gaussians the loaded map observed
        self.feature_images = FeatureImages(p.heatmap_cache_mb * 2**20)
        keys = curve.ServerKeys(p.server_secret, p.allow_dir) if p.server_secret else None
        self.server = self.own(
            QueryServer(
                self.context,
                p.query_endpoint,
                keys=keys,
                max_bytes=REQUEST_MAX_BYTES,
                queries_per_s=p.queries_per_s or None,
                burst=p.query_burst,
            )
        )
        self.collector = self.own(
            DiagnosticsCollector(self.context, p.diagnostics_bind, p.stale_after_s, topic=p.topic_diagnostics)
        )
        self.maps = self.own(Subscriber(self.context, [p.map_in], [p.topic_map], hwm=100, max_bytes=CONTROL_MAX_BYTES))
        self.warm_up = threading.Thread(target=self._warm_up, name=f"{self.name}-warm-up", daemon=True)
        self.warm_up.start()
        self.reservation: threading.Thread | None = None  # touches the heatmap cache, once views exist
        self.encoder_lock = threading.Lock()  # a query and the warm query may ask for the encoder at once
        self.warm_query: Background | None = None  # the first map's query in the background, once
        self._load_latest()
        self.last_check = time.monotonic()

    def teardown(self) -> None:
        # the warm-up and the warm query run numba kernels in the background (seconds, minutes on
        # a cold cache): a stopped node does not leave them running in a process that goes on
        # (composed launches, tests)
        if getattr(self, "warm_up", None) is not None:
            self.warm_up.join(120)
        reservation = getattr(self, "reservation", None)
        if reservation is not None:
            reservation.join(120)
        warm_query = getattr(self, "warm_query", None)
        if warm_query is not None:
            warm_query.done.wait(120)

    def spin(self) -> int | None:
        request = self.server.poll(100)
        if request is not None:
            identity, message = request
            self.server.reply(identity, self._answer(message))
        self.collector.poll(0)
        announced = []
        for _, update in self.maps.drain(0):
            if isinstance(update, MapUpdated):
                announced.append(update.version)
            else:
                self.unexpected(update, self.params.topic_map)
        if (announced and max(announced) > self.version) or time.monotonic() - self.last_check > 2.0:
            self._load_latest()
            self.last_check = time.monotonic()
        return None

    def _warm_up(self) -> None:
        """Compile the query kernels (numba: 3D clustering, feature rendering) on small inputs
        while the node already serves: on a fresh install the first real query would
        otherwise pay 10-40 s of compilation and time out at the ground station."""
        from ..query.heatmap import render_feature_map
        from ..query.localize import VoxelIndex, instances_in_3d

        try:
            start = time.perf_counter()
            points = np.random.default_rng(0).uniform(0.0, 5.0, (500, 3))
            instances_in_3d(points, np.ones(len(points), bool))
            camera = self._warm_up_camera()
            render_feature_map(self.gaussians, np.zeros((len(self.gaussians), 1), np.float32), camera)
            index = VoxelIndex.build(self.gaussians.means, self.cluster_radius)
            # the index's own path (its centres in the map's float type) compiled before it serves
            instances_in_3d(
                self.gaussians.means, np.arange(min(1000, len(self.gaussians))), self.cluster_radius, index=index
            )
            self.voxel_index = index
            log.info("query kernels and the voxel index ready in %.1f s", time.perf_counter() - start)
        except Exception:  # a warm-up failure must not take the server down; the query will say more
            log.exception("warm-up failed")

    def _warm_up_camera(self):
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

    def _load_latest(self) -> None:
        from ..query.answer import QueryFeatures
        from ..storage import LanguageMap, latest_map

        record = latest_map(self.params.map_dir)
        if record is None or record["version"] <= self.version:
            return
        try:
            language_map = LanguageMap.load(record["path"], decode=False)  # a codebook map stays codes
        except OlsplatInputError as exc:  # replaced between reading latest.json and the file: next time
            log.warning("map version %d not loaded: %s", record["version"], exc)
            return
        if len(language_map) != len(self.gaussians):
            log.error(
                "map version %d has %d Gaussians, the prior map %d: ignored",
                record["version"],
                len(language_map),
                len(self.gaussians),
            )
            return
        self.features = None  # the old version's rows go before the new ones are made (peak memory)
        self.features = QueryFeatures.of(language_map)  # once, not per query
        if self.voxel_index is not None:  # else the first query after the index makes them
            self.features.rows_in_order(self.voxel_index)
        language_map.features = np.zeros((0, self.features.table.shape[1]), np.float32)  # held once, above
        self.language_map, self.version = language_map, record["version"]
        self.map_record, self.map_observed = record, int(np.count_nonzero(language_map.observed))
        log.info("map version %d loaded (%d views)", self.version, record["views"])
        if self.reservation is None and self.params.heatmap_cache_mb > 0:
            self._reserve_heatmap_cache(self.features.table.shape[1])
        if self.warm_query is None:
            self.warm_query = Background(
                f"{self.name}-warm-query", self._warm_query, language_map, self.features, self.cluster_radius
            )

    def _warm_query(self, language_map, features, radius: float) -> float:
        """A query on the first map loaded, in the background, once: the text encoder is loaded,
        the relevance and clustering kernels come out of numba's cache and the map's rows are
        paged in, so that the operator's first query is not the one that pays for it (~0.3 s on
        the large map: the encoder 0.12 s, the first relevance + instances 0.2 s against 0.08).
        It waits for the warm-up's voxel index, and also renders a small heatmap with the map's
        own feature table (the kernel a heatmap query takes). Status value ``query_warm``: 1 once
        it is done. Returns its seconds."""
        from ..query.answer import answer_query

        self.warm_up.join()
        start = time.perf_counter()
        try:
            answer_query(
                language_map,
                self.gaussians,
                self._encoder(language_map),
                "warm-up",
                ["object", "things"],
                camera=self._warm_up_camera(),
                features=features,
                cluster_radius=radius,
                min_points=self.params.cluster_min_points,
                voxel_index=self.voxel_index,
            )
        except Exception:  # the query itself will say more; a warm-up failure must not stop the server
            log.exception("warm query failed")
        seconds = time.perf_counter() - start
        log.info("first map queried in the background in %.2f s", seconds)
        return seconds

    def _encoder(self, language_map):
        """The text encoder of a map's features, loaded once (``CachedTexts``)."""
        from ..query.answer import CachedTexts, encoder_for_map

        with self.encoder_lock:
            if language_map.encoder not in self.encoders:
                self.encoders[language_map.encoder] = CachedTexts(encoder_for_map(language_map))
            return self.encoders[language_map.encoder]

    def _reserve_heatmap_cache(self, dim: int) -> None:
        """Touch the heatmap cache's memory in the background, sized by the newest view: the
        first heatmap of a view then writes into memory already paged in (first-touched memory
        costs as much as the rendering on a small VM)."""
        from ..storage import load_views

        views = load_views(self.params.views)
        if not views:
            return
        camera = views[-1].camera
        self.reservation = threading.Thread(
            target=self.feature_images.reserve,
            args=(camera.width * camera.height, dim),
            name=f"{self.name}-reserve",
            daemon=True,
        )
        self.reservation.start()

    def _answer(self, message):
        start = time.perf_counter()
        self.stats.count("received")
        if isinstance(message, StatusRequest):
            return StatusReply(
                stamp_ns=time.time_ns(), request_id=message.request_id, nodes=self._statuses(), map_version=self.version
            )
        if isinstance(message, SplatsRequest):
            return self._splats(message)
        if isinstance(message, ViewsRequest):
            return self._view_poses(message)
        if not isinstance(message, QueryRequest):  # a well-formed message of another kind
            self.stats.count("bad_messages")
            return QueryReply(
                stamp_ns=time.time_ns(),
                request_id=getattr(message, "request_id", ""),
                status="bad_request",
                message=f"{type(message).__name__} is not a request",
            )
        reply = self._query(message)
        reply.seconds = time.perf_counter() - start
        self.stats.handled(0, reply.seconds)
        return reply

    def _decimation(self, max_splats: int) -> BrowserSplats:
        """The prior map decimated to ``max_splats`` (the last one kept: a ground station asks
        for one size, then queries for it)."""
        from ..query.splats import browser_splats

        if self.browser_splats is None or self.browser_splats_max != max_splats:
            self.browser_splats = browser_splats(self.gaussians, max_splats)
            self.browser_splats_max = max_splats
        return self.browser_splats

    def _splats(self, request: SplatsRequest) -> SplatsReply:
        from ..query.splats import MAX_SPLATS, pack_splats

        if not 1 <= request.max_splats <= MAX_SPLATS:
            return SplatsReply(
                stamp_ns=time.time_ns(),
                request_id=request.request_id,
                status="bad_request",
                message=f"max_splats must be 1..{MAX_SPLATS:,}, got {request.max_splats:,}",
                total=len(self.gaussians),
            )
        splats = self._decimation(request.max_splats)
        return SplatsReply(
            stamp_ns=time.time_ns(),
            frame_id="map",
            request_id=request.request_id,
            message=splats.caption,
            total=len(self.gaussians),
            **pack_splats(splats),  # type: ignore[arg-type]  # array fields only
        )

    def _current_views(self) -> list:
        from ..storage import load_views

        if len(self.views) != sum(1 for _ in Path(self.params.views).glob("*.json")):
            self.views = load_views(self.params.views)  # views are only ever added
        return self.views

    def _view_poses(self, request: ViewsRequest) -> ViewsReply:
        views = self._current_views()
        start = max(0, request.start)
        return ViewsReply(
            stamp_ns=time.time_ns(),
            frame_id="map",
            request_id=request.request_id,
            start=start,
            total=len(views),
            views=[view_pose(v.camera) for v in views[start : start + VIEWS_PER_REPLY]],
        )

    def _query(self, request: QueryRequest) -> QueryReply:
        from ..query.answer import answer_query
        from ..query.negatives import vocabulary_negatives
        from ..query.splats import MAX_SPLATS, relevance_margin
        from ..scene import select_view

        def refuse(status: str, text: str) -> QueryReply:
            return QueryReply(
                stamp_ns=time.time_ns(),
                request_id=request.request_id,
                status=status,
                message=text,
                text=request.text,
                view=request.view,
                map_version=self.version,
            )

        text = request.text.strip()
        if not text:
            return refuse("bad_request", "the query text is empty")
        if len(text) > self.params.max_text_chars:
            return refuse("bad_request", f"the query text is longer than {self.params.max_text_chars} characters")
        if len(request.negatives) > self.params.max_negatives:
            return refuse(
                "bad_request", f"{len(request.negatives)} negatives; at most {self.params.max_negatives} per query"
            )
        if any(len(n) > self.params.max_text_chars for n in request.negatives):
            return refuse("bad_request", f"a negative is longer than {self.params.max_text_chars} characters")
        if not 0 <= request.splats <= MAX_SPLATS:
            return refuse("bad_request", f"splats must be 0..{MAX_SPLATS:,}, got {request.splats:,}")
        if self.language_map is None:
            return refuse("no_map", "no map yet: no view has been aggregated and refined")
        try:
            views = self._current_views()
            camera = select_view([v.camera for v in views], request.view) if request.view else None
            image = views[[v.camera for v in views].index(camera)].image() if camera is not None else None
            if camera is not None and image is not None:
                camera, image = self._reply_size(camera, image)
            if camera is not None and request.heatmap:
                reply_mb = camera.width * camera.height * 8 / 2**20
                if reply_mb > self.params.max_reply_mb:
                    return refuse(
                        "bad_request",
                        f"view {camera.name} is {camera.width}x{camera.height}: its heatmap reply would be "
                        f"{reply_mb:.1f} MB, over max_reply_mb {self.params.max_reply_mb:g}",
                    )
            encoder = self._encoder(self.language_map)
            negatives = list(request.negatives or self.params.negatives) or vocabulary_negatives(text, encoder)
            threshold = request.threshold if math.isfinite(request.threshold) else None  # NaN: beat the negatives
            answer = answer_query(
                self.language_map,
                self.gaussians,
                encoder,
                text,
                negatives,
                camera,
                threshold,
                images=self.feature_images if self.params.heatmap_cache_mb > 0 else None,
                image_key=(self.version, camera.name, camera.width) if camera is not None else None,
                cluster_radius=self.cluster_radius,
                min_points=self.params.cluster_min_points,
                features=self.features,
                voxel_index=self.voxel_index,
            )
        except OlsplatInputError as exc:
            return refuse("bad_request", str(exc))
        if not request.heatmap:
            answer.heatmap = answer.mask = None
            image = None
        reply = reply_for(answer, request, self.version, image, 0.0)
        if request.splats:  # the page's colours: per splat of its decimation, in its order
            splats = self._decimation(request.splats)
            embeddings = encoder.encode_text([answer.text, *answer.negatives])
            margin = relevance_margin(self.features, self.language_map.observed, splats.ids, embeddings)
            reply.splat_margin = margin.astype(np.float16)
        return reply

    def _reply_size(self, camera, image: np.ndarray):
        """(camera, photo) of a view at the reply's size: scaled down to ``heatmap_max_side`` on
        the longer side (the photo by area averaging), or as they are."""
        import cv2

        side = self.params.heatmap_max_side
        if side <= 0 or max(camera.width, camera.height) <= side:
            return camera, image
        small = camera.scaled(side / max(camera.width, camera.height))
        return small, cv2.resize(image, (small.width, small.height), interpolation=cv2.INTER_AREA)

    def _values(self) -> dict:
        """This node's own status values: its counters and those of its three sockets;
        ``bad_messages`` counts bad input on any of them (as every other node reports it)."""
        server, collector, maps = self.server, self.collector, self.maps
        values = self.stats.values(
            **server.stats,  # requests, bad_requests, replies, dropped_replies, auth_failures
            **{f"diagnostics_{k}": collector.stats[k] for k in ("received", "bad_messages", "gaps")},
            **{f"map_{k}": maps.stats[k] for k in ("received", "bad_messages", "gaps", "reconnects")},
            heatmap_cache_hits=self.feature_images.hits,
            heatmap_cache_misses=self.feature_images.misses,
            heatmap_cache_mb=round(self.feature_images.bytes / 2**20, 1),
            # the loaded map, for a ground station's status panel
            map_version=self.version,
            map_views=int(self.map_record.get("views", 0)),
            map_observed=self.map_observed,
            map_final=int(bool(self.map_record.get("final", False))),
            # 1 once the warm-up has made the voxel index: 3D instances at full speed from then on
            query_index_ready=int(self.voxel_index is not None),
            # 1 once the first map has been queried in the background: the operator's first query
            # does not load the text encoder or the kernels (``_warm_query``)
            query_warm=int(self.warm_query is not None and self.warm_query.done.is_set()),
        )
        values["bad_messages"] = (
            self.stats.counts["bad_messages"]
            + server.stats["bad_requests"]
            + collector.stats["bad_messages"]
            + collector.stats["unexpected"]
            + maps.stats["bad_messages"]
        )
        return values

    def _statuses(self) -> list[dict]:
        """This node's own status first, then every other node's latest (STALE when silent)."""
        own = {
            "node": self.name,
            "level": 1 if self.insecure else 0,
            "message": (f"INSECURE: {self.params.query_endpoint} is served without CURVE; " if self.insecure else "")
            + f"map version {self.version}",
            "values": self._values(),
            "age_s": 0.0,
        }
        return [own, *self.collector.nodes()]
