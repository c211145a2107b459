"""``olsplat bench graph``: a flight through the node graph, live-paced or lossless, with its
per-node load, start-up, memory, refinement passes and the ground-station query latency.

The replay graph (``launch/replay.yaml``, one process per node) is fed one of two ways:
- ``--rate R`` (default 1): as a live camera would, R frames per second, latest-wins (a slow
  node drops frames; nothing waits);
- ``--lossless``: every frame of the flight aggregated, the ingest waiting for each
  acknowledgement (as ``make demo`` does); the rate is then the graph's own.

While it flies, the node diagnostics are read through the query server every 2 s and every
node's memory from ``/proc`` every ``--sample-s``. Measured:
- frames sent / aggregated / dropped, the aggregation rate, and per node its rate, mean latency
  (acquisition stamp to end of handling, queueing included) and mean busy time per message;
- start-up: ``node_ready_s`` {node: seconds from its process's start (imports included) to the
  end of its set-up (its map read, its models loaded)}, from the "ready" line every node logs;
  ``startup_s`` is the slowest node's. ``all_reporting_s``: from launch until every node has
  reported in a status reply; that also holds the first view a node takes on before its first
  heartbeat, and a heartbeat or two lost while its publisher joins;
- memory per node from ``/proc``: the peak resident set (``VmHWM``, the kernel's own peak, not
  a sample; the queries after the flight included), and the resident set sampled every
  ``--sample-s`` until the final map with the number of views stored at that moment, to see
  whether a node grows with the flight (``--sample-s 0``: no samples during the flight, only
  the peaks read at its end and after the queries);
- the refiner's passes in flight order (``refine_s`` + ``write_s`` of each snapshot record);
- the store's bytes per view and the final snapshot's size;
- then, on the final map, ``--queries`` ground-station queries over the real ZeroMQ link
  (``ground_link``): relevance only (every Gaussian scored, 3D instances) and with the heatmap
  of a view (over ``--heatmap-views`` views, the flight's first ones or with
  ``--heatmap-spread`` spread over it: the first query on a view renders it, the following ones
  are answered from the server's cache of rendered features, and both are reported).

The sum of the nodes' peaks is an upper bound of what the graph held at once (the peaks need
not coincide). Resident sets count shared pages (the libraries, a file's page cache mapped by
several nodes) once per node, so the sum over-counts; ``private`` memory (anonymous pages,
``/proc/PID/smaps_rollup``) is reported beside it at the samples.

``--json FILE`` writes ``lossless`` (true or false), ``rate`` (the frames per second sent; null
when lossless), ``frames_sent`` (each frame once), ``frames_aggregated``, ``frames_dropped``,
``frames_resent`` (lossless: sends again of a frame not acknowledged in time), ``views_per_s``
(with ``--rate``, aggregated per second of stream: frames_aggregated / (frames_sent / rate);
lossless, views / wall_s), ``seconds`` and ``wall_s`` (both the seconds from launch until the
final map), ``gaussians``, ``views``, ``width``, ``height``, ``startup_s``,
``node_ready_s`` {node: s}, ``all_reporting_s``,
``peak_rss_mb`` {node: MB}, ``peak_rss_mb_sum``, ``rss_growth_mb`` {node: resident MB at the
end minus once a quarter of the views were stored}, ``private_mb_max`` {node: MB},
``store_bytes_per_view``, ``snapshot_bytes``, ``refine_pass_s`` (list), ``refine_pass_views``
(views in the map after each pass), ``refine_pass_exact`` (false for a fold of the new views:
the refiner's first pass and its final one are exact, and so is a live pass where an exact one
was the cheaper: the refiner's fold_limit), ``refine_pass_reads`` (each pass's observations
{added, fold, exact}: those it took in, and those a fold and an exact pass would have read),
``refine_s_per_added_view`` (each pass
over the views it added), ``query_relevance_p95_ms`` (round trip) and
``query_relevance_server_p95_ms`` (the query server's own time), ``query_heatmap_p95_ms`` (all
heatmap queries), ``query_heatmap_first_p95_ms`` and ``query_heatmap_repeat_p95_ms`` (first and
later queries on a view), ``query_heatmap_first_server_p95_ms`` (the server's own time for the
first ones), ``query_heatmap_preview_p95_ms`` and ``query_heatmap_preview_first_p95_ms`` (each
heatmap query's preview, asked first as the ground station page asks it: all, and the first on
each view), ``refine_pass_observations`` (the store's observations after each pass),
``refine_pass_s_per_view_added`` ({first_third, last_third, ratio, and the same per million
observations added: first_third_per_m_obs, last_third_per_m_obs, ratio_obs}: the live
passes' seconds per view added, over the passes that ended in the first and the last third of
the flight; see pass_growth below), with ``--lossless`` ``live_drift_miou`` (the exact map's
mIoU minus the last live version's, both over the views that version held: how far the folds
let a live map drift; ``live_drift`` has both scores, Loc@50, the version and its views;
graph_drift in live.py; both null when the flight has no annotations or the run made no fold),
``heatmap_views`` (the views the heatmap queries asked
for), ``memory_series`` {node: [[views stored, resident MB, private MB], ...]} and
``nodes.<name>.{busy_ms, latency_ms, drops, handled}`` (means over the flight's heartbeats; the
accumulator's latency_ms is the frame-to-store latency), ``core_s_per_view`` {node: CPU
seconds of its processes (every thread, user + system, from ``/proc``; a restarted node's
processes summed) from launch to the final map, over the views aggregated} and
``core_s_per_view_sum`` (all nodes: with the machine's cores, the views per second it allows).

``--queries-only --work DIR``: only the queries again, on a run kept with ``--work DIR``
(``requery.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError

STATUS_EVERY_S = 2.0  # the node diagnostics' sampling (the per-node means are over these samples)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "graph",
        help="a flight through the node graph, live-paced (--rate) or --lossless: per-node load, "
        "start-up, memory, refinement passes, query latency over the ground link",
    )
    parser.add_argument("--scene", required=True, type=Path, help="a simulator flight folder (replay.mcap, map/)")
    feed = parser.add_mutually_exclusive_group()
    feed.add_argument("--rate", type=float, default=1.0, help="frames per second sent, latest-wins (default 1)")
    feed.add_argument(
        "--lossless",
        action="store_true",
        help="send every frame, the ingest waiting for each acknowledgement: every frame aggregated",
    )
    parser.add_argument("--queries", type=int, default=100, help="relevance queries after the flight")
    parser.add_argument("--heatmap-queries", type=int, default=20, help="heatmap queries, spread over --heatmap-views")
    parser.add_argument("--heatmap-views", type=int, default=4, help="views the heatmap queries ask for, in turn")
    parser.add_argument(
        "--heatmap-spread",
        action="store_true",
        help="ask for views spread evenly over the flight, not its first ones (far views cost more)",
    )
    parser.add_argument(
        "--sample-s", type=float, default=1.0, help="seconds between memory samples (0: only the peaks at the end)"
    )
    parser.add_argument("--launch", default="replay", help="the launch file to run (a shipped name or a path)")
    parser.add_argument("--port", type=int, default=5610, help="the query server's TCP port")
    parser.add_argument("--work", type=Path, help="run directory (default: a temporary one, removed after)")
    parser.add_argument(
        "--queries-only",
        action="store_true",
        help="no flight: launch only the query server on the final map of a run kept with --work DIR, "
        "and time the queries again (bench/requery.py)",
    )
    parser.add_argument("--json", type=Path, help="also write the figures here (keys: see the module docstring)")
    parser.add_argument(
        "--set",
        dest="extra",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="override a node parameter as olsplat launch --set does (repeatable), "
        "e.g. query_server.heatmap_max_side=640",
    )
    parser.set_defaults(run=run)


def feed_overrides(lossless: bool, rate: float) -> list[str]:
    """The ingest's and region encoder's parameters for a lossless or a live-paced stream."""
    if lossless:
        return ["ingest.lossless=true", "ingest.fast=true", "region_encoder.latest_wins=false"]
    if not rate > 0:
        raise OlsplatInputError(f"--rate {rate:g}: must be > 0 frames per second (or --lossless)")
    return ["ingest.lossless=false", f"ingest.rate_hz={rate}", "ingest.fast=false", "region_encoder.latest_wins=true"]


def run(args: argparse.Namespace) -> int:
    if args.queries_only:
        from .requery import run as queries_only

        return queries_only(args)
    import zmq

    from ..launcher import Supervisor, load_launch
    from ..scene import read_cameras
    from ..scene.ply import ply_vertex_count
    from ..storage.snapshot import latest_map, map_history
    from ..transport import QueryClient
    from .ground_link import final_map, report_queries, sample_status, time_queries
    from .live import graph_drift
    from .node_watch import NODES, MemoryWatch, node_ready_s

    feed = feed_overrides(args.lossless, args.rate)
    if args.sample_s < 0:
        raise OlsplatInputError(f"--sample-s {args.sample_s:g}: must be >= 0")
    scene = args.scene.resolve()
    ply = scene / "map" / "point_cloud.ply"
    gaussians = ply_vertex_count(ply)
    cameras = read_cameras(scene)
    run_dir = args.work or Path(tempfile.mkdtemp(prefix="olsplat_bench_graph_"))
    shutil.rmtree(run_dir, ignore_errors=True)
    endpoint = f"tcp://127.0.0.1:{args.port}"
    overrides = [
        f"ingest.source={scene / 'replay.mcap'}",
        *feed,
        f"query_server.map={ply}",
        f"accumulator.map={ply}",
        f"refiner.map={ply}",
        f"query_server.query_endpoint={endpoint}",
        "query_server.queries_per_s=0",  # the benchmark's own queries come back to back: no rate limit
        "refiner.exit_on_final=false",
        "launch.exit_when=[]",
    ]
    overrides += args.extra  # the user's, last: they win
    supervisor = Supervisor(load_launch(args.launch, overrides=overrides, run_dir=str(run_dir)))
    store_views = run_dir / "store" / "views"

    def views_stored() -> int:
        try:
            return sum(1 for p in store_views.iterdir() if not p.name.endswith(".tmp"))
        except OSError:
            return 0

    watch = MemoryWatch(lambda: supervisor.pids, views_stored, args.sample_s)
    start = time.monotonic()
    supervisor.check()  # a bad launch file or --set is an error here, not in the thread
    thread = threading.Thread(target=supervisor.run, daemon=True)
    thread.start()
    watch.start()
    client = QueryClient(zmq.Context.instance(), endpoint, timeout_s=60.0)
    samples: dict[str, list[dict]] = {}  # every STATUS_EVERY_S: the per-node means
    passes: dict[int, dict] = {}
    startup_s = None
    last_status = last_progress = 0.0
    succeeded = False
    try:
        record = None
        while record is None:
            time.sleep(0.5)
            due = time.monotonic() - last_status >= STATUS_EVERY_S
            if startup_s is None or due:  # every 0.5 s until every node reports: the start-up
                status = sample_status(client, samples if due else {})
                if due:
                    last_status = time.monotonic()
                if startup_s is None and status is not None and set(NODES) <= {n["node"] for n in status.nodes}:
                    startup_s = time.monotonic() - start
            record = final_map(supervisor, thread, run_dir)
            newest = record or latest_map(run_dir / "map")
            if newest is not None and "refine_s" in newest:
                passes[newest["version"]] = newest
            if time.monotonic() - last_progress > 30:
                last_progress = time.monotonic()
                done = views_stored()
                elapsed = time.monotonic() - start
                left = f", ~{(len(cameras) - done) * elapsed / done:.0f} s left" if done else ""
                print(f"  {done}/{len(cameras)} views stored after {elapsed:.0f} s{left}", flush=True)
        wall_s = time.monotonic() - start
        watch.sample()  # before the ingest exits
        # every pass, also those written between two polls of latest.json (on a fast machine a
        # fold and the final map can land within one poll)
        passes.update({r["version"]: r for r in map_history(run_dir / "map") if "refine_s" in r})
        cpu_s = watch.node_cpu_s()  # the flight's, start-up included; the queries after it not
        watch.flight_over = True  # the queries below still count in the peaks
        # the ingest's counts are final in the heartbeat it sends after it saw the final map
        # (then it exits); the sampling above may have missed it
        final_at = (run_dir / "map" / "latest.json").stat().st_mtime
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            status = sample_status(client, samples)
            if status is None:
                continue
            ingest = next((n for n in status.nodes if n["node"] == "ingest"), None)
            if ingest is not None and time.time() - ingest["age_s"] >= final_at:
                break
            time.sleep(0.5)
        last = {name: values[-1] for name, values in samples.items()}
        ingest = last.get("ingest", {})
        # frames (published also counts EndOfStream); a frame sent again (lossless: no
        # acknowledgement in time, as while the graph starts) is one frame
        resent = int(ingest.get("resent", 0))
        sent = int(ingest.get("handled", 0)) - resent
        views = int(record["views"])
        if args.lossless:
            views_per_s = views / wall_s
        else:
            views_per_s = views / (sent / args.rate) if sent else 0.0
        store_bytes = sum(f.stat().st_size for f in store_views.rglob("*") if f.is_file())
        ordered = [passes[v] for v in sorted(passes)]
        refine_pass_s = [round(p["refine_s"] + p.get("write_s", 0.0), 3) for p in ordered]
        width, height = cameras[0].width, cameras[0].height
        ready = node_ready_s(run_dir / "logs")
        figures: dict = {
            "lossless": bool(args.lossless),
            "rate": None if args.lossless else args.rate,
            "frames_sent": sent,
            "frames_aggregated": views,
            "frames_dropped": sent - views,
            "frames_resent": resent,
            "views_per_s": round(views_per_s, 3),
            "seconds": round(wall_s, 1),
            "wall_s": round(wall_s, 1),
            "gaussians": gaussians,
            "views": views,
            "width": width,
            "height": height,
            "startup_s": round(max(ready.values()), 1) if ready else None,
            "node_ready_s": {name: round(s, 1) for name, s in sorted(ready.items())},
            "all_reporting_s": round(startup_s, 1) if startup_s is not None else None,
            "store_bytes_per_view": round(store_bytes / max(views, 1)),
            "snapshot_bytes": int(record.get("bytes", 0)),
            "refine_pass_s": refine_pass_s,
            "refine_pass_views": [int(p["views"]) for p in ordered],
            "refine_pass_exact": [bool(p.get("exact", True)) for p in ordered],  # False: a fold
            "refine_pass_reads": [p.get("reads") for p in ordered],  # None from a refiner before them
            "nodes": {},
            # CPU seconds per view aggregated, by node and in all (the machine's cores are the budget)
            "core_s_per_view": {name: round(c / max(views, 1), 3) for name, c in sorted(cpu_s.items())},
            "core_s_per_view_sum": round(sum(cpu_s.values()) / max(views, 1), 3),
        }
        # a pass's cost over the views it added: flat when passes grow with the views since the
        # last pass (which refiner.max_duty lets grow as passes lengthen), not with the flight
        added = np.diff([0, *figures["refine_pass_views"]])
        figures["refine_s_per_added_view"] = [
            round(s / max(int(a), 1), 3) for s, a in zip(refine_pass_s, added, strict=True)
        ]
        figures["refine_pass_observations"] = [int(p.get("observations", 0)) for p in ordered]
        live = [i > 0 and not p.get("final") for i, p in enumerate(ordered)]  # not the first, not the final
        figures["refine_pass_s_per_view_added"] = pass_growth(
            refine_pass_s, figures["refine_pass_views"], live, views,
            figures["refine_pass_observations"],
        )  # fmt: skip
        how = (
            f"lossless ({resent} sent again for want of an acknowledgement)" if args.lossless else f"at {args.rate:g}/s"
        )
        print(
            f"graph on {scene.name}: {sent} frames sent {how}, {views} aggregated, "
            f"{sent - views} dropped, final map version {record['version']} after {wall_s:.0f} s"
        )
        if not args.lossless:
            print(f"  sustained aggregation rate {views_per_s:.2f} views/s (aggregated per second of stream)")
        print(
            f"  {gaussians:,} Gaussians, {views} views of {width}x{height} aggregated "
            f"in {wall_s:.0f} s ({views / wall_s:.2f} views/s)"
        )
        print(
            f"  start-up: slowest node ready {figures['startup_s']} s after its process started ("
            + ", ".join(f"{name} {s:.1f}" for name, s in figures["node_ready_s"].items())
            + f"); every node reporting {figures['all_reporting_s']} s after launch"
        )
        print(
            "  CPU per view (core-seconds, the flight's start-up included): "
            + ", ".join(f"{name} {c:.2f}" for name, c in figures["core_s_per_view"].items())
            + f"; in all {figures['core_s_per_view_sum']:.2f} ({os.cpu_count()} cores here)"
        )
        for name in ("ingest", "region_encoder", "accumulator", "refiner", "query_server"):
            values = [v for v in samples.get(name, []) if v.get("handled", 0)]
            if not values:
                continue
            rate = max(v.get("rate_hz", 0.0) for v in values)
            latency = float(np.mean([v.get("latency_ms", 0.0) for v in values]))
            busy = float(np.mean([v.get("busy_ms", 0.0) for v in values]))
            drops = int(values[-1].get("dropped", 0)) + int(values[-1].get("gaps", 0))
            handled = int(values[-1]["handled"])
            figures["nodes"][name] = {
                "busy_ms": round(busy, 1),
                "latency_ms": round(latency, 1),
                "drops": drops,
                "handled": handled,
            }
            print(
                f"  {name:15s} handled {handled:4d}  peak rate {rate:5.2f} Hz  mean latency "
                f"{latency:8.1f} ms  mean busy {busy:8.1f} ms  drops {drops}"
            )
        times = time_queries(
            client, scene, run_dir, args.queries, args.heatmap_queries, args.heatmap_views, args.heatmap_spread
        )
        watch.sample()  # the peaks with the queries, whatever --sample-s
        memory_figures(watch, views, figures)
        for name in NODES:
            if name in watch.peak:
                print(
                    f"  {name:15s} peak RSS {watch.peak[name]:8.0f} MB  private max "
                    f"{figures['private_mb_max'].get(name, float('nan')):7.0f} MB  growth from 1/4 of the views "
                    f"{figures['rss_growth_mb'].get(name, 0):+6.0f} MB"
                )
        print(f"  sum of the nodes' peaks {figures['peak_rss_mb_sum']:,} MB")
        print(
            f"  store {store_bytes / 2**20:.0f} MB ({figures['store_bytes_per_view'] / 2**20:.2f} MB per view), "
            f"final snapshot {figures['snapshot_bytes'] / 2**20:.0f} MB"
        )
        marked = zip(refine_pass_s, figures["refine_pass_views"], figures["refine_pass_exact"], strict=True)
        print(
            "  refinement passes (s, views in the map; * exact, the others folds): "
            + ", ".join(f"{s:.1f} ({v}{'*' if exact else ''})" for s, v, exact in marked)
        )
        print("  per view added by the pass (s): " + ", ".join(f"{s:.2f}" for s in figures["refine_s_per_added_view"]))
        growth = figures["refine_pass_s_per_view_added"]
        print(
            f"  live passes, s per view added: first third {growth['first_third']}, last third {growth['last_third']} "
            f"(x{growth['ratio']}); s per million observations added: first third "
            f"{growth['first_third_per_m_obs']}, last third {growth['last_third_per_m_obs']} (x{growth['ratio_obs']})"
        )
        report_queries(times, figures)
        if args.lossless:  # live-paced runs drop views: their exact map would not be the same views
            drift = graph_drift(scene, run_dir, passes)
            figures["live_drift_miou"] = None if drift is None else drift["drift_miou"]
            figures["live_drift"] = drift
            if drift is not None:
                print(
                    f"  drift of the last live version (v{drift['version']}, a fold at {drift['views']} views) from "
                    f"the exact map of the same views: {drift['drift_miou']:+.2f} mIoU ({drift['live_mIoU']:.2f} "
                    f"against {drift['exact_mIoU']:.2f}), {drift['drift_loc50']:+.2f} Loc@50"
                )
            elif len(ordered) > 2 and all(figures["refine_pass_exact"]):  # exact wherever a fold would read more
                print("  drift of the live versions: none, every live pass was exact (refiner.fold_limit)")
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(figures, indent=1))
            print(f"  figures -> {args.json}")
        succeeded = True
    finally:
        watch.stop.set()
        client.close()
        supervisor.request_stop(0)
        thread.join(30)
        if not args.work and succeeded:  # a failed run's logs stay, for its error message
            shutil.rmtree(run_dir, ignore_errors=True)
    return 0


def memory_figures(watch, views: int, figures: dict) -> None:
    """The memory keys of ``figures`` (``peak_rss_mb``, ``peak_rss_mb_sum``, ``rss_growth_mb``,
    ``private_mb_max``, ``memory_series``) from a ``node_watch.MemoryWatch``."""
    figures["peak_rss_mb"] = {name: round(mb) for name, mb in sorted(watch.peak.items())}
    figures["peak_rss_mb_sum"] = round(sum(watch.peak.values()))
    figures["rss_growth_mb"] = {name: round(watch.growth(name, views)) for name in sorted(watch.series)}
    figures["private_mb_max"] = {name: round(max(s[2] for s in ser)) for name, ser in sorted(watch.series.items())}
    figures["memory_series"] = {
        name: [[v, round(r), round(p)] for v, r, p in ser] for name, ser in sorted(watch.series.items())
    }


def pass_growth(
    pass_s: list[float], pass_views: list[int], live: list[bool], views: int, observations: list[int] | None = None
) -> dict:
    """Whether live passes grow with the flight: the mean seconds per view added of the live
    passes (``live`` [P] bool: every pass but the first and the final one, which are exact by
    design; a live pass is a fold, or an exact pass where that was the cheaper) that ended with
    at most a third of the flight's ``views`` in the map, and of those that ended in its last
    third; ``ratio`` = last / first. With ``observations`` [P] (the store's after each pass) the
    same per million observations added (``*_per_m_obs``, ``ratio_obs``): what a fold's cost
    follows (a view that sees more of the map adds more). None where a third has no live pass.
    ``pass_s`` [P] seconds, ``pass_views`` [P] views in the map after each pass, in pass order."""
    per_view = _thirds(pass_s, pass_views, np.diff([0, *pass_views]), live, views)
    per_m_obs = (None, None, None)
    if observations is not None and any(observations):
        per_m_obs = _thirds(pass_s, pass_views, np.diff([0, *observations]) / 1e6, live, views)
    keys = ("first_third", "last_third", "ratio", "first_third_per_m_obs", "last_third_per_m_obs", "ratio_obs")
    return dict(zip(keys, (*per_view, *per_m_obs), strict=True))


def _thirds(pass_s, pass_views, added, live, views: int) -> tuple:
    """(first third's mean, last third's mean, last / first) of the live passes' seconds per unit
    ``added`` [P] (views or observations added by each pass); None where a third has none."""
    rate = [(v, s / a) for s, v, a, counted in zip(pass_s, pass_views, added, live, strict=True) if counted and a > 0]
    first = [x for v, x in rate if v <= views / 3]
    last = [x for v, x in rate if v > 2 * views / 3]
    first_mean = round(float(np.mean(first)), 3) if first else None
    last_mean = round(float(np.mean(last)), 3) if last else None
    return first_mean, last_mean, round(last_mean / first_mean, 2) if first_mean and last_mean is not None else None
