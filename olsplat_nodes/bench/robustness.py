"""``olsplat bench robustness``: how the aggregation methods cope with view-specific feature errors.

Real vision-language encoders err differently from view to view (another crop scale, angle,
context); the shipped encoders on simulated frames err mostly the same way in every view, so
there aggregation has little to correct. This study injects view-specific errors: in every
view, each region's feature is, with probability ``p``, replaced by the feature of a random
region of the same view (the encoder "saw something else there"). The confusion of a view is
seeded by its index, so every method aggregates exactly the same corrupted features. Each
method is then scored on the scene's annotations as ``olsplat eval`` does. With ``--features
2d,2d3d`` each method also runs with the 3D branch (``olsplat eval --features 2d3d``): the
confusion hits the 2D bank before the fusion, so h_theta is taught by the confused 2D features.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np


def confuse(bank: list[np.ndarray], p: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Per level [R, D]: each row replaced with probability p by a random row of the same level."""
    out = []
    for features in bank:
        swapped = rng.random(len(features)) < p
        confused = features.copy()
        confused[swapped] = features[rng.integers(0, len(features), int(swapped.sum()))]
        out.append(confused)
    return out


def robustness_table(scores: dict[str, dict[str, dict[str, dict]]], scenes: list[str]) -> str:
    """Markdown: one row per method, one column per confusion p, "mIoU / Loc@50" averaged over
    the scenes; the best of each column in bold."""
    levels = list(next(iter(scores.values())))
    cells = {
        (label, p): (
            float(np.mean([scores[label][p][s]["mIoU"] for s in scenes])),
            float(np.mean([scores[label][p][s]["loc50"] for s in scenes])),
        )
        for label in scores
        for p in levels
    }
    best = {p: max(cells[label, p][0] for label in scores) for p in levels}
    lines = [
        f"**mIoU / Loc@50 (%) under view-specific confusion p** (mean over {len(scenes)} scene(s): "
        f"{', '.join(scenes)})",
        "",
        "| method | " + " | ".join(f"p = {p}" for p in levels) + " |",
        "| --- |" + " --- |" * len(levels),
    ]
    for label in scores:
        row = []
        for p in levels:
            miou, loc = cells[label, p]
            text = f"{miou:.1f} / {loc:.1f}"
            row.append(f"**{text}**" if miou == best[p] else text)
        lines.append(f"| {label} | " + " | ".join(row) + " |")
    return "\n".join(lines)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("robustness", help="methods under injected view-specific feature errors")
    parser.add_argument("--scene", required=True, type=Path, action="append", help="a scene folder; repeatable")
    parser.add_argument(
        "--methods",
        default="outlangsplat,outlangsplat-paper,projection,drsplat,topk,vala",
        help="comma-separated methods",
    )
    parser.add_argument("--confusion", default="0,0.15,0.3,0.45", help="comma-separated probabilities p")
    parser.add_argument("--seed", type=int, default=0, help="seed of the perturbations")
    parser.add_argument(
        "--features", default="2d", help="comma-separated, from: 2d, 2d3d (fused with the 3D branch, lambda_f 0.7)"
    )
    parser.add_argument("--json", type=Path, help="write every run's scores here")
    parser.add_argument("--md", type=Path, help="write the table (mean over the scenes) here, in Markdown")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..aggregate.snapshot import LanguageMap
    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate import evaluate_map
    from ..method import named_method
    from ..pipeline import Scene, aggregate_scene, view_features
    from ..structure.branch import StructureConfig

    scenes = [Scene.open(folder) for folder in args.scene]
    encoder = encoder_from_spec()
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    methods = {name: named_method(name) for name in names}  # unknown names fail before any work
    features = [f.strip() for f in args.features.split(",") if f.strip()]
    if not features or any(f not in ("2d", "2d3d") for f in features):
        raise OlsplatInputError(f"--features: comma-separated 2d, 2d3d; got {args.features!r}")
    levels = [float(x) for x in args.confusion.split(",")]
    if not levels or any(not 0.0 <= p <= 1.0 for p in levels):
        raise OlsplatInputError(f"--confusion: comma-separated probabilities in [0, 1], got {args.confusion!r}")
    print("p = share of each view's regions given another region's feature")
    scores: dict[str, dict[str, dict[str, dict]]] = {}  # label -> p -> scene -> scores
    for scene in scenes:
        index = {c.name: i for i, c in enumerate(scene.cameras)}
        for p in levels:

            def features_of(camera, p=p, scene=scene, index=index):
                label_maps, bank = view_features(scene, camera, encoder)
                return label_maps, confuse(bank, p, np.random.default_rng([args.seed, index[camera.name]]))

            for name, kind in ((n, f) for n in names for f in features):
                structure = StructureConfig() if kind == "2d3d" else None
                label = name if features == ["2d"] else f"{name} {kind}"
                with tempfile.TemporaryDirectory() as tmp:
                    stats = aggregate_scene(
                        scene, methods[name], encoder, Path(tmp), features_of=features_of, structure=structure
                    )
                    r = evaluate_map(scene, LanguageMap.load(Path(tmp) / "language_map.npz"), encoder)
                scores.setdefault(label, {}).setdefault(f"{p:g}", {})[scene.folder.name] = r
                print(
                    f"  {scene.folder.name} p {p:4.2f}  {label:28s} mIoU {r['mIoU']:5.1f}  mAcc {r['mAcc']:5.1f}  "
                    f"Loc@50 {r['loc50']:5.1f}  ({stats['seconds']:.0f} s)",
                    flush=True,
                )
    table = robustness_table(scores, [s.folder.name for s in scenes])
    print()
    print(table)
    if args.md:
        args.md.write_text(table + "\n")
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1))
    return 0
