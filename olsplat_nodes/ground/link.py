"""What the ground page shows, asked of a running graph over the ground link (the query
server's endpoint, CURVE when keys are given): node statuses, the map version, the prior map
as splats (once), the aggregated views' cameras (as they come) and the answers to queries,
with each splat's relevance computed on the drone (``QueryRequest.splats``).

The same interface as ``review.RunReview``: ``splats``, ``state``, ``refresh()``, ``cameras()``,
``ask()``, ``status_rows()``. A silent link is a state the page shows ("link lost - retrying"),
never an exception; the client holds the keys, the browser never sees them.
"""

from __future__ import annotations

import time
import uuid

import numpy as np

from olsplat_msgs import (
    QueryReply,
    QueryRequest,
    SplatsReply,
    SplatsRequest,
    StatusReply,
    StatusRequest,
    ViewsReply,
    ViewsRequest,
)

from ..query.geojson import from_records
from ..query.localize import Instance3D
from ..query.service import MapState
from ..query.splats import BrowserSplats, unpack_splats
from ..scene import Camera
from .review import WebAnswer, map_row, prepared_query, view_pictures

LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


def node_row(node: dict) -> tuple[str, str, str]:
    """A ``StatusReply`` node (a ``DiagnosticStatus`` as a map, plus ``age_s``) as a status row."""
    v = node.get("values", {}) or {}
    drops = int(v.get("dropped", 0) or 0) + int(v.get("gaps", 0) or 0)
    rate, latency, age = (float(x or 0) for x in (v.get("rate_hz"), v.get("latency_ms"), node.get("age_s")))
    text = f"{node.get('message', '')}; {rate:.2f} Hz, latency {latency:.0f} ms, drops {drops}, heard {age:.0f} s ago"
    return str(node.get("node", "?")), LEVELS.get(int(node.get("level", 0) or 0), str(node.get("level"))), text


class LinkSource:
    """The page's source over the ground link. ``client`` is a ``transport.QueryClient`` (its
    ``ask`` gives a reply or None after its timeout; the sockets stay in the transport layer);
    ``max_splats`` the browser decimation asked for."""

    def __init__(self, client, max_splats: int):
        self.client = client
        self.endpoint = client.endpoint
        self.secure = client.keys is not None
        self.max_splats = int(max_splats)
        self.splats: BrowserSplats | None = None
        self.state = MapState(0, 0, False, 0)
        self.nodes: list[dict] = []
        self.link_problem: str | None = f"connecting to {self.endpoint} ..."
        self._cameras: list[Camera] = []

    def _request(self, message, expected: type):
        """The reply to ``message`` if it is an ``expected``; None (and ``link_problem`` set)
        when the link is silent or the server answers something else."""
        message.request_id = uuid.uuid4().hex[:12]
        unreadable = self.client.stats["bad_replies"]
        reply = self.client.ask(message)
        if reply is None:
            self.link_problem = (
                f"link lost - retrying: {self.endpoint} did not answer within {self.client.timeout_s:g} s"
                + (" (are the CURVE keys the right pair?)" if self.secure else "")
            )
            if self.client.stats["bad_replies"] > unreadable:  # it answered, in a form we cannot read
                self.link_problem = (
                    f"{self.endpoint} answers in a form this ground station cannot read "
                    "(another olsplat version?): see this process's log - retrying"
                )
            return None
        if not isinstance(reply, expected):  # an older server, or a refusal without our message
            detail = getattr(reply, "message", "")
            self.link_problem = f"{self.endpoint} answered {type(reply).__name__} {detail}".strip()
            return None
        self.link_problem = None
        return reply

    def refresh(self) -> bool:
        """Ask for the status; then the prior map (until it came) and new views. True when the
        map version, the splats or the views changed."""
        status = self._request(StatusRequest(), StatusReply)
        if status is None:
            return False
        self.nodes = list(status.nodes)
        own: dict = next((n.get("values", {}) for n in self.nodes if "map_views" in n.get("values", {})), {})
        state = MapState(
            int(status.map_version),
            int(own.get("map_views", 0)),
            bool(own.get("map_final", 0)),
            int(own.get("map_observed", 0)),
        )
        changed = state.version != self.state.version
        self.state = state
        if self.splats is None:
            reply = self._request(SplatsRequest(max_splats=self.max_splats), SplatsReply)
            if reply is None:
                return changed
            if reply.status != "ok":
                self.link_problem = f"the prior map was refused: {reply.status}: {reply.message}"
                return changed
            self.splats = unpack_splats(reply.centers, reply.covariances, reply.rgbs, reply.opacities, reply.total)
            changed = True
        return self._fetch_views() or changed

    def _fetch_views(self) -> bool:
        from ..transport.convert import camera_of_pose

        before = len(self._cameras)
        while True:
            reply = self._request(ViewsRequest(start=len(self._cameras)), ViewsReply)
            if reply is None or reply.start != len(self._cameras) or not reply.views:
                break
            self._cameras += [camera_of_pose(v) for v in reply.views]
            if len(self._cameras) >= reply.total:
                break
        return len(self._cameras) != before

    def cameras(self) -> list[Camera]:
        return list(self._cameras)

    def ask(self, text: str, negatives: list[str], view: str = "", preview: bool = False) -> WebAnswer:
        """The drone's answer as the page shows it; bad input, no map, a silent link and a
        refusal come back as a status with a sentence. ``preview`` (with a view): the view's
        pictures alone, small (``QueryRequest.preview``)."""
        start = time.perf_counter()
        text, negatives, problem = prepared_query(text, negatives)
        if problem:
            return WebAnswer("bad_request", problem, text)
        if self.splats is None:
            return WebAnswer("no_map", "the prior map has not come from the drone yet", text)
        preview = preview and bool(view)
        request = QueryRequest(
            text=text, view=view, heatmap=bool(view), negatives=negatives, splats=self.max_splats, preview=preview
        )
        reply = self._request(request, QueryReply)
        if reply is None:
            return WebAnswer("timeout", f"no answer: {self.link_problem}", text)
        if reply.status != "ok":
            return WebAnswer(reply.status, reply.message, text, reply.map_version)
        margin = None if reply.splat_margin is None else np.asarray(reply.splat_margin, np.float32)
        if not preview and (margin is None or len(margin) != len(self.splats.centers)):
            return WebAnswer("error", "the drone's splats differ from the page's: reload the page", text)
        instances = [
            Instance3D(tuple(i["box_min"]), tuple(i["box_max"]), tuple(i["centroid"]), int(i["n_gaussians"]))
            for i in reply.instances
            if i["kind"] == "3d"
        ]
        result = WebAnswer(
            "ok",
            reply.message if preview else f"{reply.message}; {len(instances)} instances in 3D",
            text,
            reply.map_version,
            margin,
            instances,
            located=from_records(reply.instances),
            height_ref=reply.height_ref,
            preview=preview,
        )
        if view and reply.heatmap is not None and reply.mask is not None and reply.image is not None:
            boxes = [tuple(i["box2d"]) for i in reply.instances if i["kind"] == "2d"]
            valid = np.asarray(reply.heatmap) != 0  # the server sends 0 where nothing was rendered
            result.view = reply.view
            result.heatmap_picture, result.mask_picture = view_pictures(
                reply.image, reply.heatmap, valid, reply.mask, boxes, text, reply.view, reply.map_version
            )
        result.seconds = time.perf_counter() - start
        return result

    def status_rows(self) -> list[tuple[str, str, str]]:
        """(what, level, text) rows: the link, the map, the views, then every node as the query
        server reports it (the last heard, shown STALE, while the link is lost)."""
        security = "CURVE" if self.secure else "no encryption"
        link = (
            ("link", "ERROR", self.link_problem)
            if self.link_problem
            else ("link", "OK", f"{self.endpoint} ({security})")
        )
        rows = [
            link,
            map_row(self.state, "on the drone"),
            ("views", "OK" if self._cameras else "WARN", f"{len(self._cameras)} aggregated"),
        ]
        for node in self.nodes:
            name, level, text = node_row(node)
            rows.append((name, "STALE", f"last heard: {text}") if self.link_problem else (name, level, text))
        return rows
