"""``olsplat bench cluster``: the aggregation on a local Ray cluster, by tile size and worker count.

For each worker count W (a local cluster of W worker slots, on 127.0.0.1) and each tile size,
the flights are aggregated from scratch into ``--work``/``tiles<M>_workers<W>``: wall time,
views/s, each tile actor's peak resident set (its shard and its refinement), the highest of the
view tasks' worker processes (the memory-mapped map and a view's render), the driver's (the
union map), and the store's bytes per tile. The region features come from the scenes' encode
cache, filled first (not timed: ``olsplat bench encode`` times them). Needs olsplat[cluster].

Two cores give no speed-up from more workers here; the point is the memory per actor, which
falls with the tile count, and what a city-scale map needs from it (docs/cluster.md).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "cluster", help="aggregation on a local Ray cluster: wall time and memory per tile actor, by tiles and workers"
    )
    parser.add_argument(
        "--scene", required=True, type=Path, action="append", help="a flight's scene folder; repeatable"
    )
    parser.add_argument("--tile-m", default="0,100", help="tile sizes in metres, comma-separated (0: one tile)")
    parser.add_argument("--workers", default="1,2", help="worker slots of the local cluster, comma-separated")
    parser.add_argument("--views", type=int, help="the first N views of each flight (default: all)")
    parser.add_argument("--method", default="outlangsplat", help="the method (default outlangsplat)")
    parser.add_argument("--work", required=True, type=Path, help="folder for the runs' stores (emptied per run)")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.set_defaults(run=run)


def _numbers(text: str, kind, name: str) -> list:
    from ..errors import OlsplatInputError

    try:
        values = [kind(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = []
    if not values or any(v < 0 for v in values):
        raise OlsplatInputError(f"{name} must be comma-separated numbers >= 0, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..cluster.ray_aggregate import aggregate_on_ray, connect, leave
    from ..encoders.spec import DEFAULT_SPEC, encoder_from_spec
    from ..errors import OlsplatInputError
    from ..memory import reset_peak_rss
    from ..method import named_method
    from ..pipeline import Scene, view_features

    tiles, workers = _numbers(args.tile_m, float, "--tile-m"), _numbers(args.workers, int, "--workers")
    if 0 in workers:
        raise OlsplatInputError("--workers must be >= 1")
    scenes = [Scene.open(folder) for folder in args.scene]
    scenes = [Scene(s.folder, s.ply, s.cameras[: args.views]) for s in scenes]
    encoder = encoder_from_spec()
    for scene in scenes:  # the encode cache first: every run reads the same features
        for camera in tqdm(scene.cameras, desc=f"features {scene.folder.name} (cached)", unit="view"):
            view_features(scene, camera, encoder)
    method = named_method(args.method)
    runs = []
    for count in workers:
        connect("auto", num_cpus=count)  # a local cluster of ``count`` worker slots
        try:
            for tile_m in tiles:
                out = args.work / f"tiles{tile_m:g}_workers{count}"
                shutil.rmtree(out, ignore_errors=True)
                reset_peak_rss()  # the driver's peak of this run, not of the runs before it
                stats = aggregate_on_ray(scenes, method, (DEFAULT_SPEC, None), out, tile_m)
                shards = [p for p in (out / "store").iterdir() if p.is_dir()] if tile_m else [out / "store"]
                sizes = [sum(f.stat().st_size for f in p.rglob("*.npy")) / 2**20 for p in shards]
                row = {
                    "tile_m": tile_m,
                    "workers": count,
                    "tiles": stats["tiles"],
                    "views": sum(len(s.cameras) for s in scenes),
                    "wall_s": round(stats["seconds"], 1),
                    "views_per_s": round(stats["views_per_second"], 3),
                    "actor_peak_rss_mb": [round(m) for m in stats["actor_peak_rss_mb"]],
                    "worker_peak_rss_mb": round(stats["worker_peak_rss_mb"]),
                    "driver_peak_rss_mb": round(stats["peak_rss_mb"]),
                    "store_mb_per_tile": [round(m, 1) for m in sizes],
                    "observed_gaussians": stats["observed_gaussians"],
                }
                runs.append(row)
                print(
                    f"tiles {row['tiles']} ({tile_m:g} m), workers {count}: {row['wall_s']} s "
                    f"({row['views_per_s']} views/s); tile actors' peak RSS {row['actor_peak_rss_mb']} MB "
                    f"(max {max(row['actor_peak_rss_mb'])}); view workers' peak {row['worker_peak_rss_mb']} MB; "
                    f"driver {row['driver_peak_rss_mb']} MB; store per tile {row['store_mb_per_tile']} MB",
                    flush=True,
                )
        finally:
            leave()
    if args.json:
        args.json.write_text(json.dumps({"runs": runs}, indent=1))
    return 0
