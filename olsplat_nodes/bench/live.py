"""``olsplat bench live``: how far the refiner's folded live maps drift from exact passes, and
what each pass costs, replaying a finished store view by view.

The store of ``olsplat eval`` (``SCENE/eval/METHOD/store``) is replayed as the refiner meets it:
its segments appear ``--every`` at a time (linked into a growing store folder, nothing copied),
and after each arrival two live maps take a pass, one folding the new views in (``passes: fold``,
the refiner's default: a fold, or an exact pass where a fold would read more than
``--fold-limit`` times its observations, marked *) and one exact (``passes: exact``). Printed
per scene and method: each pass's seconds for both, the observations a fold and an exact pass
would read, the mean cosine between the two maps' features over the observed
Gaussians, and the scores (mIoU, Loc@50) of both maps before the final pass (all views in,
the most folds behind them): the largest drift a live user sees. The final pass is exact in
both, so the final map does not drift.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("live", help="folded vs exact live refinement passes: drift and seconds")
    parser.add_argument(
        "--scene", type=Path, action="append", help="a scene folder (repeatable; required but with --fit)"
    )
    parser.add_argument("--methods", default="outlangsplat,vala", help="methods whose eval stores to replay")
    parser.add_argument("--every", type=int, default=10, help="views that arrive between two passes")
    parser.add_argument(
        "--refresh", type=float, default=None, help="the folds' exact slice (default: the refiner's, refiner.refresh)"
    )
    parser.add_argument(
        "--fold-limit",
        type=float,
        default=None,
        help="a live pass folds while it reads at most this share of an exact pass's observations "
        "(default: the refiner's, refiner.fold_limit; inf: always fold)",
    )
    parser.add_argument(
        "--study",
        action="store_true",
        help="instead: fold without refresh, then print how much of the folds' error each refresh priority "
        "would recompute within a budget of 30%% of the stale observations",
    )
    parser.add_argument(
        "--fit",
        type=Path,
        action="append",
        help="instead: fit refiner.fold_limit from the --json files of runs with --fold-limit inf (repeatable)",
    )
    parser.add_argument("--json", type=Path, help="write the figures to this file")
    parser.set_defaults(run=run)


def fit_fold_limit(runs: list[dict]) -> dict:
    """The rule of docs/decisions.md ("A fold or an exact pass"): over every pass but the first
    of the replays ``runs`` (``replay``'s figures, folding always), least squares of fold seconds
    = a + c_f x million fold reads and of exact seconds = b + c_e x million exact pass reads;
    ``fold_limit`` = c_e / c_f rounded down to a multiple of 0.05. Also: how many passes, in how
    many of them the exact pass was the faster, and the seconds of all passes folding always,
    exact always and under the limit (a fold where fold reads <= limit x exact reads)."""
    rows = [
        (
            f["fold_reads"][i] / 1e6,
            f["fold_s"][i],
            f["exact_pass_reads"][i] / 1e6,
            f["exact_s"][i],
            f["exact_reads"][i] / 1e6,
        )
        for f in runs
        for i in range(1, len(f["views"]))
    ]
    if len(rows) < 2:
        raise ValueError(f"need at least two passes after the first to fit, got {len(rows)}")
    a = np.array(rows, np.float64)
    c_f, fold_0 = np.polyfit(a[:, 0], a[:, 1], 1)
    c_e, exact_0 = np.polyfit(a[:, 2], a[:, 3], 1)
    limit = float(np.floor(c_e / c_f / 0.05 + 1e-9) * 0.05)
    exact = a[:, 0] > limit * a[:, 4]  # the pass the limit makes exact (LiveMap.update's test)
    return {
        "passes": len(rows),
        "fold_s_per_m_reads": round(float(c_f), 4),
        "fold_s_intercept": round(float(fold_0), 3),
        "exact_s_per_m_reads": round(float(c_e), 4),
        "exact_s_intercept": round(float(exact_0), 3),
        "fold_limit": round(limit, 2),
        "exact_faster": int((a[:, 3] < a[:, 1]).sum()),
        "seconds": {
            "fold_always": round(float(a[:, 1].sum()), 1),
            "exact_always": round(float(a[:, 3].sum()), 1),
            "under_the_limit": round(float(np.where(exact, a[:, 3], a[:, 1]).sum()), 1),
        },
    }


def _cosine(a: np.ndarray, b: np.ndarray, rows: np.ndarray) -> float:
    """Mean cosine between the unit float16 rows of a and b where ``rows``."""
    x, y = a[rows].astype(np.float32), b[rows].astype(np.float32)
    return float(np.mean(np.sum(x * y, 1)))


def link_segments(segments: list[Path], work: Path) -> None:
    """Link a store's view segments into the store at ``work`` (``work/views/<segment>``, made
    when missing): a store of chosen views, nothing copied."""
    (work / "views").mkdir(parents=True, exist_ok=True)
    for segment in segments:
        (work / "views" / segment.name).symlink_to(segment.resolve(), target_is_directory=True)


def replay(store_folder: Path, method, every: int, work: Path, refresh: float, fold_limit: float) -> dict:
    """Both live maps over the store's segments, ``every`` at a time; the figures and maps
    (``refresh`` and ``fold_limit`` as ``run`` resolved them: LiveMap's when not given). Per pass besides
    the seconds: ``fold_exact`` (the live map's pass was exact: the cheaper by its fold_limit)
    and the observations ``added``, ``fold_reads`` and ``exact_reads`` (what a fold and an
    exact pass would read: ``LiveMap.reads``), ``exact_pass_reads`` (what the exact map's pass read)."""
    from ..method.live import LiveMap
    from ..storage import ObservationStore

    n = _map_size(store_folder)
    segments = ObservationStore(store_folder, n).segments()
    (work / "views").mkdir(parents=True)
    live = {
        kind: LiveMap(ObservationStore(work, n), refresh=refresh, fold_limit=fold_limit) for kind in ("fold", "exact")
    }
    figures: dict = {"views": [], "fold_s": [], "exact_s": [], "cosine": [], "fold_exact": []}
    figures.update({"added": [], "fold_reads": [], "exact_reads": [], "exact_pass_reads": []})
    for stop in range(every, len(segments) + every, every):
        link_segments(segments[stop - every : stop], work)
        for kind, live_map in live.items():
            start = time.perf_counter()
            live_map.update(method.aggregation, exact=kind == "exact")
            figures[f"{kind}_s"].append(round(time.perf_counter() - start, 3))
        fold, exact = live["fold"], live["exact"]
        assert fold.features is not None and exact.features is not None and exact.observed is not None
        figures["views"].append(fold.views)
        figures["fold_exact"].append(fold.last_exact)
        for key in ("added", "fold", "exact"):
            figures["added" if key == "added" else f"{key}_reads"].append(fold.last_reads[key])
        figures["exact_pass_reads"].append(exact.last_reads["exact"])  # what the exact map's pass read
        figures["cosine"].append(round(_cosine(fold.features, exact.features, exact.observed), 5))
    return {"figures": figures, "fold": live["fold"], "exact": live["exact"]}


STUDY_BUDGET = 0.3  # of the stale observations: what a refresh may recompute in the study


def refresh_study(store_folder: Path, method, every: int, work: Path) -> dict:
    """Which refresh priority finds the Gaussians a fold got wrong: the store's views folded
    ``every`` at a time with no refresh, then each Gaussian's error 1 - cos(fold, exact) against
    an exact pass over all views; per candidate priority, the share of the total error held by
    the Gaussians it ranks first within ``STUDY_BUDGET`` of the stale observations (each costs
    its observations). ``oracle`` ranks by the error itself per observation."""
    from ..method.live import LiveMap, refresh_priority
    from ..storage import ObservationStore

    n = _map_size(store_folder)
    segments = ObservationStore(store_folder, n).segments()
    (work / "views").mkdir(parents=True)
    fold = LiveMap(ObservationStore(work, n), refresh=0.0)
    moved = np.zeros(n)
    for stop in range(every, len(segments) + every, every):
        link_segments(segments[stop - every : stop], work)
        before = None if fold.features is None else fold.features.astype(np.float32)
        fold.update(method.aggregation, exact=False)
        if before is not None and fold.features is not None:
            had = np.linalg.norm(before, axis=1) > 0
            moved[had] += 1 - np.sum(before[had] * fold.features[had].astype(np.float32), 1)
    exact, observed = ObservationStore(work, n).refine(None, method.aggregation, False, unit_float16=True)
    assert fold.features is not None
    error = (1 - np.sum(fold.features.astype(np.float32) * exact.astype(np.float32), 1))[observed]
    seen = np.maximum(fold.seen[observed], 1).astype(np.float64)
    stale = (fold.seen - fold.exact_at)[observed].astype(np.float64)
    share, spread = stale / seen, 1 - np.clip(fold.norm[observed], 0, 1)
    budget = STUDY_BUDGET * stale.sum()
    priorities = {
        "spread x share / seen (the refiner's)": refresh_priority(spread, stale, seen),
        "spread x share": spread * share,
        "spread": spread,
        "movement in the folds": moved[observed],
        "share": share,
        "oracle: error / seen": error / seen,
    }
    captured = {}
    for name, priority in priorities.items():
        ranked = np.argsort(-priority, kind="stable")
        take = int(np.searchsorted(np.cumsum(seen[ranked]), budget, side="right"))
        captured[name] = round(float(error[ranked[:take]].sum() / max(error.sum(), 1e-12)), 3)
    return {"views": len(segments), "mean_error": round(float(error.mean()), 5), "captured": captured}


def graph_drift(scene_folder: Path, run_dir: Path, passes: dict[int, dict]) -> dict | None:
    """How far a graph run's last live version (a fold) lies from the exact map of the same
    views: both scored on the scene's annotations (``evaluate_map``, the version as the
    refiner wrote it, so a codebook snapshot is scored as a codebook). ``passes`` are the
    refiner's records by version (``latest.json`` as the run went); the exact map is one exact
    pass over the store's first ``views`` segments, linked into a temporary store (nothing
    copied), with the aggregation of the store's manifest. None when the scene has no
    annotations, the run wrote no fold or the refiner no longer keeps its snapshot. The
    figures: version, views, live and exact mIoU / Loc@50, ``drift_miou`` = exact - live."""
    from ..encoders.spec import encoder_from_spec
    from ..evaluate.scene_eval import evaluate_map
    from ..method import read_manifest
    from ..method.live import LiveMap
    from ..pipeline import Scene
    from ..storage import ObservationStore
    from ..storage.snapshot import LanguageMap

    if not any((scene_folder / "annotations").glob("*.json")):
        return None
    folds = [r for v, r in sorted(passes.items()) if not r.get("exact", True) and not r.get("final")]
    snapshot = run_dir / "map" / folds[-1]["file"] if folds else None
    manifest = read_manifest(run_dir / "store")
    if snapshot is None or not snapshot.is_file() or manifest is None or manifest.encoder is None:
        return None
    record = folds[-1]
    live = LanguageMap.load(snapshot)
    n, views = len(live), int(record["views"])
    segments = ObservationStore(run_dir / "store", n).segments()[:views]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "store"
        link_segments(segments, work)
        exact = LiveMap(ObservationStore(work, n))
        exact.update(manifest.method.aggregation, exact=True)
    assert exact.features is not None and exact.observed is not None
    scene = Scene.open(scene_folder)
    encoder = encoder_from_spec(manifest.encoder)
    scores = {
        "live": evaluate_map(scene, live, encoder),
        "exact": evaluate_map(scene, LanguageMap(exact.features, exact.observed, live.encoder), encoder),
    }
    figures = {"version": int(record["version"]), "views": views}
    figures.update({f"{k}_{m}": round(scores[k][m], 2) for k in scores for m in ("mIoU", "loc50")})
    figures["drift_miou"] = round(scores["exact"]["mIoU"] - scores["live"]["mIoU"], 2)
    figures["drift_loc50"] = round(scores["exact"]["loc50"] - scores["live"]["loc50"], 2)
    return figures


def _map_size(store_folder: Path) -> int:
    """The Gaussians of the map the store was made for: from the language map beside it."""
    from ..storage.snapshot import LanguageMap

    return len(LanguageMap.load(store_folder.parent / "language_map.npz"))


def run(args: argparse.Namespace) -> int:
    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate.scene_eval import evaluate_map
    from ..method import named_method
    from ..method.live import LiveMap
    from ..pipeline import Scene
    from ..storage.snapshot import LanguageMap

    if args.fit:
        runs = []
        for path in args.fit:
            try:
                runs += list(json.loads(path.read_text()).values())
            except (OSError, ValueError, AttributeError) as exc:
                raise OlsplatInputError(f"{path}: not the --json of olsplat bench live ({exc})") from exc
        try:
            fit = fit_fold_limit(runs)
        except (KeyError, TypeError, ValueError) as exc:
            raise OlsplatInputError(f"{', '.join(map(str, args.fit))}: cannot fit a fold limit: {exc!r}") from exc
        print(
            f"{fit['passes']} passes: fold s = {fit['fold_s_intercept']} + {fit['fold_s_per_m_reads']} x million "
            f"reads, exact s = {fit['exact_s_intercept']} + {fit['exact_s_per_m_reads']} x million reads; "
            f"fold_limit {fit['fold_limit']:.2f}"
        )
        t = fit["seconds"]
        print(
            f"  the exact pass the faster in {fit['exact_faster']} of {fit['passes']}; seconds in all: folding always "
            f"{t['fold_always']}, exact always {t['exact_always']}, under the limit {t['under_the_limit']}"
        )
        if args.json:
            args.json.write_text(json.dumps(fit, indent=1))
        return 0
    if not args.scene:
        raise OlsplatInputError("olsplat bench live needs --scene (or --fit)")
    if args.refresh is None:
        args.refresh = LiveMap.refresh
    if args.fold_limit is None:
        args.fold_limit = LiveMap.fold_limit
    if args.every < 1 or not args.refresh >= 0 or not args.fold_limit >= 0:
        raise OlsplatInputError(
            f"need --every >= 1, --refresh >= 0 and --fold-limit >= 0, got {args.every}, {args.refresh}, "
            f"{args.fold_limit}"
        )
    encoder = encoder_from_spec()
    results: dict = {}
    for folder in args.scene:
        scene = Scene.open(folder)
        for name in args.methods.split(","):
            store = folder / "eval" / name / "store"
            if not (store / "views").is_dir():
                raise OlsplatInputError(
                    f"{store}: no store; run `olsplat eval --scene {folder} --methods {name}` first"
                )
            if args.study:
                with tempfile.TemporaryDirectory() as tmp:
                    study = refresh_study(store, named_method(name), args.every, Path(tmp) / "store")
                results[f"{folder.name}/{name}"] = study
                print(
                    f"{folder.name} {name}: {study['views']} views folded {args.every} at a time without refresh, "
                    f"mean error 1 - cos {study['mean_error']}; share of the error recomputed within "
                    f"{STUDY_BUDGET:.0%} of the stale observations:"
                )
                for priority, share in study["captured"].items():
                    print(f"  {priority:40s} {share:.3f}")
                continue
            with tempfile.TemporaryDirectory() as tmp:
                out = replay(store, named_method(name), args.every, Path(tmp) / "store", args.refresh, args.fold_limit)
            scores = {}
            for kind in ("fold", "exact"):
                live = out[kind]
                scores[kind] = evaluate_map(scene, LanguageMap(live.features, live.observed, encoder.name), encoder)
            f = out["figures"]
            f.update({f"{k}_{m}": round(scores[k][m], 2) for k in scores for m in ("mIoU", "loc50")})
            results[f"{folder.name}/{name}"] = f
            print(
                f"{folder.name} {name}: {f['views'][-1]} views, a pass every {args.every}, refresh {args.refresh}, "
                f"fold limit {args.fold_limit}"
            )
            print(
                "  fold  s: "
                + ", ".join(f"{s:.2f}{'*' if e else ''}" for s, e in zip(f["fold_s"], f["fold_exact"], strict=True))
            )
            print(
                "  reads, fold / exact (M observations): "
                + ", ".join(
                    f"{a / 1e6:.2f} / {b / 1e6:.2f}" for a, b in zip(f["fold_reads"], f["exact_reads"], strict=True)
                )
            )
            print("  exact s: " + ", ".join(f"{s:.2f}" for s in f["exact_s"]))
            print("  cosine fold vs exact: " + ", ".join(f"{c:.4f}" for c in f["cosine"]))
            print(
                f"  before the final pass: fold {f['fold_mIoU']:.2f} mIoU / {f['fold_loc50']:.2f} Loc@50, "
                f"exact {f['exact_mIoU']:.2f} / {f['exact_loc50']:.2f}"
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
        print(f"figures -> {args.json}")
    return 0
