"""``olsplat bench graph --queries-only --work DIR``: the ground-station queries of a kept run
again, without flying it again.

A large flight takes ~25 min through the graph; its queries a minute. To measure a change to
the query path, keep one run (``bench graph --work DIR``), then launch only its query server
on DIR's final map and views (the launch file's ``query_server`` node, its parameters as in
the run, ``--set`` overrides last) and ask the same queries over the real link
(``ground_link.time_queries``). The run folder is read, never changed (the query server's log
is appended to ``DIR/logs``).

``--json FILE`` writes ``gaussians``, ``views``, ``width``, ``height``, ``startup_s`` (the query
server's own "ready" line), ``peak_rss_mb.query_server`` and the ``query_*_p95_ms`` keys of
``bench graph``, with ``queries_only: true``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import threading
import time

from ..errors import OlsplatInputError, RunFailed


def run(args: argparse.Namespace) -> int:
    import zmq

    from ..launcher import Supervisor, load_launch
    from ..scene import read_cameras
    from ..scene.ply import ply_vertex_count
    from ..storage.snapshot import latest_map
    from ..transport import QueryClient
    from .ground_link import report_queries, sample_status, time_queries
    from .node_watch import node_ready_s, process_memory

    if args.work is None:
        raise OlsplatInputError("--queries-only needs --work DIR: the folder of a run kept by bench graph --work DIR")
    run_dir = args.work.resolve()
    record = latest_map(run_dir / "map")
    if record is None or not record.get("final"):
        raise OlsplatInputError(
            f"{run_dir}: no final map in map/latest.json; give the folder of a completed `bench graph --work DIR` run"
        )
    scene = args.scene.resolve()
    ply = scene / "map" / "point_cloud.ply"
    endpoint = f"tcp://127.0.0.1:{args.port}"
    overrides = [
        f"query_server.map={ply}",
        f"query_server.query_endpoint={endpoint}",
        "query_server.queries_per_s=0",  # the benchmark's own queries come back to back
        "launch.exit_when=[]",
        *args.extra,
    ]
    config = load_launch(args.launch, overrides=overrides, run_dir=str(run_dir))
    config = dataclasses.replace(config, nodes=tuple(n for n in config.nodes if n.name == "query_server"))
    if not config.nodes:
        raise OlsplatInputError(f"{args.launch}: no node named query_server")
    supervisor = Supervisor(config)
    supervisor.check()
    thread = threading.Thread(target=supervisor.run, daemon=True)
    thread.start()
    client = QueryClient(zmq.Context.instance(), endpoint, timeout_s=60.0)
    try:
        # as in the full run, where the server has long been up: its warm-up (kernels, the voxel
        # index) done before the first query is timed
        deadline = time.monotonic() + 120.0
        while not _warm(sample_status(client, {})):
            if not thread.is_alive() or time.monotonic() > deadline:
                raise RunFailed(f"the query server was not ready within 120 s; see {run_dir / 'logs'}")
            time.sleep(0.2)
        times = time_queries(
            client, scene, run_dir, args.queries, args.heatmap_queries, args.heatmap_views, args.heatmap_spread
        )
        pid = supervisor.pids.get("query_server")
        peak = process_memory(pid).get("peak_rss_mb", float("nan")) if pid else float("nan")
        camera = read_cameras(scene)[0]
        ready = node_ready_s(run_dir / "logs", latest=True).get("query_server")
        figures: dict = {
            "queries_only": True,
            "gaussians": ply_vertex_count(ply),
            "views": int(record["views"]),
            "width": camera.width,
            "height": camera.height,
            "startup_s": round(ready, 1) if ready is not None else None,
            "peak_rss_mb": {"query_server": round(peak)},
        }
        print(
            f"queries on {run_dir.name} (map version {record['version']}, {figures['views']} views of "
            f"{camera.width}x{camera.height}, {figures['gaussians']:,} Gaussians): query server ready after "
            f"{figures['startup_s']} s, peak RSS {peak:.0f} MB"
        )
        report_queries(times, figures)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(figures, indent=1))
            print(f"  figures -> {args.json}")
    finally:
        client.close()
        supervisor.request_stop(0)
        thread.join(30)
    return 0


def _warm(status) -> bool:
    """Whether a status reply says the query server has finished its warm-up."""
    own = next((n for n in status.nodes if n["node"] == "query_server"), None) if status is not None else None
    return bool(own and own["values"].get("query_index_ready") and own["values"].get("query_warm"))
