"""``olsplat bench robustness``: a stress test of the aggregation methods under injected
feature errors. It is not evidence that a method copes with a real encoder's errors: the
errors are made here, by a model of how encoders err.

Two kinds of error (``--mode``):

- ``lookalike`` (default): a region is read as what the scene's encoder itself mistakes its
  true label for (the off-diagonal of the encoder's confusion matrix on the scene's
  annotations) and takes the feature of a region of that label in the same view. The decision
  is drawn per surface (an annotated instance, or a stuff label in an 8 m ground cell) and each
  view that sees the surface follows it with probability ``--correlation`` rho, else draws its
  own: errors repeat across overlapping frames, as a real encoder's do. ``evaluate/confusion.py``
  has the model and its conventions.
- ``swap``: in every view, each region's feature is, with probability ``p``, replaced by the
  feature of a random region of the same view, independently per view and region (the study's
  first form, kept bit-identical for comparison). That is exactly the consistency step's own
  assumption, so a method that checks views against each other wins it by construction.

In both, ``p`` is the probability that an observation is confused (a region in ``swap``, a
surface in a view in ``lookalike``). Every draw is seeded by ``--seed`` and the view (and the
surface), so every method aggregates exactly the same corrupted features. Each method is then
scored on the scene's annotations as ``olsplat eval`` does. With ``--features 2d,2d3d`` each
method also runs with the 3D branch (``olsplat eval --features 2d3d``): the confusion hits the
2D bank before the fusion, so h_theta is taught by the confused 2D features.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the CLI imports every bench module at start: the numeric code loads when run
    from ..evaluate.confusion import LevelTruth, Lookalikes

# A stated choice, not a measurement: two views' confusion indicators then correlate rho^2 = 0.49,
# so errors mostly repeat across overlapping frames, yet a surface is still right in some views
# and wrong in others, where weighting and consistency have work to do.
DEFAULT_CORRELATION = 0.7


def confuse(bank: list[np.ndarray], p: float, rng: np.random.Generator) -> list[np.ndarray]:
    """``--mode swap``. Per level [R, D]: each row replaced with probability p by a random row
    of the same level."""
    out = []
    for features in bank:
        swapped = rng.random(len(features)) < p
        confused = features.copy()
        confused[swapped] = features[rng.integers(0, len(features), int(swapped.sum()))]
        out.append(confused)
    return out


def scene_lookalikes(scene, encoder) -> tuple[dict[str, list[LevelTruth]], Lookalikes]:
    """What ``--mode lookalike`` needs of a scene: each annotated view's ``LevelTruth`` per
    level (by camera name; views without an annotation are left out, and stay clean) and the
    encoder's look-alikes measured on them, from the same region banks the methods aggregate."""
    from ..errors import OlsplatInputError
    from ..evaluate.annotations import read_annotation
    from ..evaluate.confusion import measure_lookalikes, measure_view
    from ..evaluate.scene_eval import label_texts, load_queries
    from ..pipeline import view_features

    labels, queries = load_queries(scene.folder)
    truths: dict[str, list[LevelTruth]] = {}

    def annotated():
        for camera in scene.cameras:
            path = scene.folder / "annotations" / f"{Path(camera.name).stem}.json"
            if path.exists():
                label_maps, bank = view_features(scene, camera, encoder)
                truth_labels, instances = read_annotation(path, labels)
                levels = measure_view(label_maps, [len(f) for f in bank], truth_labels, instances, camera, len(labels))
                truths[camera.name] = levels
                yield bank, levels

    try:
        looks = measure_lookalikes(annotated(), np.asarray(encoder.encode_text(label_texts(labels, queries))))
    except ValueError as exc:
        raise OlsplatInputError(f"{scene.folder}: --mode lookalike: {exc}") from None
    return truths, looks


def describe_lookalikes(looks: Lookalikes, labels: list[str]) -> str:
    """One line: each label's most likely look-alike and its probability, and the measured
    region accuracy (the confusion matrix's trace share)."""
    accuracy = np.trace(looks.counts) / max(int(looks.counts.sum()), 1)
    pairs = [f"{labels[t]} -> {labels[int(np.argmax(row))]} {row.max():.2f}" for t, row in enumerate(looks.rows)]
    return f"encoder region accuracy {100 * accuracy:.1f} % on {int(looks.counts.sum())} regions; look-alikes: " + (
        ", ".join(pairs)
    )


def corrupted_features(
    scene,
    encoder,
    mode: str,
    p: float,
    seed: int,
    rho: float = DEFAULT_CORRELATION,
    lookalikes: tuple[dict[str, list[LevelTruth]], Lookalikes] | None = None,
) -> Callable:
    """``features_of(camera)`` for ``aggregate_scene``: the view's (label maps, bank) with the
    ``mode``'s errors at probability ``p``; ``lookalikes`` from ``scene_lookalikes`` (made when
    absent) for ``lookalike``. The view is keyed by its index in ``scene.cameras``."""
    from ..evaluate.confusion import confuse_lookalike
    from ..pipeline import view_features

    index = {c.name: i for i, c in enumerate(scene.cameras)}
    if mode == "swap":

        def swapped(camera):
            label_maps, bank = view_features(scene, camera, encoder)
            return label_maps, confuse(bank, p, np.random.default_rng([seed, index[camera.name]]))

        return swapped
    if mode != "lookalike":
        raise ValueError(f"mode: 'lookalike' or 'swap', got {mode!r}")
    truths, looks = lookalikes or scene_lookalikes(scene, encoder)

    def lookalike(camera):
        label_maps, bank = view_features(scene, camera, encoder)
        if camera.name not in truths:
            return label_maps, bank
        return label_maps, confuse_lookalike(bank, truths[camera.name], index[camera.name], looks, p, rho, seed)

    return lookalike


def robustness_table(scores: dict[str, dict[str, dict[str, dict]]], scenes: list[str], what: str = "") -> str:
    """Markdown: one row per method, one column per confusion p, "mIoU / Loc@50" averaged over
    the scenes; the best of each column in bold. ``what`` names the confusion in the title
    (default: the ``swap`` mode's)."""
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
        f"**mIoU / Loc@50 (%) under {what or 'view-specific confusion p'}** (mean over {len(scenes)} scene(s): "
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
    parser = subparsers.add_parser(
        "robustness",
        help="stress test: methods under injected feature errors (look-alikes correlated across views, or swaps)",
        description="A stress test, not evidence about real encoders: every method aggregates the same\n"
        "features with injected errors and is scored on the scene's annotations.\n\n"
        "--mode lookalike (default): a surface (an annotated instance, or a stuff label in an 8 m\n"
        "ground cell) is read, with probability p, as a label the scene's encoder itself confuses it\n"
        "with (its confusion matrix on the annotations), and takes the feature of a region of that\n"
        "label in the same view; each view follows the surface's draw with probability\n"
        "--correlation, else draws its own, so errors repeat across overlapping frames.\n"
        "--mode swap: each region, independently per view, takes a random region's feature: the\n"
        "consistency step's own assumption, kept bit-identical for comparison.",
    )
    parser.add_argument("--scene", required=True, type=Path, action="append", help="a scene folder; repeatable")
    parser.add_argument(
        "--methods",
        default="outlangsplat,outlangsplat-paper,projection,drsplat,topk,vala",
        help="comma-separated methods",
    )
    parser.add_argument(
        "--mode",
        choices=("lookalike", "swap"),
        default="lookalike",
        help="lookalike: errors from the encoder's confusion matrix, correlated across views (default); "
        "swap: a random region's feature, independently per view",
    )
    parser.add_argument(
        "--confusion",
        default="0,0.15,0.3,0.45",
        help="comma-separated probabilities p that an observation is confused (a surface in a view for "
        "lookalike, a region for swap)",
    )
    parser.add_argument(
        "--correlation",
        type=float,
        default=DEFAULT_CORRELATION,
        metavar="RHO",
        help=f"lookalike: probability that a view follows its surface's shared draw (1: the same confusion in "
        f"every view; 0: independent views); default {DEFAULT_CORRELATION}",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the perturbations")
    parser.add_argument(
        "--features", default="2d", help="comma-separated, from: 2d, 2d3d (fused with the 3D branch, lambda_f 0.7)"
    )
    parser.add_argument("--json", type=Path, help="write every run's scores here")
    parser.add_argument("--md", type=Path, help="write the table (mean over the scenes) here, in Markdown")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate import evaluate_map
    from ..evaluate.scene_eval import load_queries
    from ..method import named_method
    from ..pipeline import Scene, aggregate_scene
    from ..storage.snapshot import LanguageMap
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
    if not 0.0 <= args.correlation <= 1.0:
        raise OlsplatInputError(f"--correlation: a probability in [0, 1], got {args.correlation!r}")
    if args.seed < 0:
        raise OlsplatInputError(f"--seed: >= 0, got {args.seed}")
    if args.mode == "swap":
        what = "view-specific confusion p"
        print("p = share of each view's regions given another region's feature")
    else:
        what = f"look-alike confusion p, correlation {args.correlation:g} across views (a stress test)"
        print(
            f"p = share of surfaces read as a look-alike in a view; each view follows the surface's shared "
            f"draw with probability {args.correlation:g}"
        )
    scores: dict[str, dict[str, dict[str, dict]]] = {}  # label -> p -> scene -> scores
    for scene in scenes:
        lookalikes = None
        if args.mode == "lookalike":
            lookalikes = scene_lookalikes(scene, encoder)
            print(f"  {scene.folder.name}: {describe_lookalikes(lookalikes[1], load_queries(scene.folder)[0])}")
        for p in levels:
            features_of = corrupted_features(scene, encoder, args.mode, p, args.seed, args.correlation, lookalikes)
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
    table = robustness_table(scores, [s.folder.name for s in scenes], what)
    print()
    print(table)
    if args.md:
        args.md.write_text(table + "\n")
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1))
    return 0
