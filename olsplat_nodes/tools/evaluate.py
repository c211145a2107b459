"""``olsplat eval``: aggregate a scene with several methods (and feature settings), score every
language map on the scene's annotations, print and write the paper's tables."""

from __future__ import annotations

import argparse
import functools
import json
from pathlib import Path


def add_parser(subparsers) -> None:
    from .method_names import DEFAULT_ENCODER, METHOD_NAMES

    ev = subparsers.add_parser("eval", help="aggregate with several methods and score them on the annotations")
    ev.add_argument(
        "--scene", required=True, type=Path, action="append", help="a scene folder; repeat for several scenes"
    )
    ev.add_argument(
        "--methods",
        default="outlangsplat,outlangsplat-paper,projection,drsplat,topk,vala",
        help=f"comma-separated, from: {', '.join(METHOD_NAMES)}",
    )
    ev.add_argument(
        "--encoders",
        default=DEFAULT_ENCODER,
        help=f"shipped names (default {DEFAULT_ENCODER}), 'shipped' (both fused) or exported encoder folders",
    )
    ev.add_argument("--weights", help="lambda_2D fusion weights, e.g. 0.6,0.4")
    ev.add_argument(
        "--features",
        choices=("2d", "2d3d"),
        default="2d",
        help="the methods' input: 2D region features, or fused with the 3D branch",
    )
    ev.add_argument("--lambda-f", type=float, default=0.7, help="2D share of the 2D-3D fusion (paper: 0.7)")
    ev.add_argument(
        "--lambda-f-points",
        type=int,
        default=0,
        metavar="N",
        help="scale each region's 3D share by its visible points up to N (0: the paper's constant share)",
    )
    ev.add_argument(
        "--minkunet",
        help="3D branch: 'shipped' (the packaged self-supervised MinkUNet) or a MinkUNet checkpoint "
        "(SegContrast layout) instead of geometric descriptors",
    )
    ev.add_argument(
        "--feature-ablation",
        action="store_true",
        help="also run the paper's Table 6 (each encoder, 2D fusion, 2D-3D fusion with descriptors and with "
        "the MinkUNet)",
    )
    ev.add_argument(
        "--fusion-sweep", action="store_true", help="also run the paper's Table 7 (lambda_2D x lambda_f, 12 runs)"
    )
    ev.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a method parameter for every method, as in launch files (tau_d=0.3, beta=[1,2,4], topk_max=24); "
        "repeatable; names: olsplat_nodes/method/params.py",
    )
    ev.add_argument(
        "--tuned",
        type=Path,
        metavar="TUNE.json",
        help="each method's chosen setting from `olsplat bench tune --json` (under --set, which still applies to "
        "every method); a method not in the file keeps its defaults",
    )
    ev.add_argument("--work", type=Path, help="folder for the per-run maps (default: SCENE/eval)")
    ev.add_argument(
        "--resume",
        action="store_true",
        help="reuse a scene's results saved in its work folder (results.json) by an earlier run with the same scene, "
        "runs, settings and encoder files; an interrupted evaluation continues where it stopped",
    )
    ev.add_argument(
        "--ledger",
        type=Path,
        metavar="DIR",
        help="a ledger of finished runs (one JSON per run, named by what made it: the scene's content, the method's "
        "parameters, the encoder files, the 3D branch): a run found there is not run again (the first is, and must "
        "match), each finished run is added; docs/evaluation-protocol.md",
    )
    ev.add_argument("--json", type=Path, help="write the results here")
    ev.add_argument("--md", type=Path, help="write the paper's tables (Markdown) here")
    ev.add_argument("--figures", type=Path, help="write side-by-side heatmaps per view and query here")
    ev.add_argument("--figure-views", type=int, default=2, help="annotated views per scene in --figures (default 2)")
    ev.set_defaults(run=run)


def _folder_name(label: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def run(args: argparse.Namespace) -> int:

    from ..encoders.spec import encoder_fingerprint, encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate.figures import qualitative_figures
    from ..evaluate.ledger import RunLedger, run_key, scene_digest
    from ..evaluate.one_run import aggregate_and_score
    from ..evaluate.runs import plan_runs
    from ..evaluate.tables import overall, paper_tables, spread
    from ..method import MethodParams
    from ..params import parse_assignments, parse_params
    from ..pipeline import Scene
    from ..structure.branch import StructureConfig, minkunet_path

    scenes = [Scene.open(folder) for folder in args.scene]  # every folder is checked before any work
    names = [m.strip() for m in args.methods.split(",") if m.strip()]
    settings = parse_assignments(args.set, "--set")
    if "method" in settings:
        raise OlsplatInputError("--set method=...: choose methods with --methods")
    if not 0.0 <= args.lambda_f <= 1.0:
        raise OlsplatInputError(f"--lambda-f must be in [0, 1], got {args.lambda_f}")
    checkpoint = minkunet_path(args.minkunet)
    if checkpoint is not None and not checkpoint.is_file():
        raise OlsplatInputError(f"{checkpoint}: no such MinkUNet checkpoint")
    weights = tuple(float(w) for w in args.weights.split(",")) if args.weights else None
    if args.lambda_f_points < 0:
        raise OlsplatInputError(f"--lambda-f-points must be >= 0, got {args.lambda_f_points}")
    structure = StructureConfig(lambda_f=args.lambda_f, lambda_f_points=args.lambda_f_points, minkunet=checkpoint)
    runs = plan_runs(
        names, args.encoders, weights, args.features == "2d3d", args.feature_ablation, args.fusion_sweep, structure
    )
    tuned = read_tuned(args.tuned, args.encoders, args.weights) if args.tuned else None
    chosen: dict[str, dict | None] = {}  # per method: the tuned setting, None when not tuned
    for r in runs:
        if r.method not in chosen:
            chosen[r.method] = tuned.get(r.method) if tuned is not None else None
            if tuned is not None and chosen[r.method] is None:
                print(f"{r.method}: not in {args.tuned}, its default setting")
            elif tuned is not None:
                print(f"{r.method}: tuned setting {json.dumps(chosen[r.method])} from {args.tuned}")
    used = {m: {**(setting or {}), **settings} for m, setting in chosen.items()}  # --set over the tuned setting
    methods = {  # unknown names and bad values fail before any work
        m: parse_params(MethodParams, {**values, "method": m}, where).resolve(where)
        for m, values in used.items()
        for where in ["--set" if chosen[m] is None else f"--tuned/--set ({m})"]
    }
    encoders = {}
    for r in runs:  # every encoder is loaded before any work
        if (r.encoders, r.weights) not in encoders:
            encoders[r.encoders, r.weights] = encoder_from_spec(
                r.encoders, ",".join(map(str, r.weights)) if r.weights else None
            )
    titles = [s.folder.name for s in scenes]
    if len(set(titles)) < len(titles):
        titles = [str(s.folder) for s in scenes]
    results: dict[str, dict] = {}
    fingerprints = {spec: encoder_fingerprint(spec) for spec in {r.encoders for r in runs}}
    ledger = RunLedger(args.ledger if not args.figures else None)  # figures need every map made here
    for title, scene in zip(titles, scenes, strict=True):
        work = (args.work / title if len(scenes) > 1 else args.work) if args.work else scene.folder / "eval"
        resume_key = _resume_key(scene, runs, used, fingerprints)
        saved = _saved_results(work, resume_key) if args.resume and not args.figures else None
        if saved is not None:
            results[title] = saved
            print(f"{title}: {len(saved)} runs reused from {work / RESULTS_FILE} (--resume)")
            continue
        results[title], maps, done = {}, {}, {}
        content = scene_digest(scene.folder) if ledger.folder is not None else ""
        for r in runs:
            encoder = encoders[r.encoders, r.weights]
            key = (r.method, encoder.name, r.structure)
            if key not in done:
                kept: list = []  # the map, when the figures need it
                compute = functools.partial(
                    aggregate_and_score, scene, methods[r.method], encoder, r.structure,
                    work / _folder_name(r.label), r.label, kept if args.figures and r.kind == "method" else None,
                )  # fmt: skip
                made_of = run_key(
                    content, methods[r.method], r.encoders, r.weights, fingerprints[r.encoders], r.structure
                )
                scores, reused = ledger.run(made_of, compute, f"{title} {r.label}")
                if reused:
                    print(f"{title}: {r.label} from the ledger ({ledger.path(made_of).name})")
                done[key] = (scores, kept[0] if kept else None)
            scores, kept_map = done[key]
            described = {**r.describe(), "settings": used[r.method], "tuned": chosen[r.method]}
            results[title][r.label] = {**scores, "run": described}
            if kept_map is not None:
                maps[r.label] = kept_map
            print(f"{title}: {r.label:28s} mIoU {scores['mIoU']:5.1f}  mAcc {scores['mAcc']:5.1f}  Loc@40/50/60 "
                  f"{scores['loc40']:5.1f} {scores['loc50']:5.1f} {scores['loc60']:5.1f}  ({scores['seconds']:.0f} "
                  "s)")  # fmt: skip
        _save_results(work, resume_key, results[title])
        if args.figures:
            folder = args.figures / title if len(scenes) > 1 else args.figures
            files = qualitative_figures(
                scene, maps, encoders[runs[0].encoders, runs[0].weights], folder, args.figure_views
            )
            print(f"{title}: {len(files)} figures -> {folder}")
    tables = paper_tables(results)
    print()
    print(tables)
    if args.json:
        document = _document(results, overall, spread)
        if tuned is not None:  # what each method ran with: its tuned setting, or null (its defaults)
            document["tuned"] = {"file": str(args.tuned), "chosen": chosen}
        args.json.write_text(json.dumps(document, indent=2))
    if args.md:
        args.md.write_text(tables)
    return 0


RESULTS_FILE = "results.json"  # a scene's results in its work folder, for --resume


def _resume_key(scene, runs, used: dict, fingerprints: dict[str, str]) -> dict:
    """What a scene's saved results must have been made with to be reused: the scene (its
    scene.json, sha256), every run as described and with its settings, and the encoder files."""
    import hashlib

    scene_json = scene.folder / "scene.json"
    return json.loads(
        json.dumps(
            {
                "scene": hashlib.sha256(scene_json.read_bytes()).hexdigest() if scene_json.is_file() else None,
                "runs": [
                    {"label": r.label, **r.describe(), "structure": str(r.structure), "settings": used[r.method]}
                    for r in runs
                ],
                "encoders": fingerprints,
            }
        )
    )


def _saved_results(work: Path, key: dict) -> dict | None:
    """A scene's saved results (run label -> scores) when ``work``/results.json was made with
    ``key``; None when absent, unreadable or made otherwise."""
    try:
        saved = json.loads((work / RESULTS_FILE).read_text())
    except (OSError, ValueError):
        return None
    return saved.get("results") if isinstance(saved, dict) and saved.get("key") == key else None


def _save_results(work: Path, key: dict, results: dict) -> None:
    """``work``/results.json, written whole or not at all (a temporary file renamed over it)."""
    work.mkdir(parents=True, exist_ok=True)
    partial = work / (RESULTS_FILE + ".partial")
    partial.write_text(json.dumps({"key": key, "results": results}, indent=1))
    partial.replace(work / RESULTS_FILE)


def read_tuned(path: Path, encoders: str | None = None, weights: str | None = None) -> dict[str, dict]:
    """Each method's chosen setting in a ``bench tune --json`` file: {method: {name: value}}.
    Anything else is one line (OlsplatInputError) naming the file. A note is printed when the
    file was tuned with other encoders than ``encoders`` / ``weights`` (this run's)."""
    from ..errors import OlsplatInputError

    try:
        document = json.loads(path.read_text())
        chosen = {name: result["chosen"] for name, result in document["methods"].items()}
    except FileNotFoundError:
        raise OlsplatInputError(f"--tuned {path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise OlsplatInputError(
            f"--tuned {path}: not a tuning result of `olsplat bench tune --json` ({type(exc).__name__}: {exc})"
        ) from None
    bad = [name for name, setting in chosen.items() if not isinstance(setting, dict)]
    if bad:
        raise OlsplatInputError(f"--tuned {path}: not a tuning result (the chosen setting of {bad[0]} is no mapping)")
    tuned_with = (document.get("encoders"), document.get("weights"))
    if encoders is not None and tuned_with[0] is not None and tuned_with != (encoders, weights):
        print(f"note: {path} was tuned with --encoders {tuned_with[0]} --weights {tuned_with[1]}, this run uses "
              f"--encoders {encoders} --weights {weights}")  # fmt: skip
    return chosen


def _document(results: dict, overall, spread) -> dict:
    """{"methods": {...}} as the issue specifies (the mean over scenes when there are several),
    plus "features" and "fusion_sweep" when those ran, and "scenes" with each scene's own.
    Over several scenes: "paired" (outlangsplat minus each method) and, with Table 6's runs,
    "features_paired" (the 2D-only run minus each feature configuration)."""
    from ..evaluate.runs import WITHOUT_3D

    def split(runs: dict) -> dict:
        out = {"methods": {k: v for k, v in runs.items() if v["run"]["kind"] == "method"}}
        for kind, key in (("feature", "features"), ("sweep", "fusion_sweep")):
            chosen = {k: v for k, v in runs.items() if v["run"]["kind"] == kind}
            if chosen:
                out[key] = chosen
        return out

    if len(results) == 1:
        return split(next(iter(results.values())))
    merged = overall(results)
    for label, value in merged.items():
        value["run"] = next(iter(results.values()))[label]["run"]
    document = split(merged)
    for label, figures in spread(results, labels=list(document["methods"])).items():  # over scenes, paired
        if "paired" in figures:  # ours minus each other method, per scene: document["paired"][method]
            document["paired"] = figures.pop("paired")
        document["methods"][label].update(figures)
    if WITHOUT_3D in document.get("features", {}):  # Table 6: paired against the 2D-only run
        for label, figures in spread(results, WITHOUT_3D, list(document["features"])).items():
            if "paired" in figures:
                document["features_paired"] = figures.pop("paired")
            document["features"][label].update(figures)
    document["scenes"] = {title: split(runs) for title, runs in results.items()}
    return document
