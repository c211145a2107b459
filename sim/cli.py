"""``olsplat sim make`` and ``olsplat sim replay``."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

from .presets import PRESETS


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("sim", help="synthetic UAV scenes: make a dataset, replay a log")
    commands = parser.add_subparsers(dest="sim_command", required=True, metavar="COMMAND")

    make = commands.add_parser(
        "make",
        help="generate a scene, fly over it, write a dataset",
        epilog="examples:\n  olsplat sim make --preset tiny --seed 0 --out scene\n"
        "  olsplat sim make --preset small --seed 1 --out small1 --views 30\n"
        "  olsplat sim make --preset small --seed 1 --flight-seed 7 --out small1-f7   # small1's map, another flight\n"
        "  olsplat sim make --preset small --seed 1 --flight-seed 8 --changes default --out small1-f8  # changed",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    make.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="tiny",
        help="scene size: "
        + "; ".join(f"{k}: {p.n_gaussians:,} Gaussians, {p.n_views} views" for k, p in PRESETS.items())
        + " (default tiny)",
    )
    make.add_argument(
        "--seed",
        type=int,
        default=0,
        help="the town, its map and its flight (default 0; seeds >= 1000 train the shipped encoders)",
    )
    make.add_argument(
        "--flight-seed",
        type=int,
        metavar="M",
        help="fly the town of --seed again on another path (turned, other noise; frames flight<M>_frame_NNNN.jpg): "
        "the same map/point_cloud.ply, so that flights can be aggregated into one map (default: the seed's flight)",
    )
    make.add_argument(
        "--changes",
        metavar="SPEC",
        help="with --flight-seed: the flight sees the town after changes (the map stays the one of before; "
        "truth/changes/ says what changed): default (a mix of every kind, sized to the town), none, or "
        "kind=N,... of cars_moved, cars_added, cars_removed, objects_added, roofs_damaged, roofs_recoloured, "
        "trees_felled, flooded_m2, burnt_m2 (sim/README.md, 'Changes between flights')",
    )
    make.add_argument("--out", type=Path, required=True, help="a new or empty folder for the dataset")
    make.add_argument("--force", action="store_true", help="empty --out first if it holds files")
    make.add_argument("--views", type=int, help="override the preset's number of views")
    make.add_argument("--gaussians", type=int, help="override the preset's number of Gaussians")
    make.add_argument("--rate", type=float, default=1.0, metavar="HZ", help="frame rate of the flight (default 1)")
    make.add_argument("--fov", type=float, default=50.0, metavar="DEG", help="horizontal field of view (default 50)")
    make.add_argument(
        "--motion-blur", type=float, default=0.0, metavar="SECONDS", help="shutter time for motion blur (0: none)"
    )
    make.add_argument("--no-pose-noise", action="store_true", help="write the true poses to sparse/0 and the log")
    make.add_argument(
        "--bag",
        nargs="?",
        const="mcap",
        choices=("mcap", "sqlite3"),
        metavar="STORAGE",
        help="also write the flight as a ROS 2 bag, replay_bag/ (rosbag2 folder; storage mcap or sqlite3, "
        "default mcap): replay.mcap's frames for ros2 bag and other ROS tools",
    )
    make.add_argument(
        "--world",
        choices=("v1", "v2", "v2g"),
        default="v1",
        help="the evaluation world (sim/README.md, 'Worlds'): v1 as before; v2 adds view-dependent appearance, "
        "a varying altitude, tilted nadir views, haze, cloud shadows and a calibrated camera; v2g is v2 with "
        "geometry that follows the labels (geometry.strength=1) (default v1)",
    )
    make.add_argument(
        "--world-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one world setting (repeatable; dotted keys, YAML values), "
        "e.g. --world-set sensor.vignette=0 --world-set haze.beta=0.002 --world-set clouds.wind_mps=[3,0]",
    )
    make.set_defaults(run=run_make)

    train = commands.add_parser("train-encoders", help="train the compact encoders shipped in the package")
    train.add_argument("--out", type=Path, help="output folder (default: the package's encoders/assets)")
    train.add_argument("--seeds", type=int, default=10, help="training scenes (seeds 1000, 1001, ...)")
    train.add_argument("--views", type=int, default=16, help="views per scene")
    train.add_argument("--epochs", type=int, default=8, help="passes over the training crops")
    train.set_defaults(run=run_train)

    pair = commands.add_parser(
        "train-pair", help="train the independent encoder pair (olsplat-nadir32, olsplat-oblique48; sim/train_pair.py)"
    )
    pair.add_argument("--work", type=Path, required=True, help="work folder: rungs, scores.json, train_pair.json")
    pair.add_argument("--out", type=Path, help="export the chosen encoders to OUT/NAME (e.g. the package's assets)")
    pair.add_argument("--scenes", type=Path, help="folder of the validation scenes val2000... (default WORK/scenes)")
    pair.add_argument("--seeds", type=int, default=10, help="training scenes per encoder (A: 3000..., B: 4000...)")
    pair.add_argument("--views", type=int, default=16, help="views per scene")
    pair.set_defaults(run=run_train_pair)

    structure = commands.add_parser(
        "train-structure",
        help="pre-train the 3D branch's MinkUNet (SegContrast, no labels) on training-seed maps",
        epilog="examples:\n  olsplat sim train-structure   # seeds 1000-1002, 1200 windows: ~18 min on one core\n"
        "  olsplat sim train-structure --cr 1 --steps 3000 --out minkunet-full.pt",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    structure.add_argument("--out", type=Path, help="checkpoint file (default: the package's shipped one)")
    structure.add_argument("--seeds", type=int, default=3, help="training maps (seeds 1000, 1001, ...; default 3)")
    structure.add_argument("--preset", choices=sorted(PRESETS), default="small", help="map size (default small)")
    structure.add_argument("--steps", type=int, default=1200, help="training windows (default 1200)")
    structure.add_argument(
        "--cr", type=float, default=0.25, help="channel ratio; 1.0 = SegContrast's size (default 0.25)"
    )
    structure.add_argument("--seed", type=int, default=0, help="seed of the windows and augmentations")
    structure.set_defaults(run=run_train_structure)

    zero = commands.add_parser("zeroshot", help="region-level zero-shot accuracy on held-out scenes")
    zero.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="evaluation seeds (< 1000)")
    zero.add_argument("--views", type=int, default=12, help="views per evaluation scene")
    zero.add_argument("--encoders", help="comma-separated extra encoder folders to evaluate too")
    zero.set_defaults(run=run_zeroshot)

    replay = commands.add_parser("replay", help="play a replay log (.mcap) or an image folder + COLMAP model")
    replay.add_argument(
        "--log", type=Path, required=True, help="a replay log (.mcap) or an image folder + COLMAP model"
    )
    pace = replay.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, metavar="HZ", help="frames per second (default: as recorded)")
    pace.add_argument("--fast", action="store_true", help="as fast as possible")
    replay.add_argument("--limit", type=int, help="stop after this many frames")
    replay.set_defaults(run=run_replay)


def run_make(args: argparse.Namespace) -> int:
    from olsplat_nodes.errors import OlsplatInputError
    from olsplat_nodes.outputs import empty_output_folder

    from .make import MakeOptions, make_dataset
    from .reconstruct import ReconstructionSpec
    from .world import WORLDS, with_settings

    preset = PRESETS[args.preset]
    changes = {k: v for k, v in (("n_views", args.views), ("n_gaussians", args.gaussians)) if v is not None}
    if any(v <= 0 for v in changes.values()):
        raise OlsplatInputError(f"--views and --gaussians must be positive, got {changes}")
    if args.rate <= 0 or not 5.0 <= args.fov <= 150.0 or args.motion_blur < 0:
        raise OlsplatInputError(
            f"need --rate > 0, 5 <= --fov <= 150, --motion-blur >= 0; got {args.rate}, {args.fov}, {args.motion_blur}"
        )
    if args.flight_seed is not None and args.flight_seed < 0:
        raise OlsplatInputError(f"--flight-seed must be >= 0, got {args.flight_seed}")
    preset = dataclasses.replace(preset, **changes)
    change_spec = None
    if args.changes is not None:
        from .change_spec import ChangeSpec

        if args.flight_seed is None:
            raise OlsplatInputError("--changes needs --flight-seed: changes happen between two flights of a town")
        try:
            change_spec = ChangeSpec.parse(args.changes, preset.size_m)
        except ValueError as exc:
            raise OlsplatInputError(str(exc)) from None
    try:
        world = with_settings(WORLDS[args.world], args.world_set)
    except ValueError as exc:
        raise OlsplatInputError(str(exc)) from None
    if args.motion_blur:
        world = dataclasses.replace(world, sensor=dataclasses.replace(world.sensor, blur_exposure_s=args.motion_blur))
    empty_output_folder(args.out, args.force)
    recon = (
        ReconstructionSpec(pose_position_m=0.0, pose_rotation_deg=0.0) if args.no_pose_noise else ReconstructionSpec()
    )
    options = MakeOptions(world, recon, rate_hz=args.rate, fov_deg=args.fov)
    try:
        make_dataset(
            preset, args.seed, args.out, options, flight_seed=args.flight_seed, bag=args.bag, changes=change_spec
        )
    except ValueError as exc:  # a town too small for the changes asked for (changes.py), before any file is written
        if change_spec is None or not str(exc).startswith("--changes"):
            raise
        raise OlsplatInputError(str(exc)) from None
    return 0


def run_replay(args: argparse.Namespace) -> int:
    from olsplat_nodes.sources.replay_log import paced, read_replay

    start, count, first = time.monotonic(), 0, None
    for frame in paced(read_replay(args.log), rate_hz=args.rate, fast=args.fast):
        first = frame.stamp_ns if first is None else first
        x, y, z = frame.camera.center
        print(
            f"{frame.seq:5d} {frame.name:20s} t={(frame.stamp_ns - first) / 1e9:8.3f} s  "
            f"{frame.camera.width}x{frame.camera.height}  camera at ({x:7.1f}, {y:7.1f}, {z:6.1f}) m"
        )
        count += 1
        if args.limit and count >= args.limit:
            break
    elapsed = time.monotonic() - start
    print(f"{count} frames in {elapsed:.2f} s ({count / max(elapsed, 1e-9):.1f} frames/s)")
    return 0


def run_train_pair(args: argparse.Namespace) -> int:
    from olsplat_nodes.extras import require

    require("torch", "olsplat sim train-pair", "sim")
    import torch

    torch.set_num_threads(1)  # the budget ladder's timings and results are those of one thread
    from .train_pair import main

    argv = ["--work", str(args.work), "--seeds", str(args.seeds), "--views", str(args.views)]
    argv += ["--out", str(args.out)] if args.out is not None else []
    argv += ["--scenes", str(args.scenes)] if args.scenes is not None else []
    return main(argv)


def run_train(args: argparse.Namespace) -> int:
    from olsplat_nodes.extras import require

    require("torch", "olsplat sim train-encoders", "sim")
    from .train_encoders import ASSETS, train_all

    train_all(args.out or ASSETS, args.seeds, args.views, args.epochs)
    return 0


def run_train_structure(args: argparse.Namespace) -> int:
    from olsplat_nodes.extras import require

    for module in ("torch", "open3d"):
        require(module, "olsplat sim train-structure", "sim,structure")
    from olsplat_nodes.structure.branch import SHIPPED_MINKUNET
    from olsplat_nodes.structure.segcontrast import PretrainConfig

    from .train_structure import train_structure

    config = PretrainConfig(cr=args.cr, steps=args.steps, seed=args.seed)
    train_structure(args.out or SHIPPED_MINKUNET, args.seeds, args.preset, config)
    return 0


def run_zeroshot(args: argparse.Namespace) -> int:
    from olsplat_nodes.encoders.onnx_encoder import OnnxEncoder
    from olsplat_nodes.encoders.shipped import SHIPPED, default_encoder, shipped_encoder
    from olsplat_nodes.errors import OlsplatInputError

    from .labels import LABELS
    from .zeroshot import evaluate, label_queries

    encoders: dict[str, Any] = {name: shipped_encoder(name) for name in SHIPPED}
    encoders["fusion (lambda_2D = 0.6)"] = default_encoder()
    for folder in (args.encoders or "").split(",") if args.encoders else []:
        encoder = OnnxEncoder(Path(folder))
        encoders[folder if encoder.name in encoders else encoder.name] = encoder  # a retrained shipped one: its folder
    try:
        results = evaluate(encoders, args.seeds, args.views)
    except ValueError as exc:
        raise OlsplatInputError(str(exc)) from None
    counts = results.pop("_counts")
    print(
        f"held-out seeds {args.seeds}, {args.views} views each, {int(counts.sum())} regions; queries: {label_queries()}"
    )
    short = [label.replace(" buildings", "") for label in LABELS]
    print(f"{'encoder':26s} {'accuracy':>8s} {'balanced':>8s}  " + " ".join(f"{s[:9]:>9s}" for s in short))
    print(f"{'(regions per label)':26s} {'':>8s} {'':>8s}  " + " ".join(f"{int(c):>9d}" for c in counts))
    for name, r in results.items():
        cells = " ".join(f"{v:>9.2f}" if v == v else f"{'-':>9s}" for v in r["per_label"])
        print(f"{name:26s} {r['accuracy']:>8.3f} {r['balanced']:>8.3f}  {cells}")
    return 0
