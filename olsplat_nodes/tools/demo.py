"""``olsplat demo``: the main job of ``make demo``, end to end through the node graph.

1. make (or reuse) a simulated UAV flight: prior Gaussian map, replay log, annotated queries;
2. launch the replay graph (the shipped launch file ``replay``: ingest -> region encoder -> accumulator ->
   refiner -> query server, one process each, over ZeroMQ);
3. while the flight streams, ask the ground-station queries each time a new map version is out;
4. after the final map, ask them again over a view, write heatmap and mask PNGs, and a summary
   (frames, drops, answers, timings) to ``OUT/summary.json`` and ``OUT/summary.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import threading
import time
import uuid
from pathlib import Path

import numpy as np

DEMO_QUERIES = ("red roof buildings", "road", "trees", "cars")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help="simulated flight streamed through the node graph, queried from the ground"
    )
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (default: out)")
    parser.add_argument("--preset", default="small", help="simulator preset of the flight (default: small, 60 frames)")
    parser.add_argument("--seed", type=int, default=0, help="the generated town and flight")
    parser.add_argument("--launch", default="replay", help="the launch file of the graph (a shipped name or a path)")
    parser.add_argument("--port", type=int, default=5600, help="TCP port of the query server on 127.0.0.1")
    parser.add_argument("--timeout", type=float, default=1800.0, help="give up after this many seconds")
    parser.set_defaults(run=run)


def ensure_flight(folder: Path, preset: str, seed: int) -> dict:
    """The flight in ``folder`` when it was made with this preset and seed, else a new one."""
    from olsplat_sim.make import make_dataset
    from olsplat_sim.presets import PRESETS

    from ..errors import OlsplatInputError

    summary = folder / "scene.json"
    if summary.exists():
        made = json.loads(summary.read_text())
        if (
            made.get("preset", {}).get("name") == preset
            and made.get("seed") == seed
            and (folder / "replay.mcap").exists()
        ):
            print(f"flight: reusing {folder} ({preset}, seed {seed})")
            return made
    if preset not in PRESETS:
        raise OlsplatInputError(f"unknown preset {preset!r}; known: {', '.join(PRESETS)}")
    shutil.rmtree(folder, ignore_errors=True)
    print(f"flight: simulating {preset} (seed {seed}) -> {folder}")
    return make_dataset(PRESETS[preset], seed, folder)


class Ground:
    """The ground station's side of the demo: queries over the real ZeroMQ link."""

    def __init__(self, endpoint: str, texts: list[str], timeout_s: float = 60.0):
        import zmq

        from ..transport import QueryClient

        self.client = QueryClient(zmq.Context.instance(), endpoint, timeout_s=timeout_s)
        self.texts = texts
        self.log: list[dict] = []
        self.latency_ms: dict[str, list[float]] = {}  # node -> mean latencies seen while streaming

    def ask(self, text: str, view: str = "", phase: str = "streaming"):
        from olsplat_msgs import QueryRequest

        negatives = [t for t in self.texts if t != text]
        start = time.perf_counter()
        reply = self.client.request(
            QueryRequest(
                request_id=uuid.uuid4().hex[:12],
                text=text,
                view=view,
                heatmap=bool(view),
                threshold=float("nan"),
                negatives=negatives,
            )
        )
        found = [i for i in reply.instances if i["kind"] == "3d"]
        self.log.append(
            {
                "phase": phase,
                "text": text,
                "view": view,
                "status": reply.status,
                "message": reply.message,
                "map_version": reply.map_version,
                "instances_3d": len(found),
                "regions_2d": len(reply.instances) - len(found),
                "round_trip_s": round(time.perf_counter() - start, 3),
                "server_s": round(reply.seconds, 3),
            }
        )
        print(
            f"  ground: {text!r:22} map v{reply.map_version:<3d} {reply.status:6s} {len(found):3d} instances in 3D  "
            f"({self.log[-1]['round_trip_s']:.2f} s)"
        )
        return reply

    def close(self) -> None:
        self.client.close()

    def status(self):
        from olsplat_msgs import StatusRequest

        return self.client.request(StatusRequest(request_id=uuid.uuid4().hex[:12]))

    def wait_for_version(self, version: int, timeout_s: float) -> None:
        """Block until the query server answers from map ``version`` (or newer); an error naming
        the version it still serves after ``timeout_s``."""
        from ..errors import OlsplatInputError

        deadline = time.monotonic() + timeout_s
        served = self.status().map_version
        while served < version:
            if time.monotonic() > deadline:
                raise OlsplatInputError(
                    f"the query server still serves map version {served} {timeout_s:.0f} s after version {version} "
                    "was written"
                )
            time.sleep(0.2)
            served = self.status().map_version

    def sample_status(self) -> None:
        """Keep each node's reported mean latency while the flight streams (its window is the
        last 10 s, so the figures at the end would only describe an idle graph)."""
        for node in self.status().nodes:
            latency = node["values"].get("latency_ms", 0.0)
            if latency > 0:
                self.latency_ms.setdefault(node["node"], []).append(latency)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..evaluate.scene_eval import label_texts, load_queries
    from ..launcher import Supervisor, find_launch_file, load_launch
    from ..storage.snapshot import latest_map
    from ..viz import write_query_pictures
    from .ground import print_status

    out: Path = args.out
    find_launch_file(args.launch)  # a wrong --launch fails now, not after the flight is simulated
    started = time.perf_counter()
    flight = out / "flight"
    made = ensure_flight(flight, args.preset, args.seed)
    launched = time.perf_counter()  # the stream's clock starts at the launch, not before making the flight
    labels, queries = load_queries(flight)
    texts = label_texts(labels, queries)
    run_dir = out / "run"
    shutil.rmtree(run_dir, ignore_errors=True)  # a fresh store: the demo aggregates every frame itself
    endpoint = f"tcp://127.0.0.1:{args.port}"
    ply = str((flight / "map" / "point_cloud.ply").resolve())
    overrides = [
        f"ingest.source={(flight / 'replay.mcap').resolve()}",
        f"query_server.map={ply}",
        f"accumulator.map={ply}",
        f"refiner.map={ply}",
        f"query_server.query_endpoint={endpoint}",
        "refiner.exit_on_final=false",
        "launch.exit_when=[]",  # the demo asks its last queries, then stops the graph
    ]
    config = load_launch(args.launch, overrides=overrides, run_dir=str(run_dir))
    supervisor = Supervisor(config)
    exit_code: list[int] = []
    supervisor.check()  # a bad launch file is an error here, not in the thread
    thread = threading.Thread(target=lambda: exit_code.append(supervisor.run()), daemon=True)
    thread.start()
    print(
        f"graph: {len(config.nodes)} nodes launched (logs in {run_dir / 'logs'}); streaming {made.get('views', '?')} "
        "frames"
    )
    ground = Ground(endpoint, texts)
    asked_version = 0
    record = None
    try:
        while time.perf_counter() - started < args.timeout:
            if exit_code:
                raise OlsplatInputError(f"the graph stopped early (exit {exit_code[0]}); see {run_dir / 'logs'}")
            record = latest_map(run_dir / "map")
            if record and record["version"] > asked_version and not record["final"]:
                print(f"map version {record['version']}: {record['views']} views aggregated so far")
                for text in DEMO_QUERIES[:2]:
                    ground.ask(text, phase="streaming")
                asked_version = record["version"]
            if record and record["final"]:
                break
            ground.sample_status()
            time.sleep(1.0)
        else:
            raise OlsplatInputError(f"the flight was not processed within {args.timeout:.0f} s; see {run_dir / 'logs'}")
        stream_seconds = time.perf_counter() - launched
        print(
            f"final map: version {record['version']}, {record['views']} views, {record['observed_gaussians']:,} "
            "Gaussians observed"
        )
        # the final snapshot is on disk before the query server has loaded it (it loads on the
        # refiner's announcement or its 2 s check): the final queries wait for it to say so
        ground.wait_for_version(record["version"], timeout_s=60.0)
        view = sorted((flight / "annotations").glob("*.json"))[0].stem  # an annotated view
        pictures = out / "ground"
        for text in DEMO_QUERIES:
            reply = ground.ask(text, view=view, phase="final")
            if reply.status == "ok" and reply.heatmap is not None:
                boxes = [tuple(i["box2d"]) for i in reply.instances if i["kind"] == "2d"]
                write_query_pictures(
                    pictures,
                    reply.view or view,
                    text,
                    reply.image,
                    reply.heatmap,
                    (reply.heatmap != 0).astype("float32"),
                    reply.mask,
                    boxes,
                    map_version=reply.map_version,
                )
        status = ground.status()
        print_status(status, as_json=False)
    finally:
        ground.close()
        supervisor.request_stop(0)
        thread.join(30)
    nodes = {n["node"]: n["values"] for n in status.nodes}
    summary = {
        "flight": {"preset": args.preset, "seed": args.seed, "frames": made.get("views")},
        "frames_aggregated": record["views"],
        "map_version": record["version"],
        "drops": {name: int(v.get("dropped", 0)) + int(v.get("gaps", 0)) for name, v in nodes.items()},
        "bad_messages": {name: int(v.get("bad_messages", 0)) for name, v in nodes.items()},
        "node_latency_ms": {name: round(float(np.mean(ground.latency_ms.get(name, [0.0]))), 1) for name in nodes},
        "stream_seconds": round(stream_seconds, 1),
        "total_seconds": round(time.perf_counter() - started, 1),
        "queries": ground.log,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    write_summary_md(out / "summary.md", summary)
    print(f"summary -> {out / 'summary.json'}, {out / 'summary.md'}; pictures -> {pictures}/")
    # the page's negatives are then the flight's labels (queries.json beside the map's folder)
    print(f"look at the map in a browser (http://127.0.0.1:8080):\n  .venv/bin/olsplat ground web --run {run_dir}")
    return 0


def write_summary_md(path: Path, s: dict) -> None:
    lines = [
        "# olsplat demo",
        "",
        f"Flight: {s['flight']['preset']} preset, seed {s['flight']['seed']}, {s['flight']['frames']} frames; "
        f"{s['frames_aggregated']} aggregated into map version {s['map_version']} in {s['stream_seconds']} s "
        f"(total {s['total_seconds']} s).",
        "",
        "| node | drops | bad messages | mean latency while streaming, ms |",
        "|---|---|---|---|",
        *[f"| {n} | {s['drops'][n]} | {s['bad_messages'][n]} | {s['node_latency_ms'][n]} |" for n in s["drops"]],
        "",
        "| phase | query | view | map version | status | 3D instances | 2D regions | round trip s |",
        "|---|---|---|---|---|---|---|---|",
        *[
            f"| {q['phase']} | {q['text']} | {q['view']} | {q['map_version']} | {q['status']} | {q['instances_3d']} | "
            f"{q['regions_2d']} | {q['round_trip_s']} |"
            for q in s["queries"]
        ],
    ]
    path.write_text("\n".join(lines) + "\n")
