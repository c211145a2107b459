"""``olsplat aggregate`` and ``olsplat eval``: the method offline on a scene folder."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_parser(subparsers) -> None:
    from ..pipeline import METHODS

    agg = subparsers.add_parser("aggregate", help="aggregate a scene's views into a language map")
    agg.add_argument("--scene", required=True, type=Path)
    agg.add_argument("--method", default="outlangsplat", choices=sorted(METHODS))
    agg.add_argument("--encoders", default="shipped", help="'shipped' (default), shipped names or exported folders")
    agg.add_argument("--weights", help="fusion weights, e.g. 0.6,0.4")
    agg.add_argument("--out", required=True, type=Path, help="output folder (store + language_map.npz)")
    agg.add_argument("--codebook", type=int, metavar="K", help="store the map as K-centre codebook codes (~100x smaller; K=1024 is a good choice)")
    agg.set_defaults(run=run_aggregate)

    ev = subparsers.add_parser("eval", help="aggregate with several methods and score them on the annotations")
    ev.add_argument("--scene", required=True, type=Path, action="append", help="a scene folder; repeat for several scenes")
    ev.add_argument("--methods", default="outlangsplat,projection,topk,vala", help=f"comma-separated, from: {', '.join(METHODS)}")
    ev.add_argument("--encoders", default="shipped")
    ev.add_argument("--weights")
    ev.add_argument("--work", type=Path, help="folder for the per-method maps (default: SCENE/eval)")
    ev.add_argument("--json", type=Path, help="write the results here")
    ev.add_argument("--md", type=Path, help="write the paper's tables (Markdown) here")
    ev.add_argument("--figures", type=Path, help="write side-by-side heatmaps per view and query here")
    ev.add_argument("--figure-views", type=int, default=2, help="annotated views per scene in --figures (default 2)")
    ev.set_defaults(run=run_eval)


def run_aggregate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..pipeline import Scene, aggregate_scene

    scene = Scene.open(args.scene)
    encoder = encoder_from_spec(args.encoders, args.weights)
    if args.codebook is not None and not 2 <= args.codebook <= 65_534:
        raise OlsplatInputError(f"--codebook must be between 2 and 65534 centres, got {args.codebook}")
    stats = aggregate_scene(scene, args.method, encoder, args.out, lambda xs: tqdm(xs, desc=args.method, unit="view"), args.codebook)
    print(f"{args.method}: {len(scene.cameras)} views in {stats['seconds']:.1f} s ({stats['views_per_second']:.2f} views/s), "
          f"peak memory {stats['peak_rss_mb']:.0f} MB, {stats['observed_gaussians']:,} Gaussians observed -> {args.out}")  # fmt: skip
    return 0


def run_eval(args: argparse.Namespace) -> int:
    import shutil

    from tqdm import tqdm

    from ..aggregate.snapshot import LanguageMap
    from ..encoders.spec import encoder_from_spec
    from ..evaluate import evaluate_map
    from ..evaluate.figures import qualitative_figures
    from ..evaluate.tables import overall, paper_tables
    from ..pipeline import Scene, aggregate_scene
    from ..pipeline.offline import method

    scenes = [Scene.open(folder) for folder in args.scene]  # every folder is checked before any work
    encoder = encoder_from_spec(args.encoders, args.weights)
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    for name in names:
        method(name)  # unknown names fail before any work
    titles = [s.folder.name for s in scenes]
    if len(set(titles)) < len(titles):
        titles = [str(s.folder) for s in scenes]
    results: dict[str, dict] = {}
    for title, scene in zip(titles, scenes):
        work = (args.work / title if len(scenes) > 1 else args.work) if args.work else scene.folder / "eval"
        results[title] = {}
        maps = {}
        for name in names:
            out = work / name
            shutil.rmtree(out, ignore_errors=True)
            stats = aggregate_scene(scene, name, encoder, out, progress=lambda xs, n=name: tqdm(xs, desc=n, unit="view"))
            maps[name] = LanguageMap.load(out / "language_map.npz")
            scores = evaluate_map(scene, maps[name], encoder)
            results[title][name] = {**scores, "seconds": stats["seconds"], "peak_rss_mb": stats["peak_rss_mb"]}
            print(f"{title}: {name:28s} mIoU {scores['mIoU']:5.1f}  mAcc {scores['mAcc']:5.1f}  Loc@40/50/60 "
                  f"{scores['loc40']:5.1f} {scores['loc50']:5.1f} {scores['loc60']:5.1f}  ({stats['seconds']:.0f} s)")  # fmt: skip
        if args.figures:
            folder = args.figures / title if len(scenes) > 1 else args.figures
            files = qualitative_figures(scene, maps, encoder, folder, args.figure_views)
            print(f"{title}: {len(files)} figures -> {folder}")
    tables = paper_tables(results)
    print()
    print(tables)
    if args.json:
        top = overall(results) if len(results) > 1 else results[titles[0]]
        document = {"methods": top}
        if len(results) > 1:
            document["scenes"] = {title: {"methods": runs} for title, runs in results.items()}
        args.json.write_text(json.dumps(document, indent=2))
    if args.md:
        args.md.write_text(tables)
    return 0
