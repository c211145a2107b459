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
``allow_dir``): other clients get no answer at all, and each client's queries are rate-limited.

Thin: the map, its caches, the warm-ups and the answers are ``query.service.MapService``'s;
here are the sockets, the requests and replies, and the node's status.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

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

from ..transport import CONTROL_MAX_BYTES, REQUEST_MAX_BYTES, DiagnosticsCollector, QueryServer, Subscriber, curve
from ..transport.convert import reply_for, view_pose
from .base import Node

if TYPE_CHECKING:  # imported at run time in setup: the launcher imports node classes
    from ..query.service import MapAnswer, MapService

log = logging.getLogger(__name__)
VIEWS_PER_REPLY = 500  # ViewPose records per ViewsReply (~150 kB): a long flight comes in pages


def is_public(endpoint: str) -> bool:
    """Whether a ZeroMQ bind endpoint can be reached from other computers: tcp on anything but a
    loopback address (``ipc://`` and ``inproc://`` are local)."""
    if not endpoint.startswith("tcp://"):
        return False
    host = endpoint[len("tcp://") :].rsplit(":", 1)[0].strip("[]")
    return not (host == "localhost" or host == "::1" or host.startswith("127."))


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
        # an aggregate's per-flight maps (OUT/flights of olsplat aggregate --per-flight): a request
        # naming `since` (an earlier flight) is answered against the newest one; "" = none
        flights: str = ""
        # the change rule's cuts for such a request, "C,O,N[,A]" as `olsplat query --change-cuts`
        # (candidate cut, object cut, fewest Gaussians, least m²): "" = the defaults, chosen on
        # 60-view flights; shorter flights and sparser maps need looser ones (docs/method.md)
        change_cuts: str = ""  # what changed (no text)
        text_change_cuts: str = ""  # a text's changes ("new vehicles")

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
        from ..query.change import TEXT_PARAMS, ChangeParams

        for name, base in (("change_cuts", ChangeParams()), ("text_change_cuts", TEXT_PARAMS)):
            if getattr(params, name):
                try:
                    base.with_cuts(getattr(params, name))
                except ValueError as exc:
                    raise ParameterError(f"{where}: {name}: {exc}") from exc
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
        p = self.params
        self.limit_threads(p.threads)
        self.insecure = not p.server_secret and is_public(p.query_endpoint)  # allowed by `insecure: true` only
        if self.insecure:
            log.warning("INSECURE: %s is served without CURVE (insecure: true)", p.query_endpoint)
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
        # after the sockets: a node that cannot bind starts no background work
        self.service = self._service()
        self.service.refresh(views=False)  # a late joiner: the newest map at once
        self.last_check = time.monotonic()

    def _service(self) -> MapService:
        from ..query.service import MapService  # heavy imports here: the launcher imports node classes

        p = self.params
        return MapService(
            p.map,
            p.map_dir,
            p.views,
            cluster_radius=p.cluster_radius,
            cluster_min_points=p.cluster_min_points,
            heatmap_cache_mb=p.heatmap_cache_mb,
            negatives=p.negatives,
            max_text_chars=p.max_text_chars,
            max_negatives=p.max_negatives,
            max_reply_mb=p.max_reply_mb,
            heatmap_max_side=p.heatmap_max_side,
            flights_dir=p.flights,
            change_cuts=p.change_cuts,
            text_change_cuts=p.text_change_cuts,
            name=self.name,
        )

    def teardown(self) -> None:
        if getattr(self, "service", None) is not None:
            self.service.close()  # joins the warm-up, the reservation and the warm query

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
        # the views are re-read when a request needs them, not here
        if (announced and max(announced) > self.service.version) or time.monotonic() - self.last_check > 2.0:
            self.service.refresh(views=False)
            self.last_check = time.monotonic()
        return None

    def _answer(self, message):
        start = time.perf_counter()
        self.stats.count("received")
        if isinstance(message, StatusRequest):
            return StatusReply(
                stamp_ns=time.time_ns(),
                request_id=message.request_id,
                nodes=self._statuses(),
                map_version=self.service.version,
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

    def _splats(self, request: SplatsRequest) -> SplatsReply:
        from ..query.splats import MAX_SPLATS, pack_splats

        total = len(self.service.gaussians)
        if not 1 <= request.max_splats <= MAX_SPLATS:
            return SplatsReply(
                stamp_ns=time.time_ns(),
                request_id=request.request_id,
                status="bad_request",
                message=f"max_splats must be 1..{MAX_SPLATS:,}, got {request.max_splats:,}",
                total=total,
            )
        splats = self.service.splats(request.max_splats)
        return SplatsReply(
            stamp_ns=time.time_ns(),
            frame_id="map",
            request_id=request.request_id,
            message=splats.caption,
            total=total,
            **pack_splats(splats),  # type: ignore[arg-type]  # array fields only
        )

    def _view_poses(self, request: ViewsRequest) -> ViewsReply:
        cameras = self.service.cameras()
        start = max(0, request.start)
        return ViewsReply(
            stamp_ns=time.time_ns(),
            frame_id="map",
            request_id=request.request_id,
            start=start,
            total=len(cameras),
            views=[view_pose(c) for c in cameras[start : start + VIEWS_PER_REPLY]],
        )

    def _query(self, request: QueryRequest) -> QueryReply:
        if request.since and request.preview:
            return _no_answer(request, "bad_request", "a change query has no preview: ask without it",
                              self.service.version)  # fmt: skip
        if request.since:
            return self._change_query(request)
        result: MapAnswer = self.service.answer(
            request.text,
            request.negatives,
            view=request.view,
            threshold=request.threshold,  # NaN: beat the negatives
            heatmap=request.heatmap,
            splats=request.splats,
            preview=request.preview,
        )
        if result.answer is None:
            return _no_answer(request, result.status, result.message, result.version)
        reply = reply_for(result.answer, request, result.version, result.photo, 0.0, self.service.georef)
        if request.preview:
            assert result.camera is not None
            reply.preview = True
            reply.message = (
                f"preview of view {result.camera.name} at {result.camera.width}x{result.camera.height}: "
                "the 3D instances come with the full answer"
            )
        if result.margin is not None:  # the page's colours, per splat of its decimation
            reply.splat_margin = result.margin.astype(np.float16)
        return reply

    def _change_query(self, request: QueryRequest) -> QueryReply:
        """What changed since flight ``request.since`` (``MapService.answer_change``): the change
        instances as 3D ``Instance`` records with their median scores in ``change_scores``; with a
        view, the change heatmap (score, 0 where not scored), its mask and regions."""
        from ..query.answer import QueryAnswer

        result = self.service.answer_change(
            request.text, request.since, request.gone, request.negatives, view=request.view
        )
        change = result.change
        if change is None:
            return _no_answer(request, result.status, result.message, result.version)
        heatmap = change.heatmap if request.heatmap else None
        as_query = QueryAnswer(
            change.text or "",
            change.negatives,
            change.candidates,
            list(change.instances),
            heatmap=None if heatmap is None else np.nan_to_num(heatmap, nan=0.0).astype(np.float32),
            mask=result.change_mask if request.heatmap else None,
            regions=result.change_regions,
        )
        reply = reply_for(as_query, request, result.version, result.photo, 0.0, self.service.georef)
        reply.message = (
            f"{change.title} since flight {result.since} (now {result.now}): {change.scored:,} Gaussians seen well "
            f"enough by both flights, {change.candidates:,} candidates"
            + (f"; the move must favour the text over: {', '.join(change.negatives)}" if change.negatives else "")
        )
        reply.since, reply.now = result.since, result.now
        reply.change_scores = np.array([i.score for i in change.instances], np.float32)
        return reply

    def _values(self) -> dict:
        """This node's own status values: its counters, those of its three sockets and the
        service's (the heatmap cache, the loaded map, the warm-ups); ``bad_messages`` counts bad
        input on any socket (as every other node reports it)."""
        server, collector, maps = self.server, self.collector, self.maps
        values = self.stats.values(
            **server.stats,  # requests, bad_requests, replies, dropped_replies, auth_failures
            **{f"diagnostics_{k}": collector.stats[k] for k in ("received", "bad_messages", "gaps")},
            **{f"map_{k}": maps.stats[k] for k in ("received", "bad_messages", "gaps", "reconnects")},
            **self.service.status_values(),
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
            + f"map version {self.service.version}",
            "values": self._values(),
            "age_s": 0.0,
        }
        return [own, *self.collector.nodes()]


def _no_answer(request: QueryRequest, status: str, message: str, version: int) -> QueryReply:
    """The reply to a request the map could not answer (``status`` other than "ok"): the request's
    text, view and flight echoed, the reason in ``message``."""
    return QueryReply(
        stamp_ns=time.time_ns(),
        request_id=request.request_id,
        status=status,
        message=message,
        text=request.text,
        view=request.view,
        map_version=version,
        since=request.since,
    )
