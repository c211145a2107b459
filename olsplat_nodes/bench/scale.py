"""``olsplat bench scale``: a whole flight through the node graph, losslessly, with its memory.

The replay graph (``launch/replay.yaml``, one process per node) aggregates every frame of the
flight (the ingest waits for each acknowledgement, as ``make demo`` does). Measured:
- start-up: ``node_ready_s`` {node: seconds from its process's start (imports included) to the
  end of its set-up (its map read, its models loaded)}, from the "ready" line every node logs;
  ``startup_s`` is the slowest node's. ``all_reporting_s``: from launch until every node has
  reported in a status reply; that also holds the first view a node takes on before its first
  heartbeat, and a heartbeat or two lost while its publisher joins;
- memory per node from ``/proc``: the peak resident set (``VmHWM``, the kernel's own peak, not
  a sample; the queries after the flight included), and the resident set sampled every
  ``--sample-s`` until the final map with the number of views stored at that moment, to see
  whether a node grows with the flight;
- the refiner's passes in flight order (``refine_s`` + ``write_s`` of each snapshot record);
- the store's bytes per view and the final snapshot's size;
- then, on the final map, ground-station queries over the real link (``ground_link``).

The sum of the nodes' peaks is an upper bound of what the graph held at once (the peaks need
not coincide). Resident sets count shared pages (the libraries, a file's page cache mapped by
several nodes) once per node, so the sum over-counts; ``private`` memory (anonymous pages,
``/proc/PID/smaps_rollup``) is reported beside it at the samples.

``--json FILE`` writes ``gaussians``, ``views``, ``wall_s``, ``views_per_s``, ``startup_s``,
``node_ready_s`` {node: s}, ``all_reporting_s``,
``peak_rss_mb`` {node: MB}, ``peak_rss_mb_sum``, ``rss_growth_mb`` {node: resident MB at the
end minus once a quarter of the views were stored}, ``private_mb_max`` {node: MB},
``store_bytes_per_view``, ``snapshot_bytes``, ``refine_pass_s`` (list), ``refine_pass_views``
(views in the map after each pass), ``refine_pass_exact`` (false for a fold of the new views:
the refiner's first pass and its final one are exact), ``refine_s_per_added_view`` (each pass over the views it
added), ``query_relevance_p95_ms`` (round trip) and ``query_relevance_server_p95_ms`` (the
query server's own time), ``query_heatmap_p95_ms``, ``query_heatmap_first_p95_ms``,
``query_heatmap_repeat_p95_ms``, ``query_heatmap_first_server_p95_ms``, ``heatmap_views``
(the views the heatmap queries asked for), and ``width``, ``height``.

``--queries-only --work DIR``: only the queries again, on a run kept with ``--work DIR``
(``requery.py``).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

NODES = ("query_server", "ingest", "region_encoder", "accumulator", "refiner")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "scale",
        help="a whole flight through the node graph: memory per node, start-up, refinement passes, queries",
        epilog="examples:\n  olsplat bench scale --scene medium0 --json scale-medium.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--scene", required=True, type=Path, help="a simulator flight folder (replay.mcap, map/)")
    parser.add_argument("--queries", type=int, default=100, help="relevance queries after the flight")
    parser.add_argument("--heatmap-queries", type=int, default=20, help="heatmap queries, spread over --heatmap-views")
    parser.add_argument("--heatmap-views", type=int, default=4, help="views the heatmap queries ask for, in turn")
    parser.add_argument(
        "--heatmap-spread",
        action="store_true",
        help="ask for views spread evenly over the flight, not its first ones (far views cost more)",
    )
    parser.add_argument("--sample-s", type=float, default=1.0, help="seconds between memory samples")
    parser.add_argument("--launch", default="replay", help="the launch file to run (a shipped name or a path)")
    parser.add_argument("--port", type=int, default=5612, help="the query server's TCP port")
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


_READY = re.compile(r" (\S+) ready: ([0-9.]+) s after its process started")


def node_ready_s(logs: Path, latest: bool = False) -> dict[str, float]:
    """{node: seconds from its process's start to the end of its set-up}, each node's first
    start (``latest``: its latest), from the "ready" lines of the launch's node logs
    (``nodes.base.Node.run``)."""
    ready: dict[str, float] = {}
    for log_file in sorted(logs.glob("*.log")):
        for line in log_file.read_text(errors="replace").splitlines():
            found = _READY.search(line)
            if found and (latest or found[1] not in ready):
                ready[found[1]] = float(found[2])
    return ready


def process_memory(pid: int) -> dict[str, float]:
    """{rss_mb, peak_rss_mb, private_mb} of a live process from /proc (Linux); {} once it is gone."""
    values: dict[str, float] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                values["rss_mb" if key == "VmRSS" else "peak_rss_mb"] = int(rest.split()[0]) / 1024
        private = 0
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("Private_Clean", "Private_Dirty"):
                private += int(rest.split()[0])
        values["private_mb"] = private / 1024
    except (OSError, ValueError, IndexError):
        return {}
    return values


class MemoryWatch:
    """Samples every node's memory in a background thread: per node the highest peak RSS seen
    (over restarts too) and a series of (views stored, rss_mb, private_mb)."""

    def __init__(self, pids, views_stored, every_s: float):
        self.pids, self.views_stored, self.every_s = pids, views_stored, every_s
        self.peak: dict[str, float] = {}
        self.series: dict[str, list[tuple[int, float, float]]] = {}
        self.flight_over = False  # after the final map: peaks still taken, the series stops
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="memory-watch", daemon=True)

    def _loop(self) -> None:
        while not self.stop.wait(self.every_s):
            self.sample()

    def sample(self) -> None:
        views = self.views_stored()
        for name, pid in self.pids().items():
            values = process_memory(pid)
            if values:
                self.peak[name] = max(self.peak.get(name, 0.0), values["peak_rss_mb"])
                if not self.flight_over:
                    self.series.setdefault(name, []).append((views, values["rss_mb"], values["private_mb"]))

    def growth(self, name: str, views: int) -> float:
        """Resident MB at the last sample minus at the first sample once a quarter of the
        flight's ``views`` were stored (start-up, the first map and the first caches are
        behind by then: what is left is growth with the flight)."""
        series = [s for s in self.series.get(name, []) if s[0] >= max(1, views // 4)]
        return series[-1][1] - series[0][1] if series else 0.0


def run(args: argparse.Namespace) -> int:
    if args.queries_only:
        from .requery import run as queries_only

        return queries_only(args)
    import zmq

    from ..aggregate.snapshot import latest_map
    from ..launcher import Supervisor, load_launch
    from ..scene import read_cameras
    from ..scene.ply import ply_vertex_count
    from ..transport import QueryClient
    from .ground_link import final_map, report_queries, sample_status, time_queries

    scene = args.scene.resolve()
    run_dir = args.work or Path(tempfile.mkdtemp(prefix="olsplat_bench_scale_"))
    shutil.rmtree(run_dir, ignore_errors=True)
    ply = scene / "map" / "point_cloud.ply"
    gaussians = ply_vertex_count(ply)
    cameras = read_cameras(scene)
    endpoint = f"tcp://127.0.0.1:{args.port}"
    overrides = [
        f"ingest.source={scene / 'replay.mcap'}",
        f"query_server.map={ply}",
        f"accumulator.map={ply}",
        f"refiner.map={ply}",
        f"query_server.query_endpoint={endpoint}",
        "query_server.queries_per_s=0",  # the benchmark's own queries come back to back
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
    watch.thread.start()
    client = QueryClient(zmq.Context.instance(), endpoint, timeout_s=60.0)
    samples: dict[str, list[dict]] = {}
    passes: dict[int, dict] = {}
    startup_s = None
    last_progress = 0.0
    succeeded = False
    try:
        record = None
        while record is None:
            time.sleep(0.5)
            if startup_s is None:
                status = sample_status(client, samples)
                if status is not None and set(NODES) <= {n["node"] for n in status.nodes}:
                    startup_s = time.monotonic() - start
            record = final_map(supervisor, thread, run_dir)
            newest = record or latest_map(run_dir / "map")
            if newest is not None and "refine_s" in newest:
                passes[newest["version"]] = newest
            if time.monotonic() - last_progress > 30:
                last_progress = time.monotonic()
                done = views_stored()
                elapsed = time.monotonic() - start
                left = (len(cameras) - done) * elapsed / done if done else float("nan")
                print(f"  {done}/{len(cameras)} views stored after {elapsed:.0f} s, ~{left:.0f} s left", flush=True)
        wall_s = time.monotonic() - start
        watch.sample()
        watch.flight_over = True  # the queries below still count in the peaks
        views = int(record["views"])
        store_bytes = sum(f.stat().st_size for f in store_views.rglob("*") if f.is_file())
        ordered = [passes[v] for v in sorted(passes)]
        refine_pass_s = [round(p["refine_s"] + p.get("write_s", 0.0), 3) for p in ordered]
        width, height = cameras[0].width, cameras[0].height
        ready = node_ready_s(run_dir / "logs")
        figures: dict = {
            "gaussians": gaussians,
            "views": views,
            "width": width,
            "height": height,
            "wall_s": round(wall_s, 1),
            "views_per_s": round(views / wall_s, 3),
            "startup_s": round(max(ready.values()), 1) if ready else None,
            "node_ready_s": {name: round(s, 1) for name, s in sorted(ready.items())},
            "all_reporting_s": round(startup_s, 1) if startup_s is not None else None,
            "peak_rss_mb": {name: round(mb) for name, mb in sorted(watch.peak.items())},
            "peak_rss_mb_sum": round(sum(watch.peak.values())),
            "rss_growth_mb": {name: round(watch.growth(name, views)) for name in sorted(watch.series)},
            "private_mb_max": {name: round(max(s[2] for s in ser)) for name, ser in sorted(watch.series.items())},
            "store_bytes_per_view": round(store_bytes / max(views, 1)),
            "snapshot_bytes": int(record.get("bytes", 0)),
            "refine_pass_s": refine_pass_s,
            "refine_pass_views": [int(p["views"]) for p in ordered],
            "refine_pass_exact": [bool(p.get("exact", True)) for p in ordered],  # False: a fold
        }
        # a pass's cost over the views it added: flat when passes grow with the views since the
        # last pass (which refiner.max_duty lets grow as passes lengthen), not with the flight
        added = np.diff([0, *figures["refine_pass_views"]])
        per_view = [round(s / max(int(a), 1), 3) for s, a in zip(refine_pass_s, added, strict=True)]
        figures["refine_s_per_added_view"] = per_view
        print(
            f"scale on {scene.name}: {gaussians:,} Gaussians, {views} views of {width}x{height} aggregated "
            f"in {wall_s:.0f} s ({figures['views_per_s']:.2f} views/s)"
        )
        print(
            f"  start-up: slowest node ready {figures['startup_s']} s after its process started ("
            + ", ".join(f"{name} {s:.1f}" for name, s in figures["node_ready_s"].items())
            + f"); every node reporting {figures['all_reporting_s']} s after launch"
        )
        for name in NODES:
            if name in watch.peak:
                print(
                    f"  {name:15s} peak RSS {watch.peak[name]:8.0f} MB  private max "
                    f"{figures['private_mb_max'][name]:7.0f} MB  growth from 1/4 of the views "
                    f"{figures['rss_growth_mb'][name]:+6.0f} MB"
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
        times = time_queries(
            client, scene, run_dir, args.queries, args.heatmap_queries, args.heatmap_views, args.heatmap_spread
        )
        report_queries(times, figures)
        figures["memory_series"] = {
            name: [[v, round(r), round(p)] for v, r, p in ser] for name, ser in sorted(watch.series.items())
        }
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
