"""``olsplat bench tune``: the same tuning budget for every method, on training scenes only.

Each method gets ``len(GRIDS[method])`` settings of its own parameters (its published or current
default first); every setting aggregates and scores every given scene as ``olsplat eval`` does;
the chosen setting has the best mean mIoU over the scenes, where a lead of less than
``TIE_MIOU`` (the resolution of our tables) is a tie and a tie goes to the earlier setting (the
default first): a default is not replaced on noise. Scenes must be simulator scenes of training seeds (>= 1000, their
``scene.json``): choices made on the held-out seeds of the results would flatter whoever is
tuned most. The chosen values are the defaults of ``method/table.py``; docs/evaluation.md ("Comparisons")
shows the sweep. ``--encoders``/``--weights`` tune with the encoder configuration of the table
the choice is for (``olsplat bench paper`` passes its own); the ``--json`` file records them and
is what ``olsplat eval --tuned`` reads. ``--grid-limit N`` (hidden) runs only the first N
settings of each grid: for tests, never for a table.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path
from typing import Any

from ..tools.method_names import DEFAULT_ENCODER

TRAINING_SEEDS = 1000  # scenes of seeds below this are held out for results
TIE_MIOU = 0.1  # mean mIoU points: closer than this is a tie

# Four settings per method. Symbols in method/params.py; each grid varies what its paper leaves
# open or what decides the most for that method.
GRIDS: dict[str, list[dict[str, Any]]] = {
    "outlangsplat": [{}, {"tau_d": 0.02}, {"tau_d": 0.1}, {"beta": [1.0, 2.0, 4.0]}],
    "outlangsplat-paper": [{}, {"tau_d": 0.02}, {"tau_d": 0.1}, {"beta": [1.0, 2.0, 4.0]}],
    # LUDVIG prunes Gaussians with little total weight; here: observations with d_iv <= tau_d
    "projection": [{}, {"tau_d": 0.01}, {"tau_d": 0.05}, {"tau_d": 0.2}],
    "drsplat": [
        {},
        {"topk_min": 16, "topk_max": 16},
        {"topk_min": 32, "topk_max": 32},
        {"topk_min": 64, "topk_max": 64},
    ],
    "topk": [{}, {"topk_coverage": 0.8}, {"topk_coverage": 0.95}, {"topk_min": 8}],
    "vala": [
        {},  # VALA's LERF values: tau_mass 0.75, tau_abs 0.13, stage-B cut 0.15
        {"gate_mass": 0.9, "gate_floor": 0.0, "gate_cut": 0.05},
        {"gate_mass": 0.75, "gate_floor": 0.0, "gate_cut": 0.0},
        {"gate_mass": 0.5, "gate_floor": 0.0, "gate_cut": 0.0},
    ],
}


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("tune", help="the same tuning budget for every method, on training scenes")
    parser.add_argument("--scene", required=True, type=Path, action="append", help="a training scene; repeatable")
    parser.add_argument("--methods", default=",".join(GRIDS), help="comma-separated, from: " + ", ".join(GRIDS))
    parser.add_argument(
        "--encoders",
        default=DEFAULT_ENCODER,
        help=f"the encoder configuration of the table the choice is for, as `olsplat eval --encoders` takes it "
        f"(default {DEFAULT_ENCODER})",
    )
    parser.add_argument("--weights", help="lambda_2D fusion weights of --encoders, e.g. 0.6,0.4")
    parser.add_argument("--json", type=Path, help="write every setting's scores and the choices here")
    parser.add_argument("--md", type=Path, help="write the sweep as a Markdown table here")
    parser.add_argument(
        "--ledger", type=Path, metavar="DIR", help="reuse and add finished runs here, as `olsplat eval --ledger`"
    )
    # tests only: the first N settings of each grid (a smaller budget than the protocol's)
    parser.add_argument("--grid-limit", type=int, help=argparse.SUPPRESS)
    parser.set_defaults(run=run)


def tune_table(methods: dict[str, Any]) -> str:
    """Markdown: one row per method and setting (mean mIoU and Loc@50 over the training
    scenes, then per scene), the chosen setting in bold."""
    scenes = list(next(iter(methods.values()))["rows"][0]["per_scene"])
    lines = [
        "| method | setting | mIoU | Loc@50 | " + " | ".join(f"{s} mIoU / Loc@50" for s in scenes) + " |",
        "| --- | --- | --- | --- |" + " --- |" * len(scenes),
    ]
    for name, result in methods.items():
        for row in result["rows"]:
            setting = ", ".join(f"{k}={v}" for k, v in row["setting"].items()) or "default"
            mark = "**" if row["setting"] == result["chosen"] else ""
            per_scene = " | ".join(
                f"{row['per_scene'][s]['mIoU']:.1f} / {row['per_scene'][s]['loc50']:.1f}" for s in scenes
            )
            lines.append(
                f"| {name} | {mark}{setting}{mark} | {mark}{row['mIoU']:.2f}{mark} | {row['loc50']:.2f} | {per_scene} |"
            )
    return "\n".join(lines)


def choose(rows: list[dict[str, Any]]) -> int:
    """Index of the chosen row (rows with mean "mIoU", in grid order): the earliest row that no
    later row beats by TIE_MIOU or more."""
    best = 0
    for i, row in enumerate(rows):
        if row["mIoU"] >= rows[best]["mIoU"] + TIE_MIOU:
            best = i
    return best


def _seed_of(folder: Path) -> int | None:
    try:
        return int(json.loads((folder / "scene.json").read_text())["seed"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def check_training_scenes(folders: list[Path]) -> None:
    """Refuse (one line) any folder that is not a simulator scene of a training seed."""
    from ..errors import OlsplatInputError

    for folder in folders:
        seed = _seed_of(folder)
        if seed is None or seed < TRAINING_SEEDS:
            raise OlsplatInputError(
                f"{folder}: tune on training scenes only (simulator seed >= {TRAINING_SEEDS} in scene.json), "
                f"found seed {seed}"
            )


def tune_methods(
    folders: list[Path],
    names: list[str],
    encoders: str = DEFAULT_ENCODER,
    weights: str | None = None,
    grid_limit: int | None = None,
    ledger: Path | None = None,
) -> dict[str, Any]:
    """Run each method's grid (its first ``grid_limit`` settings, or all) on the training scenes
    ``folders`` with the encoder configuration ``encoders`` / ``weights`` (as ``olsplat eval``
    takes them); returns the ``--json`` document: ``{"scenes", "encoders", "weights", "methods":
    {name: {"rows", "chosen"}}}``. Every scene, name and setting is checked before any work. A run
    in the ``ledger`` folder (``evaluate.ledger``) is not run again; each finished run is added."""
    import numpy as np

    from ..encoders.spec import encoder_fingerprint, encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate.ledger import RunLedger, run_key, scene_digest
    from ..evaluate.one_run import aggregate_and_score
    from ..method import MethodParams
    from ..params import parse_params
    from ..pipeline import Scene

    unknown = [n for n in names if n not in GRIDS]
    if unknown:
        raise OlsplatInputError(f"--methods: no tuning grid for {', '.join(unknown)}; known: {', '.join(GRIDS)}")
    if grid_limit is not None and grid_limit < 1:
        raise OlsplatInputError(f"--grid-limit must be >= 1, got {grid_limit}")
    check_training_scenes(folders)
    scenes = [Scene.open(folder) for folder in folders]
    grids = {name: GRIDS[name][:grid_limit] for name in names}
    settings = {  # every setting is checked before any work
        name: [parse_params(MethodParams, {**s, "method": name}, f"{name} {s}").resolve() for s in grids[name]]
        for name in names
    }
    encoder = encoder_from_spec(encoders, weights)
    runs = RunLedger(ledger)
    contents = [scene_digest(scene.folder) for scene in scenes] if ledger is not None else [""] * len(scenes)
    fingerprint = encoder_fingerprint(encoders) if ledger is not None else ""
    lambdas = [float(w) for w in weights.split(",")] if weights else None

    results: dict[str, Any] = {}
    for name in names:
        rows: list[dict[str, Any]] = []
        for grid, method in zip(grids[name], settings[name], strict=True):
            scores = []
            start = time.perf_counter()
            for scene, content in zip(scenes, contents, strict=True):
                made_of = run_key(content, method, encoders, lambdas, fingerprint, None)
                compute = functools.partial(aggregate_and_score, scene, method, encoder)
                scores.append(runs.run(made_of, compute, f"{scene.folder.name} {name} {json.dumps(grid)}")[0])
            row = {
                "setting": grid,
                "mIoU": float(np.mean([s["mIoU"] for s in scores])),
                "loc50": float(np.mean([s["loc50"] for s in scores])),
                "per_scene": {
                    s.folder.name: {"mIoU": r["mIoU"], "loc50": r["loc50"]} for s, r in zip(scenes, scores, strict=True)
                },
                "seconds": time.perf_counter() - start,
            }
            rows.append(row)
            figures = f"mIoU {row['mIoU']:5.2f}  Loc@50 {row['loc50']:5.2f}  ({row['seconds']:.0f} s)"
            print(f"{name:20s} {json.dumps(grid):55s} {figures}", flush=True)
        best = choose(rows)
        results[name] = {"rows": rows, "chosen": rows[best]["setting"]}
        print(f"{name:20s} chosen: {json.dumps(rows[best]['setting'])}", flush=True)
    return {"scenes": [str(s.folder) for s in scenes], "encoders": encoders, "weights": weights, "methods": results}


def run(args: argparse.Namespace) -> int:
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    document = tune_methods(args.scene, names, args.encoders, args.weights, args.grid_limit, args.ledger)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document, indent=1))
        print(f"figures -> {args.json}")
    if args.md:
        args.md.write_text(tune_table(document["methods"]) + "\n")
    return 0
