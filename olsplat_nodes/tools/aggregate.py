"""``olsplat aggregate``: the method offline on a scene folder, into a language map."""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path


def add_parser(subparsers) -> None:
    from .method_names import DEFAULT_ENCODER, METHOD_NAMES

    agg = subparsers.add_parser("aggregate", help="aggregate a scene's views into a language map")
    agg.add_argument(
        "--scene",
        required=True,
        type=Path,
        action="append",
        help="a scene folder (olsplat sim make, or images + COLMAP); repeat it for several flights over one prior "
        "map, aggregated into one map",
    )
    agg.add_argument(
        "--method",
        default="outlangsplat",
        choices=sorted(METHOD_NAMES),
        help="the method or a baseline (olsplat_nodes/method/table.py)",
    )
    agg.add_argument(
        "--encoders",
        default=DEFAULT_ENCODER,
        help=f"shipped names (default {DEFAULT_ENCODER}), 'shipped' (both fused) or exported folders",
    )
    agg.add_argument("--weights", help="fusion weights, e.g. 0.6,0.4")
    agg.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a method parameter, as in launch files (tau_d=0.3, beta=[1,2,4], topk_max=24); repeatable; "
        "names: olsplat_nodes/method/params.py",
    )
    agg.add_argument("--out", required=True, type=Path, help="output folder (store + language_map.npz)")
    agg.add_argument(
        "--codebook",
        type=int,
        metavar="K",
        help="store the map as K-centre codebook codes (~100x smaller; K=1024 is a good choice)",
    )
    agg.add_argument(
        "--tile-m",
        type=float,
        default=0.0,
        metavar="M",
        help="keep the store per ground tile of M metres (x-y cells of the map's frame; default 0: one tile); "
        "the same map, a tile per Ray actor with --cluster",
    )
    agg.add_argument(
        "--per-flight",
        action="store_true",
        help="also write one map per flight, OUT/flights/f<k>/language_map.npz (float16, with the evidence change "
        "scores need; flight k = the k-th --scene) and OUT/flights/flights.json",
    )
    agg.add_argument(
        "--cluster",
        metavar="ADDRESS",
        help="run on a Ray cluster (pip install olsplat[cluster]): 'auto' (the one `ray start` runs here, else a "
        "local one on 127.0.0.1) or ray://HOST:PORT",
    )
    agg.set_defaults(run=run_aggregate)


def run_aggregate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..method import MethodParams
    from ..outputs import output_folder
    from ..params import parse_assignments, parse_params
    from ..pipeline import Scene
    from ..pipeline.offline import aggregate_flights
    from ..storage.tiles import TileGrid

    output_folder(args.out)  # before the work: a bad --out is one line at the start
    settings = parse_assignments(args.set, "--set")
    if "method" in settings:
        raise OlsplatInputError("--set method=...: choose the method with --method")
    settings["method"] = args.method
    method = parse_params(MethodParams, settings, "--set").resolve("--set")  # before any work
    scenes = [Scene.open(folder) for folder in args.scene]
    if args.codebook is not None and not 2 <= args.codebook <= 65_534:
        raise OlsplatInputError(f"--codebook must be between 2 and 65534 centres, got {args.codebook}")
    TileGrid(args.tile_m)  # a bad size is one line before any work
    views = sum(len(scene.cameras) for scene in scenes)
    if args.cluster:
        try:
            from ..cluster.ray_aggregate import aggregate_on_ray
        except ImportError as exc:
            raise OlsplatInputError(f"--cluster needs Ray: pip install 'olsplat[cluster]' ({exc})") from exc
        bar = tqdm(total=views, desc=args.method, unit="view")

        def advance(done: int, _total: int) -> None:
            bar.update(done - bar.n)

        stats = aggregate_on_ray(
            scenes,
            method,
            (args.encoders, args.weights),
            args.out,
            args.tile_m,
            args.cluster,
            args.codebook,
            advance,
        )
        bar.close()
    else:
        encoder = encoder_from_spec(args.encoders, args.weights)
        stats = aggregate_flights(
            scenes,
            method,
            encoder,
            args.out,
            lambda xs: tqdm(xs, desc=args.method, unit="view"),
            args.codebook,
            tile_m=args.tile_m,
        )
    flights = _flight_maps(args, scenes, method) if args.per_flight else []
    print(
        f"{args.method}: {views} views of {len(scenes)} flight(s)"
        + (f" ({stats['views_refused']} refused: off the map)" if stats.get("views_refused") else "")
        + f", {stats['tiles']} tile(s), in "
        f"{stats['seconds']:.1f} s ({stats['views_per_second']:.2f} views/s), "
        f"peak memory {stats['peak_rss_mb']:.0f} MB, "
        f"{stats['observed_gaussians']:,} Gaussians observed -> {args.out}"
    )
    for record in flights:
        print(f"  flight {record['flight']}: {record['views']} views -> {args.out / 'flights' / record['map']}")
    for before, after in itertools.pairwise(flights):
        print(f"  {_change_line(args.out / 'flights', before, after)}")
    return 0


def _change_line(folder: Path, before: dict, after: dict) -> str:
    """One line on the change scores from one flight's map to the next (``aggregate/change.py``)."""
    import numpy as np

    from ..aggregate.change import ChangeRule, change_score
    from ..storage import LanguageMap

    rule = ChangeRule()
    score = change_score(LanguageMap.load(folder / before["map"]), LanguageMap.load(folder / after["map"]), rule)
    scored = score[np.isfinite(score)]
    if not len(scored):
        return f"change {before['flight']} -> {after['flight']}: no Gaussian seen well enough by both flights"
    p50, p99, p999 = np.percentile(scored, [50, 99, 99.9])
    return (
        f"change {before['flight']} -> {after['flight']}: {len(scored):,} of {len(score):,} Gaussians seen well "
        f"enough by both; score p50 {p50:.2f}, p99 {p99:.2f}, p99.9 {p999:.2f}, max {scored.max():.2f}; "
        f"{int((scored > rule.threshold).sum()):,} above {rule.threshold:g}"
    )


def _flight_maps(args: argparse.Namespace, scenes: list, method) -> list[dict]:
    """Each flight's map from the run's store (``storage/flights.py``); the index's records."""
    from ..pipeline.offline import same_prior_map
    from ..storage import LanguageMap
    from ..storage.flights import write_flight_maps
    from ..storage.tiles import TileGrid, Tiling

    tiling = Tiling.of(same_prior_map(scenes).means, TileGrid(args.tile_m))
    encoder = LanguageMap.load(args.out / "language_map.npz", decode=False).encoder  # what the run's map says
    return write_flight_maps(args.out, tiling, method.aggregation, encoder, [str(s.folder) for s in scenes])
