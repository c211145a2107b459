"""``olsplat bench graph``: the node graph on a live-paced stream, and ground-station query latency.

The replay graph (``launch/replay.yaml``, one process per node) is fed as a live camera would
be: ``--rate`` frames per second, latest-wins (a slow node drops frames; nothing waits). While
it streams, the node diagnostics are read through the query server every 2 s. Printed:
frames sent / aggregated / dropped, the sustained aggregation rate, and per node its rate,
mean latency (acquisition stamp to end of handling, queueing included) and mean busy time per
message. Then, on the final map, ``--queries`` ground-station queries over the real ZeroMQ link:
relevance only (every Gaussian scored, 3D instances) and with the heatmap of a view (over
``--heatmap-views`` views: the first query on a view renders it, the following ones are
answered from the server's cache of rendered features, and both are reported).

``--json FILE`` writes ``frames_sent``, ``frames_aggregated``, ``frames_dropped``,
``views_per_s`` (aggregated per second of stream: frames_aggregated / (frames_sent / rate)),
``seconds`` (until the final map), ``query_relevance_p95_ms`` (and ``query_relevance_server_p95_ms``,
the server's own time), ``query_heatmap_p95_ms`` (all
heatmap queries), ``query_heatmap_first_p95_ms`` and ``query_heatmap_repeat_p95_ms`` (first and
later queries on a view), ``query_heatmap_first_server_p95_ms`` (the server's own time for
the first ones), and
``nodes.<name>.{busy_ms, latency_ms, drops, handled}`` (means over the flight's heartbeats; the
accumulator's latency_ms is the frame-to-store latency).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "graph", help="node graph on a live-paced stream; query latency over the ground link"
    )
    parser.add_argument("--scene", required=True, type=Path, help="a simulator flight folder (replay.mcap, map/)")
    parser.add_argument("--rate", type=float, default=1.0, help="frames per second sent (default 1)")
    parser.add_argument("--queries", type=int, default=100, help="relevance queries after the flight")
    parser.add_argument("--heatmap-queries", type=int, default=20, help="heatmap queries, spread over --heatmap-views")
    parser.add_argument("--heatmap-views", type=int, default=4, help="views the heatmap queries ask for, in turn")
    parser.add_argument("--launch", default="replay", help="the launch file to run (a shipped name or a path)")
    parser.add_argument("--port", type=int, default=5610, help="the query server's TCP port")
    parser.add_argument("--work", type=Path, help="run directory (default: a temporary one, removed after)")
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


def run(args: argparse.Namespace) -> int:
    import threading

    import zmq

    from ..launcher import Supervisor, load_launch
    from ..transport import QueryClient
    from .ground_link import final_map, report_queries, sample_status, time_queries

    scene = args.scene.resolve()
    run_dir = args.work or Path(tempfile.mkdtemp(prefix="olsplat_bench_graph_"))
    shutil.rmtree(run_dir, ignore_errors=True)
    ply = scene / "map" / "point_cloud.ply"
    endpoint = f"tcp://127.0.0.1:{args.port}"
    overrides = [
        f"ingest.source={scene / 'replay.mcap'}",
        "ingest.lossless=false",
        f"ingest.rate_hz={args.rate}",
        "ingest.fast=false",
        "region_encoder.latest_wins=true",
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
    supervisor.check()  # a bad launch file or --set is an error here, not in the thread
    thread = threading.Thread(target=supervisor.run, daemon=True)
    thread.start()
    client = QueryClient(zmq.Context.instance(), endpoint, timeout_s=60.0)
    samples: dict[str, list[dict]] = {}
    start = time.monotonic()
    succeeded = False
    try:
        record = None
        while record is None:
            time.sleep(2.0)
            sample_status(client, samples)
            record = final_map(supervisor, thread, run_dir)
        seconds = time.monotonic() - start
        # the ingest's counts are final in the heartbeat it sends after it saw the final map
        # (then it exits); the 2 s sampling above may have missed it
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
        sent = int(last.get("ingest", {}).get("handled", 0))  # frames (published also counts EndOfStream)
        aggregated = int(record["views"])
        views_per_s = aggregated / (sent / args.rate) if sent else 0.0
        figures: dict = {
            "frames_sent": sent,
            "frames_aggregated": aggregated,
            "frames_dropped": sent - aggregated,
            "views_per_s": round(views_per_s, 3),
            "seconds": round(seconds, 1),
            "nodes": {},
        }
        print(
            f"graph on {scene.name}: {sent} frames sent at {args.rate:g}/s, {aggregated} aggregated, "
            f"{sent - aggregated} dropped, final map version {record['version']} after {seconds:.0f} s"
        )
        print(f"  sustained aggregation rate {views_per_s:.2f} views/s (aggregated per second of stream)")
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
        times = time_queries(client, scene, run_dir, args.queries, args.heatmap_queries, args.heatmap_views)
        report_queries(times, figures)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(figures, indent=1))
            print(f"  figures -> {args.json}")
        succeeded = True
    finally:
        client.close()
        supervisor.request_stop(0)
        thread.join(30)
        if not args.work and succeeded:  # a failed run's logs stay, for its error message
            shutil.rmtree(run_dir, ignore_errors=True)
    return 0
