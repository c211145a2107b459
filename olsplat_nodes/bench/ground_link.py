"""The benchmarks' ground-station side: status samples and query latency over the real link.

Shared by ``bench graph``'s flight (``graph.py``), which launches the replay graph and reads the
nodes' diagnostics through the query server, and its ``--queries-only`` (``requery.py``): both
end with the same ground-station queries on the final map (relevance of every Gaussian with 3D
instances; heatmaps of views, the first query on a view rendering it and the next ones answered
from the server's cache).
"""

from __future__ import annotations

import time
import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import RunFailed


def percentiles(seconds: list[float]) -> str:
    ms = 1000 * np.asarray(seconds)
    return f"p50 {np.percentile(ms, 50):7.1f} ms  p95 {np.percentile(ms, 95):7.1f} ms  ({len(ms)} queries)"


def sample_status(client, samples: dict[str, list[dict]]):
    """Ask the query server for the graph's status and keep every node's values in ``samples``;
    the StatusReply, or None when it did not answer in time."""
    from olsplat_msgs import StatusRequest

    from ..transport import NoReply

    try:
        status = client.request(StatusRequest(request_id=uuid.uuid4().hex[:8]))
    except NoReply:
        return None
    for node in status.nodes:
        samples.setdefault(node["node"], []).append(node["values"])
    return status


def final_map(supervisor, thread, run_dir: Path) -> dict | None:
    """The run's final map record (``latest.json``), or None while the flight goes on. Raises
    RunFailed when no final map can come: the launch has ended (``thread``, running
    ``supervisor.run``), or the ingest has finished without one. The ingest exits 0 only after
    the refiner announced the final map, which the refiner writes first; so a finished ingest
    and no final snapshot mean the stream ended with no view aggregated (every frame dropped,
    or none in the source)."""
    from ..storage.snapshot import latest_map

    record = latest_map(run_dir / "map")
    if record is not None and record.get("final"):
        return record
    logs = run_dir / "logs"
    if not thread.is_alive():
        raise RunFailed(f"the launch ended before the final map; see {logs}")
    if supervisor.states.get("ingest") == "finished":
        record = latest_map(run_dir / "map")  # the ingest may have ended since the first look
        if record is not None and record.get("final"):
            return record
        raise RunFailed(
            "the ingest ended its stream and no view was aggregated: the source has no frame, or every "
            f"frame was dropped (a lossy stream faster than the graph); see {logs}"
        )
    return None


QUERY_KINDS = {
    "relevance": "relevance",
    # the query server's own time (QueryReply.seconds) for each kind below: the rest of a round
    # trip is the reply's encoding, the link and the decoding
    "relevance_server": "relevance",
    "heatmap": "heatmap",
    "heatmap_first": "heatmap, first query on its view",
    "heatmap_repeat": "heatmap, next queries on the view",
    "heatmap_first_server": "heatmap, first query on its view",
    # each heatmap query is preceded by its preview (QueryRequest.preview), as the page asks them
    "heatmap_preview": "preview heatmap (<= 320 px)",
    "heatmap_preview_first": "preview, first query on its view",
}


def pick_views(names: list[str], count: int, spread: bool) -> list[str]:
    """The ``count`` views heatmap queries ask for: the flight's first ones, or with ``spread``
    views evenly spaced from its first to its last (a survey's far views cost more: more of the
    map in view)."""
    if not spread or count <= 1 or count >= len(names):
        return names[:count]
    return [names[round(k * (len(names) - 1) / (count - 1))] for k in range(count)]


def time_queries(
    client, scene: Path, run_dir: Path, relevance: int, heatmaps: int, heatmap_views: int, spread: bool = False
) -> dict[str, list]:
    """Round-trip seconds per kind (``QUERY_KINDS``) of ``relevance`` queries without a view and
    ``heatmaps`` queries spread over ``heatmap_views`` views of the run (``pick_views``), each
    asked as the ground station page asks it: its preview first, then the full answer; each text
    one of the scene's labels with the others as negatives, and under ``"heatmap_views"`` the
    names of the views asked for. Raises RunFailed on a refusal.
    Waits first (up to 60 s) until the query server has loaded the run's newest map: the
    refiner writes it before the server hears of it (announcement, or its 2 s look at
    ``latest.json``), and a query in between is answered ``no_map`` or from an older version."""
    from olsplat_msgs import QueryRequest

    from ..evaluate.scene_eval import label_texts, load_queries
    from ..storage.snapshot import latest_map
    from ..storage.views import load_views

    newest = latest_map(run_dir / "map")
    deadline = time.monotonic() + 60.0
    while newest is not None:
        status = sample_status(client, {})
        if status is not None and status.map_version >= newest["version"]:
            break
        if time.monotonic() > deadline:
            raise RunFailed(f"the query server did not load map version {newest['version']} within 60 s")
        time.sleep(0.2)
    labels, queries = load_queries(scene)
    texts = label_texts(labels, queries)
    views = pick_views([v.camera.name for v in load_views(run_dir / "views")], heatmap_views, spread)
    per_view = max(1, heatmaps // max(1, len(views)))
    plan = [("relevance", "", i) for i in range(relevance)]
    plan += [("heatmap", view, i) for view in views for i in range(per_view)]
    times: dict[str, list] = {kind: [] for kind in QUERY_KINDS}
    times["heatmap_views"] = views
    for kind, view, i in plan:
        text = texts[i % len(texts)]
        request = QueryRequest(
            request_id=uuid.uuid4().hex[:8],
            text=text,
            view=view,
            heatmap=bool(view),
            threshold=float("nan"),
            negatives=[t for t in texts if t != text],
        )
        if kind == "heatmap":
            start = time.perf_counter()
            preview = client.request(replace(request, request_id=f"{request.request_id}p", preview=True))
            seconds = time.perf_counter() - start
            if preview.status != "ok" or not preview.preview:
                raise RunFailed(f"preview {text!r}: {preview.status}: {preview.message}")
            times["heatmap_preview"].append(seconds)
            if i == 0:
                times["heatmap_preview_first"].append(seconds)
        start = time.perf_counter()
        reply = client.request(request)
        seconds = time.perf_counter() - start
        if reply.status != "ok":
            raise RunFailed(f"query {text!r}: {reply.status}: {reply.message}")
        times[kind].append(seconds)
        if kind == "relevance":
            times["relevance_server"].append(reply.seconds)
        if kind == "heatmap":
            times["heatmap_first" if i == 0 else "heatmap_repeat"].append(seconds)
            if i == 0:
                times["heatmap_first_server"].append(reply.seconds)
    return times


def report_queries(times: dict[str, list], figures: dict) -> None:
    """Print each kind's percentiles and put ``query_<kind>_p95_ms`` into ``figures``, and the
    views the heatmap queries asked for into ``heatmap_views``."""
    for kind, label in QUERY_KINDS.items():
        if times.get(kind):
            where = "(in the server)" if kind.endswith("_server") else "(round trip)"
            print(f"  query {label:34s} {where:15s} {percentiles(times[kind])}")
            figures[f"query_{kind}_p95_ms"] = round(float(np.percentile(1000 * np.asarray(times[kind]), 95)), 1)
    if times.get("heatmap_views"):
        print(f"  heatmap queries asked for views {', '.join(times['heatmap_views'])}")
        figures["heatmap_views"] = list(times["heatmap_views"])
