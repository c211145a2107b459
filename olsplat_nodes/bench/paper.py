"""``olsplat bench paper``: the evaluation protocol's one command (docs/evaluation-protocol.md).

Per world (``--world v1 --world v2``): make the scenes of the held-out and training seeds under
``WORK/<world>/<preset><seed>`` (a scene already there is reused when its scene.json is what
``olsplat sim make --preset P --seed S --world W`` makes), tune Table 5's methods on the training
seeds with the table's encoders (``bench tune``, written to ``WORK/<world>/tune.json``), then run
``olsplat eval --tuned`` on the held-out seeds with the feature ablation and the fusion sweep
(``WORK/<world>/eval.json``). The Markdown document has, per world, Tables 5, 6 and 7 with the
mean and the paired 95 % interval over the held-out seeds beside the paper's figures, and the
claims table: each claim's paired difference, its interval and the verdict by the protocol's
rule (holds: the interval above zero; fails: below; tie: otherwise).

An interrupted run continues where it stopped when the same command is given again: scenes whose
scene.json is what sim make writes are reused, a world's tuning is reused when ``tune.json`` was
made with the same training scenes, methods, grids and encoder files (``tuning_key``), and each
held-out scene's results when its ``results.json`` under ``WORK/<world>/eval`` matches its runs
and settings (``olsplat eval --resume``). A changed encoder or setting is run again, not reused.
Below those, every finished aggregation goes to the run ledger (``--ledger``, default
``WORK/ledger``; ``evaluate.ledger``): a tuning or a scene cut short keeps its finished runs, and a
ledger copied to another machine (the repository keeps the protocol's) spares its runs there.

Training seeds are >= 1000 and held-out seeds below (``bench tune``'s ``TRAINING_SEEDS``): a
choice of settings never sees a seed whose results are reported. ``--grid-limit N`` (hidden)
gives each method only the first N settings of its grid, ``--views N`` (hidden) makes scenes of N
views instead of the preset's: for tests, never for a table.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

TABLE5_METHODS = ("outlangsplat", "outlangsplat-paper", "projection", "drsplat", "vala")
INDEPENDENT_PAIR = "olsplat-nadir32,olsplat-oblique48"  # the pair the protocol's command is built with
PEAK = "lambda_2D=0.6 lambda_f=0.7"  # the paper's best cell of Table 7 (the label plan_runs gives it)

# The paper's figures, from ../shared/paper/outlangsplat.tex (the table's \label, then its row).
# Table 5, \label{tab:aggregation_ablation}: rows "mIoU" and "mAcc"; columns Projection Agg.,
# VALA Agg., Our Agg.
PAPER_TABLE5 = {
    "projection": {"mIoU": 65.44, "mAcc": 84.00},
    "vala": {"mIoU": 62.87, "mAcc": 82.04},
    "outlangsplat": {"mIoU": 68.31, "mAcc": 86.61},
}
# Table 6, \label{tab:feature_ablation}: rows "mIoU" and "mAcc"; columns RemoteCLIP (the first
# encoder: lambda_2D weighs phi_R, eq:2d_feature_fusion), RS5M, w/o 3D fusion, 2D-3D fusion
PAPER_TABLE6 = {
    "first encoder alone": {"mIoU": 49.91, "mAcc": 66.89},
    "second encoder alone": {"mIoU": 58.99, "mAcc": 78.69},
    "2D fusion": {"mIoU": 63.90, "mAcc": 77.41},
    "2D-3D fusion": {"mIoU": 68.31, "mAcc": 86.61},
}
# Table 7, \label{tab:fusion_param}: one row per lambda_2D, lambda_f 0.6/0.7/0.8 in each cell;
# (lambda_2D, lambda_f) -> mIoU, mAcc, mLoc@50
PAPER_TABLE7 = {
    (0.5, 0.6): (64.9, 84.9, 82.8),
    (0.5, 0.7): (67.5, 85.2, 88.2),
    (0.5, 0.8): (63.7, 85.2, 86.2),
    (0.6, 0.6): (66.2, 86.8, 89.7),
    (0.6, 0.7): (68.3, 86.6, 91.6),
    (0.6, 0.8): (62.4, 81.6, 86.2),
    (0.7, 0.6): (64.6, 80.5, 86.7),
    (0.7, 0.7): (64.1, 82.4, 87.2),
    (0.7, 0.8): (62.3, 86.5, 89.2),
}
# Seconds per run (aggregation + scoring, the control pair fused) by the kind of run: 2D features,
# 2D-3D with the descriptors, with the MinkUNet. small: docs/evaluation.md ("The 3D branch": 67-111 s,
# 222-281 s, 93-105 s per run beside other jobs).
SECONDS_PER_RUN = {"small": {"2d": 100, "descriptors": 250, "minkunet": 100}}
VERDICTS = {"win": "holds", "loss": "fails", "tie": "tie", "n/a": "n/a (one seed)"}


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "paper",
        help="the paper's Tables 5-7 per world on held-out seeds, tuned on training seeds, with paired intervals "
        "and the paper's figures (docs/evaluation-protocol.md)",
    )
    parser.add_argument(
        "--world",
        action="append",
        choices=("v1", "v2", "v2g"),
        help="a world; repeatable (default: v1, v2 and v2g, v2 with geometry that follows its labels)",
    )
    parser.add_argument("--seeds", default="0,1,2,3,4", help="held-out seeds, each < 1000 (default 0,1,2,3,4)")
    parser.add_argument("--train-seeds", default="1001,1002", help="training seeds, each >= 1000 (default 1001,1002)")
    parser.add_argument("--preset", default="small", help="the scenes' preset: tiny, small, medium, large")
    parser.add_argument(
        "--methods", default=",".join(TABLE5_METHODS), help="Table 5's methods, tuned and compared (comma-separated)"
    )
    parser.add_argument(
        "--encoders",
        default=INDEPENDENT_PAIR,
        help=f"the tables' encoders, as `olsplat eval` takes them (default: the independent pair, {INDEPENDENT_PAIR})",
    )
    parser.add_argument("--weights", default="0.6,0.4", help="lambda_2D fusion weights of --encoders (0.6,0.4)")
    parser.add_argument("--work", type=Path, required=True, help="folder for the scenes, tunings, maps and results")
    parser.add_argument(
        "--ledger",
        type=Path,
        metavar="DIR",
        help="the ledger of finished runs (default WORK/ledger): a run found there is not run again, each finished "
        "run is added, so the tables can be made in pieces and on other machines (the repository keeps the "
        "protocol's in results/paper-ledger)",
    )
    parser.add_argument("--json", type=Path, help="write the tables' figures and the claims here")
    parser.add_argument("--md", type=Path, help="write the Markdown document here")
    parser.add_argument("--dry-run", action="store_true", help="print the plan (scenes, runs) and stop")
    # tests only: the first N settings of each method's grid (a smaller budget than the protocol's), and
    # scenes of N views instead of the preset's (as `sim make --views N`)
    parser.add_argument("--grid-limit", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--views", type=int, help=argparse.SUPPRESS)
    parser.set_defaults(run=run)


def parse_seeds(text: str, option: str, training: bool) -> list[int]:
    """'0,1,2' -> [0, 1, 2]; held-out seeds must be < 1000, training seeds >= 1000 (one line each)."""
    from ..errors import OlsplatInputError
    from .tune import TRAINING_SEEDS

    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise OlsplatInputError(f"{option} must be comma-separated integers, got {text!r}") from None
    if not seeds or len(set(seeds)) < len(seeds) or min(seeds) < 0:
        raise OlsplatInputError(f"{option} needs distinct seeds >= 0, got {text!r}")
    bad = [s for s in seeds if (s < TRAINING_SEEDS) == training]
    if bad:
        kind = f"training seeds are >= {TRAINING_SEEDS}" if training else f"held-out seeds are < {TRAINING_SEEDS}"
        raise OlsplatInputError(f"{option}: {kind} (docs/evaluation-protocol.md, 'Seeds'), got {bad[0]}")
    return seeds


# --- the claims --------------------------------------------------------------------------------


def claim_verdict(ours: Sequence[float], theirs: Sequence[float]) -> dict[str, Any]:
    """The protocol's rule on per-seed figures (same seeds, same order): the mean of ours - theirs,
    its paired 95 % t interval (n - 1 degrees of freedom), and the verdict: "holds" when the
    interval lies above zero, "fails" below, "tie" otherwise ("n/a (one seed)": no interval)."""
    from ..evaluate.statistics import paired, verdict

    mean, interval = paired(ours, theirs)
    return {"difference": mean, "ci95": list(interval) if interval else None, "verdict": VERDICTS[verdict(interval)]}


def _single_encoders(first: dict[str, dict]) -> list[str]:
    from ..evaluate.runs import FUSED_DESCRIPTORS, FUSED_MINKUNET, WITHOUT_3D

    fused = (WITHOUT_3D, FUSED_DESCRIPTORS, FUSED_MINKUNET)
    return [k for k, v in first.items() if v.get("run", {}).get("kind") == "feature" and k not in fused]


def claims(results: dict[str, dict[str, dict]]) -> list[dict[str, Any]]:
    """The protocol's claims on ``results`` (seed's scene -> run label -> scores, as ``olsplat
    eval`` keeps them): per claim, what is compared, the per-seed mIoU of each side, the paired
    difference with its interval and verdict (``claim_verdict``), and the paper's figures.
    A claim whose runs are missing says "not run"."""
    from ..evaluate.runs import FUSED_DESCRIPTORS, FUSED_MINKUNET, WITHOUT_3D

    first = next(iter(results.values()))

    def per_seed(label: str) -> list[float]:
        return [scene[label]["mIoU"] for scene in results.values()]

    def mean(label: str) -> float:
        return sum(per_seed(label)) / len(results)

    singles = _single_encoders(first)
    better = max(singles, key=mean) if singles else None
    others = [k for k, v in first.items() if v.get("run", {}).get("kind") == "sweep" and k != PEAK]
    best_other = max(others, key=mean) if others else None
    p5, p6 = PAPER_TABLE5, PAPER_TABLE6
    rows = [
        ("its aggregation beats projection", 5, "outlangsplat", "projection",
         p5["outlangsplat"]["mIoU"], p5["projection"]["mIoU"], "Projection Agg."),
        ("its aggregation beats VALA", 5, "outlangsplat", "vala",
         p5["outlangsplat"]["mIoU"], p5["vala"]["mIoU"], "VALA Agg."),
        ("two fused encoders beat the better one alone", 6, WITHOUT_3D, better,
         p6["2D fusion"]["mIoU"], p6["second encoder alone"]["mIoU"], "RS5M"),
        ("2D-3D fusion (descriptors) beats 2D fusion", 6, FUSED_DESCRIPTORS, WITHOUT_3D,
         p6["2D-3D fusion"]["mIoU"], p6["2D fusion"]["mIoU"], "w/o 3D fusion"),
        ("2D-3D fusion (MinkUNet) beats 2D fusion", 6, FUSED_MINKUNET, WITHOUT_3D,
         p6["2D-3D fusion"]["mIoU"], p6["2D fusion"]["mIoU"], "w/o 3D fusion"),
        ("λ2D 0.6, λf 0.7 beats the grid's best other cell", 7, PEAK, best_other,
         PAPER_TABLE7[0.6, 0.7][0], PAPER_TABLE7[0.5, 0.7][0], "λ2D 0.5, λf 0.7"),
    ]  # fmt: skip
    out = []
    for claim, table, ours, theirs, paper_ours, paper_theirs, paper_other in rows:
        row: dict[str, Any] = {
            "claim": claim,
            "table": table,
            "ours": ours,
            "theirs": theirs,
            "paper": {"ours": paper_ours, "theirs": paper_theirs, "difference": round(paper_ours - paper_theirs, 2),
                      "theirs_is": paper_other},
        }  # fmt: skip
        if theirs is None or ours not in first or theirs not in first:
            out.append({**row, "verdict": "not run"})
            continue
        a, b = per_seed(ours), per_seed(theirs)
        out.append({**row, "ours_mIoU": a, "theirs_mIoU": b, **claim_verdict(a, b)})
    return out


def claims_table(rows: list[dict[str, Any]], seeds: int) -> list[str]:
    def interval(row) -> str:
        return f"[{row['ci95'][0]:+.1f}, {row['ci95'][1]:+.1f}]" if row.get("ci95") else "—"

    lines = [
        f"**Claims** (ΔmIoU = first minus second run, per held-out seed; mean and paired 95 % t interval over "
        f"{seeds} seeds; holds: the interval above zero, fails: below, tie: otherwise)",
        "",
        "| claim | table | runs | ΔmIoU | 95 % interval | verdict | paper |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        paper = row["paper"]
        figures = f"{paper['ours']:.2f} vs {paper['theirs']:.2f} ({paper['theirs_is']}): {paper['difference']:+.2f}"
        if row["verdict"] == "not run":
            lines.append(f"| {row['claim']} | {row['table']} | {row['ours']} − {row['theirs']} | — | — | not run | "
                         f"{figures} |")  # fmt: skip
            continue
        lines.append(
            f"| {row['claim']} | {row['table']} | {row['ours']} − {row['theirs']} | {row['difference']:+.2f} | "
            f"{interval(row)} | **{row['verdict']}** | {figures} |"
        )
    return lines


# --- the tables --------------------------------------------------------------------------------


def _with_column(lines: list[str], header: str, values: dict[str, str]) -> list[str]:
    """A Markdown table of ``tables.py`` (title, blank, header, rule, rows) with one more column:
    ``values`` by the row's first cell ("—" where it has none)."""
    out = list(lines[:2])
    out.append(lines[2] + f" {header} |")
    out.append(lines[3] + " --- |")
    for line in lines[4:]:
        name = line.split("|")[1].strip()
        out.append(line + f" {values.get(name, '—')} |")
    return out


def world_tables(results: dict[str, dict[str, dict]], world: str, chosen: dict[str, Any]) -> tuple[str, dict]:
    """Markdown of one world (tuning choices, Tables 5, 6, 7, claims) and its figures for --json."""
    from ..evaluate.runs import FUSED_DESCRIPTORS, FUSED_MINKUNET, WITHOUT_3D
    from ..evaluate.tables import spread, spread_table, strategy_table, sweep_table

    first = next(iter(results.values()))
    labels = [k for k in first if all(k in scene for scene in results.values())]

    def kind(label: str) -> str:
        return first[label].get("run", {}).get("kind", "method")

    methods = [k for k in labels if kind(k) == "method"]
    features = [k for k in labels if kind(k) == "feature"]
    sweep = [k for k in labels if kind(k) == "sweep"]
    n = len(results)
    sections = [[f"## World {world} ({n} held-out seeds: {', '.join(results)})"]]
    tuned = ", ".join(f"{m} {json.dumps(s) if s else 'default'}" for m, s in chosen.items())
    sections.append([f"Settings chosen on the training seeds (bench tune): {tuned}."])
    figures: dict[str, Any] = {}
    reference = "outlangsplat"
    if methods:
        paper = {m: f"{v['mIoU']:.2f}" for m, v in PAPER_TABLE5.items()}
        ref = reference if reference in methods else methods[0]
        lines = spread_table(results, methods, ref, "Aggregation methods, paper Table 5. ")
        sections.append(_with_column(lines, "paper mIoU", paper))
        means = strategy_table(
            results, methods, "**Aggregation methods** (mean over the seeds: mAcc, time; paper Table 5)"
        )
        paper_macc = [f"{PAPER_TABLE5[m]['mAcc']:.2f}" if m in PAPER_TABLE5 else "—" for m in methods]
        sections.append([*means[:6], "| paper mAcc | " + " | ".join(paper_macc) + " |", *means[6:]])  # after mAcc
        figures["table5"] = spread(results, ref, methods)
    if features:
        singles = _single_encoders(first)
        paper_names = (("first encoder alone", "RemoteCLIP"), ("second encoder alone", "RS5M"))
        paper = {
            s: f"{PAPER_TABLE6[p]['mIoU']:.2f} ({name})" for s, (p, name) in zip(singles, paper_names, strict=False)
        }
        paper[WITHOUT_3D] = f"{PAPER_TABLE6['2D fusion']['mIoU']:.2f}"
        for label in (FUSED_DESCRIPTORS, FUSED_MINKUNET):
            paper[label] = f"{PAPER_TABLE6['2D-3D fusion']['mIoU']:.2f}"
        ref = WITHOUT_3D if WITHOUT_3D in features else features[0]
        lines = spread_table(results, features, ref, "Feature configurations, paper Table 6. ")
        sections.append(_with_column(lines, "paper mIoU", paper))
        figures["table6"] = spread(results, ref, features)
    if sweep:
        means = sweep_table(results, sweep, "**Fusion weights λ2D x λf** (mean over the seeds; paper Table 7)")
        rows: dict[float, list[float]] = {}
        for (l2d, _), values in sorted(PAPER_TABLE7.items()):
            rows.setdefault(l2d, []).append(values[0])
        paper = {f"{l2d:g}": "/".join(f"{v:.1f}" for v in values) for l2d, values in rows.items()}
        sections.append(_with_column(means, "paper mIoU", paper))
        ref = PEAK if PEAK in sweep else sweep[0]
        sections.append(spread_table(results, sweep, ref, "Fusion weights, paper Table 7. "))
        figures["table7"] = spread(results, ref, sweep)
    figures["claims"] = claims(results)
    sections.append(claims_table(figures["claims"], n))
    return "\n\n".join("\n".join(s) for s in sections), figures


# --- the run -----------------------------------------------------------------------------------


def _preset(name: str, views: int | None):
    from dataclasses import replace

    from olsplat_sim.presets import PRESETS

    return replace(PRESETS[name], n_views=views) if views else PRESETS[name]


def _expected_scene(preset: str, seed: int, world: str, views: int | None = None) -> dict[str, Any]:
    """The scene.json fields ``olsplat sim make --preset P --seed S --world W [--views N]`` writes
    that name what was made (JSON-normalised, as read back from the file)."""
    from dataclasses import asdict

    from olsplat_sim.make import MakeOptions
    from olsplat_sim.world import WORLDS

    fields = {"preset": asdict(_preset(preset, views)), "seed": seed, "flight_seed": None,
              "options": asdict(MakeOptions(WORLDS[world]))}  # fmt: skip
    return json.loads(json.dumps(fields))


def scene_state(folder: Path, preset: str, seed: int, world: str, views: int | None = None) -> str:
    """Whether to "reuse" the scene (its scene.json is the one sim make writes for these),
    "make" it (absent, empty, or a make that did not finish: no scene.json) or refuse it,
    "other" (another scene)."""
    try:
        found = json.loads((folder / "scene.json").read_text())
    except FileNotFoundError:
        return "make"
    except (OSError, json.JSONDecodeError):
        return "other"
    expected = _expected_scene(preset, seed, world, views)
    return "reuse" if all(found.get(k) == v for k, v in expected.items()) else "other"


def _plan_counts(args, methods: list[str], seeds: list[int], train: list[int]) -> dict[str, int]:
    """Per world, every aggregation + scoring the command makes: "tuning" runs (2D features),
    held-out runs on 2D features ("2d"), with the descriptors ("descriptors") and with the
    MinkUNet ("minkunet")."""
    from ..evaluate.runs import plan_runs
    from .tune import GRIDS

    weights = tuple(float(w) for w in args.weights.split(",")) if args.weights else None
    runs = plan_runs(methods, args.encoders, weights, feature_ablation=True, fusion_sweep=True)
    distinct = {(r.method, r.encoders, r.weights, r.structure) for r in runs}  # eval runs each once
    kinds = ["2d" if s is None else "descriptors" if s.minkunet is None else "minkunet" for *_, s in distinct]
    counts = {"tuning": sum(len(GRIDS[m][: args.grid_limit]) for m in methods) * len(train)}
    return counts | {kind: kinds.count(kind) * len(seeds) for kind in ("2d", "descriptors", "minkunet")}


def _print_ledger_progress(ledger: Path, worlds, folders, states, train, seeds, counts) -> None:
    """Per world, how many of its tuning and held-out runs the ledger already holds (found by the
    scenes' content; a scene not made yet counts none)."""
    from ..evaluate.ledger import RunLedger, scene_digest

    held = RunLedger(ledger).scene_counts()
    per_seed = (counts["2d"] + counts["descriptors"] + counts["minkunet"]) // len(seeds)
    for world in worlds:
        found = {
            seed: held.get(scene_digest(folders[world, seed]), 0) if states[world, seed] == "reuse" else 0
            for seed in [*train, *seeds]
        }
        done = [found[s] for s in seeds]
        print(f"  ledger {ledger}: [{world}] {sum(found[s] for s in train)}/{counts['tuning']} tuning runs, "
              f"{sum(done)}/{per_seed * len(seeds)} held-out runs (per seed {', '.join(map(str, done))} of "
              f"{per_seed})")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    import time

    from olsplat_sim.presets import PRESETS

    from ..errors import OlsplatInputError
    from ..tools import evaluate
    from .tune import GRIDS, tune_methods, tune_table

    seeds = parse_seeds(args.seeds, "--seeds", training=False)
    if len(seeds) < 2:
        raise OlsplatInputError(f"--seeds: the paired intervals need two held-out seeds or more, got {seeds}")
    train = parse_seeds(args.train_seeds, "--train-seeds", training=True)
    worlds = list(dict.fromkeys(args.world or ["v1", "v2", "v2g"]))
    if args.preset not in PRESETS:
        raise OlsplatInputError(f"--preset must be one of {', '.join(PRESETS)}, got {args.preset!r}")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in GRIDS]
    if not methods or unknown:
        missing = ", ".join(unknown) or "no method"
        raise OlsplatInputError(f"--methods: no tuning grid for {missing}; known: {', '.join(GRIDS)}")
    if args.grid_limit is not None and args.grid_limit < 1:
        raise OlsplatInputError(f"--grid-limit must be >= 1, got {args.grid_limit}")
    if args.views is not None and args.views < 1:
        raise OlsplatInputError(f"--views must be >= 1, got {args.views}")

    folders = {
        (world, seed): args.work / world / f"{args.preset}{seed}" for world in worlds for seed in [*train, *seeds]
    }
    states = {key: scene_state(folder, args.preset, key[1], key[0], args.views) for key, folder in folders.items()}
    other = [key for key, state in states.items() if state == "other"]
    if other:
        (world, seed), *_ = other
        raise OlsplatInputError(
            f"{folders[world, seed]}: holds another scene than `olsplat sim make --preset {args.preset} --seed {seed} "
            f"--world {world}` makes; remove it or choose another --work"
        )
    counts = _plan_counts(args, methods, seeds, train)
    held_out = counts["2d"] + counts["descriptors"] + counts["minkunet"]
    to_make = sum(state == "make" for state in states.values())
    print(f"plan: worlds {', '.join(worlds)}; preset {args.preset}; held-out seeds {seeds}; training seeds {train}")
    print(f"  scenes: {to_make} to make, {len(states) - to_make} reused (under {args.work})")
    print(f"  per world: {counts['tuning']} tuning runs ({', '.join(methods)} x their grids x {len(train)} training "
          f"seeds), {held_out} held-out runs (Tables 5-7 x {len(seeds)} seeds: {counts['2d']} on 2D features, "
          f"{counts['descriptors']} with the 3D descriptors, {counts['minkunet']} with the MinkUNet)")  # fmt: skip
    print(f"  in all: {len(worlds) * (counts['tuning'] + held_out)} aggregations, each scored on every annotated view")
    if args.preset in SECONDS_PER_RUN:
        times = SECONDS_PER_RUN[args.preset]
        seconds = len(worlds) * sum(n * times[k if k != "tuning" else "2d"] for k, n in counts.items())
        per_run = f"2D {times['2d']} s, descriptors {times['descriptors']} s, MinkUNet {times['minkunet']} s per run"
        print(f"  about {seconds / 3600:.1f} h on two idle cores at the per-run times measured on {args.preset} "
              f"({per_run}), plus the scenes")  # fmt: skip
    ledger = args.ledger or args.work / "ledger"
    if ledger.is_dir():
        _print_ledger_progress(ledger, worlds, folders, states, train, seeds, counts)
    if args.dry_run:
        return 0

    markdown = [
        "# The paper's Tables 5-7 under the evaluation protocol",
        "",
        f"`olsplat bench paper` (docs/evaluation-protocol.md): preset {args.preset}, held-out seeds "
        f"{', '.join(map(str, seeds))}, training seeds {', '.join(map(str, train))}, encoders {args.encoders} "
        f"(weights {args.weights}). Paper figures: ../shared/paper/outlangsplat.tex.",
    ]
    document: dict[str, Any] = {
        "preset": args.preset, "seeds": seeds, "train_seeds": train, "methods": methods,
        "encoders": args.encoders, "weights": args.weights, "grid_limit": args.grid_limit, "worlds": {},
    }  # fmt: skip
    started = time.perf_counter()
    for world in worlds:
        for seed in [*train, *seeds]:
            if states[world, seed] == "make":
                _make_scene(folders[world, seed], args.preset, seed, world, args.views)
        base = args.work / world
        key = tuning_key([folders[world, s] for s in train], methods, args.encoders, args.weights, args.grid_limit)
        tune = saved_tuning(base / "tune.json", key)
        if tune is not None:
            print(f"[{world}] tuning reused from {base / 'tune.json'} (same scenes, methods, grids and encoder files)")
        else:
            print(f"[{world}] tuning {', '.join(methods)} on seeds {train} ({time.perf_counter() - started:.0f} s)")
            tune = tune_methods(
                [folders[world, s] for s in train], methods, args.encoders, args.weights, args.grid_limit, ledger
            )
            tune["key"] = key
            partial = base / "tune.json.partial"
            partial.write_text(json.dumps(tune, indent=1))
            partial.replace(base / "tune.json")  # whole or not at all: a rerun never reads half a tuning
            (base / "tune.md").write_text(tune_table(tune["methods"]) + "\n")
        print(f"[{world}] held-out seeds {seeds}: eval --tuned {base / 'tune.json'} "
              f"({time.perf_counter() - started:.0f} s)")  # fmt: skip
        argv = [a for s in seeds for a in ("--scene", str(folders[world, s]))]
        argv += ["--methods", ",".join(methods), "--encoders", args.encoders, "--feature-ablation", "--fusion-sweep"]
        argv += ["--tuned", str(base / "tune.json"), "--work", str(base / "eval"), "--resume", "--ledger", str(ledger)]
        argv += ["--json", str(base / "eval.json"), "--md", str(base / "eval.md")]
        if args.weights:
            argv += ["--weights", args.weights]
        if evaluate.run(_parse(evaluate.add_parser, "eval", argv)) != 0:
            raise OlsplatInputError(f"[{world}] olsplat eval {' '.join(argv)} failed")
        results = per_scene_results(json.loads((base / "eval.json").read_text()))
        chosen = {m: tune["methods"][m]["chosen"] for m in methods}
        text, figures = world_tables(results, world, chosen)
        markdown += ["", text]
        document["worlds"][world] = {"tune": str(base / "tune.json"), "eval": str(base / "eval.json"),
                                     "chosen": chosen, **figures}  # fmt: skip
    markdown += ["", f"Made in {time.perf_counter() - started:.0f} s."]
    text = "\n".join(markdown) + "\n"
    print()
    print(text)
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(text)
        print(f"tables -> {args.md}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document, indent=1))
        print(f"figures -> {args.json}")
    return 0


def tuning_key(folders: list[Path], methods: list[str], encoders: str, weights: str | None,
               grid_limit: int | None) -> dict[str, Any]:  # fmt: skip
    """What a saved tuning must have been made with to be reused: the training scenes (each
    scene.json's sha256), the methods and their grids as tuned, the encoders, their weights and
    their files (``encoder_fingerprint``)."""
    import hashlib

    from ..encoders.spec import encoder_fingerprint
    from .tune import GRIDS

    return json.loads(json.dumps({
        "scenes": {str(f): hashlib.sha256((f / "scene.json").read_bytes()).hexdigest() for f in folders},
        "grids": {m: GRIDS[m][:grid_limit] for m in methods},
        "encoders": encoders, "weights": weights, "encoder_files": encoder_fingerprint(encoders),
    }))  # fmt: skip


def saved_tuning(path: Path, key: dict[str, Any]) -> dict[str, Any] | None:
    """The tuning document at ``path`` when it was made with ``key`` (``tuning_key``), else None."""
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return saved if isinstance(saved, dict) and saved.get("key") == key else None


def _make_scene(folder: Path, preset: str, seed: int, world: str, views: int | None) -> None:
    """``olsplat sim make --preset P --seed S --world W --out FOLDER --force``, in this process."""
    import time

    from olsplat_sim.make import MakeOptions, make_dataset
    from olsplat_sim.world import WORLDS

    from ..outputs import empty_output_folder

    started = time.perf_counter()
    print(f"[{world}] making {folder} (olsplat sim make --preset {preset} --seed {seed} --world {world})", flush=True)
    empty_output_folder(folder, force=True)  # no scene.json: a make that did not finish
    make_dataset(_preset(preset, views), seed, folder, MakeOptions(WORLDS[world]), log=lambda *_: None)
    print(f"[{world}] made {folder} in {time.perf_counter() - started:.0f} s", flush=True)


def _parse(add_parser, name: str, argv: list[str]) -> argparse.Namespace:
    """``argv`` parsed by a command's own parser (its defaults and checks), to call its ``run``."""
    parser = argparse.ArgumentParser(prog="olsplat")
    add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args([name, *argv])


def per_scene_results(document: dict[str, Any]) -> dict[str, dict[str, dict]]:
    """An ``olsplat eval --json`` document of several scenes -> scene -> run label -> scores."""
    return {
        title: {label: r for key in ("methods", "features", "fusion_sweep") for label, r in runs.get(key, {}).items()}
        for title, runs in document["scenes"].items()
    }
