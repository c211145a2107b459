"""The paper's result tables, in Markdown, from ``olsplat eval`` results.

``results`` maps scene name -> method name -> the scores of ``evaluate_map`` (plus timing).
Layouts follow the paper: Table 2 (localisation, one cell "Loc@40/50/60" per method and
scene), Table 3 (mIoU and mAcc per method and scene), Table 4 (category-level IoU per query,
one row per method), Table 5 (aggregation strategies, one column per method), the component
ablation (the full method against each component switched off), Table 6 (feature
configurations) and Table 7 (lambda_2D x lambda_f). Each result may say which kind of run it
came from (``result["run"]["kind"]``: "method", "feature", "sweep"; "method" when absent). With several scenes
an "Overall" row averages the scenes (every scene counts the same, as in the paper). The best
value of each row is in bold.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .runs import WITHOUT_3D

ABLATIONS = ("outlangsplat", "outlangsplat-noquality", "outlangsplat-noconsistency")


def overall(results: dict[str, dict[str, dict]]) -> dict[str, dict]:
    """Per method, the mean over scenes of every figure (per-query IoU over the scenes that have it)."""
    methods = list(dict.fromkeys(m for scene in results.values() for m in scene))
    out = {}
    for name in methods:
        runs = [scene[name] for scene in results.values() if name in scene]
        merged: dict[str, Any] = {
            key: float(np.mean([r[key] for r in runs]))
            for key in ("mIoU", "mAcc", "loc40", "loc50", "loc60", "seconds", "score_seconds", "peak_rss_mb")
            if all(key in r for r in runs)  # result files of older versions have no scoring time
        }
        queries = dict.fromkeys(q for r in runs for q in r["per_query"])
        merged["per_query"] = {
            q: {k: float(np.mean([r["per_query"][q][k] for r in runs if q in r["per_query"]])) for k in ("IoU", "acc")}
            for q in queries
        }
        merged["scenes"] = len(runs)
        out[name] = merged
    return out


def _bold_best(values: list[float]) -> list[str]:
    """One-decimal cells; every cell equal to the best (as printed) in bold."""
    cells = [f"{v:.1f}" for v in values]
    best = max(values) if values else None
    return [f"**{c}**" if best is not None and c == f"{best:.1f}" else c for c in cells]


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _rows_by_scene(results, methods):
    rows = list(results.items())
    if len(results) > 1:
        rows.append(("Overall", overall(results)))
    return rows


def localisation_table(results: dict, methods: list[str]) -> list[str]:
    lines = ["**Localisation accuracy, Loc@40/50/60 (%)** (paper Table 2)", ""]
    lines += [_row(["Scenes", *methods]), _row(["---"] * (1 + len(methods)))]
    for scene, runs in _rows_by_scene(results, methods):
        columns = [_bold_best([runs[m][k] for m in methods]) for k in ("loc40", "loc50", "loc60")]
        lines.append(_row([scene, *("/".join(c[i] for c in columns) for i in range(len(methods)))]))
    return lines


def segmentation_table(results: dict, methods: list[str]) -> list[str]:
    lines = ["**Semantic segmentation, mIoU / mAcc (%)** (paper Table 3)", ""]
    lines += [
        _row(["Scenes", *(f"{m} {k}" for m in methods for k in ("mIoU", "mAcc"))]),
        _row(["---"] * (1 + 2 * len(methods))),
    ]
    for scene, runs in _rows_by_scene(results, methods):
        miou, macc = _bold_best([runs[m]["mIoU"] for m in methods]), _bold_best([runs[m]["mAcc"] for m in methods])
        lines.append(_row([scene, *(c for pair in zip(miou, macc, strict=True) for c in pair)]))
    return lines


def category_table(results: dict, methods: list[str]) -> list[str]:
    runs = overall(results) if len(results) > 1 else next(iter(results.values()))
    queries = list(dict.fromkeys(q for m in methods for q in runs[m]["per_query"]))
    where = "mean over the scenes" if len(results) > 1 else next(iter(results))
    lines = [f"**Category-level IoU (%)** ({where}; paper Table 4)", ""]
    lines += [_row(["Methods", *queries]), _row(["---"] * (1 + len(queries)))]
    columns = [
        _bold_best([runs[m]["per_query"].get(q, {"IoU": float("nan")})["IoU"] for m in methods]) for q in queries
    ]
    for i, name in enumerate(methods):
        lines.append(_row([name, *(c[i] for c in columns)]))
    return lines


def strategy_table(results: dict, methods: list[str], title: str) -> list[str]:
    runs = overall(results) if len(results) > 1 else next(iter(results.values()))
    lines = [title, ""]
    lines += [_row(["Metrics", *methods]), _row(["---"] * (1 + len(methods)))]
    for key, label in (("mIoU", "mIoU ↑"), ("mAcc", "mAcc ↑"), ("loc50", "Loc@50 ↑")):
        lines.append(_row([label, *_bold_best([runs[m][key] for m in methods])]))
    lines.append(_row(["seconds", *(f"{runs[m]['seconds']:.0f}" for m in methods)]))
    if all("score_seconds" in runs[m] for m in methods):  # older result files have no scoring time
        lines.append(_row(["seconds to score", *(f"{runs[m]['score_seconds']:.0f}" for m in methods)]))
    lines.append(_row(["peak RSS, MB", *(f"{runs[m]['peak_rss_mb']:,.0f}" for m in methods)]))
    return lines


def _kind(result: dict) -> str:
    return result.get("run", {}).get("kind", "method")


def sweep_table(results: dict, labels: list[str], title: str) -> list[str]:
    runs = overall(results) if len(results) > 1 else next(iter(results.values()))
    first = next(iter(results.values()))
    grid: dict[float, dict[float, dict]] = {}
    for label in labels:
        run = first[label]["run"]
        grid.setdefault(run["weights"][0], {})[run["lambda_f"]] = runs[label]
    lambdas_f = sorted({lf for row in grid.values() for lf in row})
    best = {k: max(r[k] for row in grid.values() for r in row.values()) for k in ("mIoU", "mAcc", "loc50")}
    lines = [title, ""]
    lines += [_row(["λ2D", "λf", "mIoU ↑", "mAcc ↑", "Loc@50 ↑"]), _row(["---"] * 5)]
    for l2d in sorted(grid):
        cells = []
        for key in ("mIoU", "mAcc", "loc50"):
            values = [grid[l2d][lf][key] if lf in grid[l2d] else float("nan") for lf in lambdas_f]
            cells.append("/".join(f"**{v:.1f}**" if f"{v:.1f}" == f"{best[key]:.1f}" else f"{v:.1f}" for v in values))
        lines.append(_row([f"{l2d:g}", "/".join(f"{lf:g}" for lf in lambdas_f), *cells]))
    return lines


def paper_tables(results: dict[str, dict[str, dict]]) -> str:
    """All tables the runs in ``results`` allow, as one Markdown document."""
    first = next(iter(results.values()))
    labels = [m for m in first if all(m in scene for scene in results.values())]
    methods = [m for m in labels if _kind(first[m]) == "method"]
    baselines = [m for m in methods if m not in ABLATIONS[1:]]
    sections = [
        localisation_table(results, baselines),
        segmentation_table(results, baselines),
        category_table(results, baselines),
    ]
    if len(results) > 1:
        sections.insert(0, spread_table(results, baselines))
    where = "mean over the scenes" if len(results) > 1 else next(iter(results))
    sections.append(strategy_table(results, baselines, f"**Aggregation strategies** ({where}; paper Table 5)"))
    ablations = [m for m in ABLATIONS if m in methods]
    if len(ablations) > 1:
        sections.append(strategy_table(results, ablations, f"**Component ablation** ({where}; components off)"))
    features = [m for m in labels if _kind(first[m]) == "feature"]
    if features:
        sections.append(strategy_table(results, features, f"**Feature configurations** ({where}; paper Table 6)"))
        if len(results) > 1 and WITHOUT_3D in features:
            sections.append(spread_table(results, features, WITHOUT_3D, "Feature configurations, paper Table 6. "))
    sweep = [m for m in labels if _kind(first[m]) == "sweep"]
    if sweep:
        sections.append(sweep_table(results, sweep, f"**Fusion weights λ2D x λf** ({where}; paper Table 7)"))
    return "\n\n".join("\n".join(s) for s in sections) + "\n"


REFERENCE = "outlangsplat"  # the method the paired differences are taken against


def spread(
    results: dict[str, dict[str, dict]], reference: str = REFERENCE, labels: list[str] | None = None
) -> dict[str, dict]:
    """Per run label (``labels``, default every label all scenes have), over the scenes:
    ``mIoU``, ``loc50`` ... means with ``mIoU_std``, ``mIoU_ci95`` and ``loc50_std``,
    ``loc50_ci95`` ([low, high], None with one scene); and, under ``reference``, ``paired``:
    against each other label, ``dmIoU``, ``dmIoU_ci95``, ``dloc50``, ``dloc50_ci95``
    (``reference`` minus it, per scene) and ``verdict`` on mIoU and Loc@50."""
    from .statistics import mean_ci, paired, verdict

    scenes = list(results)
    methods = [m for m in results[scenes[0]] if all(m in results[s] for s in scenes)]
    if labels is not None:
        methods = [m for m in methods if m in labels]
    out: dict[str, dict] = {}
    for name in methods:
        entry: dict[str, Any] = {}
        for key in ("mIoU", "mAcc", "loc40", "loc50", "loc60"):
            mean, std, interval = mean_ci([results[s][name][key] for s in scenes])
            entry[key] = mean
            if key in ("mIoU", "loc50"):
                entry[f"{key}_std"] = std
                entry[f"{key}_ci95"] = list(interval) if interval else None
        out[name] = entry
    if reference in methods:
        ours = {key: [results[s][reference][key] for s in scenes] for key in ("mIoU", "loc50")}
        out[reference]["paired"] = {}
        for name in methods:
            if name == reference:
                continue
            row: dict[str, Any] = {}
            for key in ("mIoU", "loc50"):
                mean, interval = paired(ours[key], [results[s][name][key] for s in scenes])
                row[f"d{key}"] = mean
                row[f"d{key}_ci95"] = list(interval) if interval else None
                row[f"{key}_verdict"] = verdict(interval)
            out[reference]["paired"][name] = row
    return out


def spread_table(
    results: dict[str, dict[str, dict]], methods: list[str], reference: str = REFERENCE, title: str = ""
) -> list[str]:
    """Mean ± half the 95 % interval over scenes, and the paired difference of ``reference``
    with each of ``methods``, marked a win / tie / loss only by whether its interval excludes zero."""
    figures = spread(results, reference, methods)
    n = len(results)
    lines = [
        f"**{title}Over {n} scenes** (mean ± half-width of the 95 % interval, Student's t; paired: "
        f"{reference} minus the row, per scene)",
        "",
        _row(["run", "mIoU", "Loc@50", f"paired ΔmIoU ({reference} −)", "paired ΔLoc@50"]),
        _row(["---"] * 5),
    ]

    def pm(mean: float, interval) -> str:
        return f"{mean:.1f} ± {(interval[1] - interval[0]) / 2:.1f}" if interval else f"{mean:.1f}"

    pairs = figures.get(reference, {}).get("paired", {})
    for name, entry in figures.items():
        cells = [name, pm(entry["mIoU"], entry["mIoU_ci95"]), pm(entry["loc50"], entry["loc50_ci95"])]
        if name in pairs:
            row = pairs[name]
            cells += [
                f"{pm(row['dmIoU'], row['dmIoU_ci95'])} ({row['mIoU_verdict']})",
                f"{pm(row['dloc50'], row['dloc50_ci95'])} ({row['loc50_verdict']})",
            ]
        else:
            cells += ["", ""]
        lines.append(_row(cells))
    return lines
