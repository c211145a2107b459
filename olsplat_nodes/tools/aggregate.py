"""``olsplat aggregate``: the method offline on a scene folder, into a language map."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    from .method_names import DEFAULT_ENCODER, METHOD_NAMES

    agg = subparsers.add_parser("aggregate", help="aggregate a scene's views into a language map")
    agg.add_argument("--scene", required=True, type=Path, help="a scene folder (olsplat sim make, or images + COLMAP)")
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
    agg.set_defaults(run=run_aggregate)


def run_aggregate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..method import MethodParams
    from ..params import parse_assignments, parse_params
    from ..pipeline import Scene, aggregate_scene
    from .outputs import output_folder

    output_folder(args.out)  # before the work: a bad --out is one line at the start
    settings = parse_assignments(args.set, "--set")
    if "method" in settings:
        raise OlsplatInputError("--set method=...: choose the method with --method")
    settings["method"] = args.method
    method = parse_params(MethodParams, settings, "--set").resolve("--set")  # before any work
    scene = Scene.open(args.scene)
    encoder = encoder_from_spec(args.encoders, args.weights)
    if args.codebook is not None and not 2 <= args.codebook <= 65_534:
        raise OlsplatInputError(f"--codebook must be between 2 and 65534 centres, got {args.codebook}")
    stats = aggregate_scene(
        scene, method, encoder, args.out, lambda xs: tqdm(xs, desc=args.method, unit="view"), args.codebook
    )
    print(
        f"{args.method}: {len(scene.cameras)} views in {stats['seconds']:.1f} s "
        f"({stats['views_per_second']:.2f} views/s), peak memory {stats['peak_rss_mb']:.0f} MB, "
        f"{stats['observed_gaussians']:,} Gaussians observed -> {args.out}"
    )
    return 0
