"""``olsplat bench change``: what changed since the last flight, against the simulator's truth.

Per seed, three flights over one town and its prior map (``olsplat sim make``): ``a``, the
seed's own flight; ``b``, flight seed 1 after the default changes (``--changes default``); ``c``,
flight seed 2 with no change (``--changes none``). Each is made under ``WORK/<preset><seed>/``
or reused when its scene.json is what that command writes. Two runs aggregate the three flights
with per-flight maps (``olsplat aggregate --scene a --scene b --scene c --per-flight``): the
default method (ours) and ``projection`` (both baselines); a run is reused when its
``done.json`` names the same scenes. Flight a against b is the changed pair, a against c the
unchanged one. The scores (``change_scores.py``) become instances through
``query.change.change_instances``, the same extraction for every method, and are scored by
``change_metrics.py``.

The order is the protocol's (docs/evaluation-protocol.md, "What changed since the last
flight"): the training seeds (>= 1000) first; each method's two cuts chosen on them by one rule
and written to ``WORK/tune.json``; only then are the held-out seeds made and scored with those
cuts. ``--views N`` (hidden) makes flights of N views: for tests, never for a table.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import change_metrics as metrics
from .change_scores import METHODS, best_view_difference, feature_difference
from .change_text import TEXT, TextTruth, params_of, score_text, text_truth, tune_text

# folder -> (flight seed, --changes): the seed's own flight, a changed later one, an unchanged one
FLIGHTS: dict[str, tuple[int | None, str | None]] = {"a": (None, None), "b": (1, "default"), "c": (2, "none")}
RUNS = ("outlangsplat", "projection")  # the aggregations per seed: ours, and both baselines' observations
DEFAULTS = "ours, default cuts"  # the shipped ChangeParams, reported beside the tuned rows, never claimed
# the truth as the score (1 on a true change's Gaussians, 0 elsewhere) through the same extraction: the
# ceiling the instances and the >= 50 % rule leave (adjacent changes merge), reported, never claimed
CEILING = "truth as the score"
REPORTED = (*METHODS, DEFAULTS, CEILING)
TEXT_ROWS = (f'"{TEXT}" appeared (ours)', f'"{TEXT}" appeared (ours, default cuts)')  # change_text.py
CLAIMED = ("precision", "recall", "f1", "false_alarms_per_km2")


def add_parser(subparsers) -> None:
    from olsplat_sim.presets import PRESETS

    parser = subparsers.add_parser(
        "change",
        help="change instances against the simulator's truth: precision, recall and false alarms per km² of ours "
        "and two baselines over held-out seeds, cuts tuned on training seeds (docs/evaluation-protocol.md)",
    )
    parser.add_argument("--preset", default="tiny", choices=sorted(PRESETS), help="the flights' preset (tiny)")
    parser.add_argument("--seeds", default="0,1,2,3,4", help="held-out seeds, each < 1000 (default 0,1,2,3,4)")
    parser.add_argument(
        "--train-seeds", default="1001,1002,1003", help="training seeds, each >= 1000 (default 1001,1002,1003)"
    )
    parser.add_argument("--work", type=Path, required=True, help="folder for the flights, runs and the tuning")
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--md", type=Path, help="write the tables here (Markdown)")
    parser.add_argument("--views", type=int, help=argparse.SUPPRESS)  # tests only: flights of N views
    parser.set_defaults(run=run)


@dataclass
class Seed:
    """One seed's flights, truth and scores."""

    seed: int
    means: np.ndarray  # [N, 3] prior-map centres, metres
    change_id: np.ndarray  # [N] int32 true change of each Gaussian (flight b), -1 unchanged
    visible: np.ndarray  # [K] bool: the changes flight b shows (change_metrics.MIN_PIXELS)
    area_m2: float  # the town
    scores: dict[str, dict[str, np.ndarray]]  # method -> "changed" (a -> b) / "unchanged" (a -> c) -> [N]
    text: TextTruth | None = None  # ours' moves towards change_text.TEXT and the arrivals' truth


# --- flights and runs --------------------------------------------------------------------------


def _preset(name: str, views: int | None):
    from dataclasses import replace

    from olsplat_sim.presets import PRESETS

    return replace(PRESETS[name], n_views=views) if views else PRESETS[name]


def _command(preset: str, seed: int, flight: str) -> str:
    flight_seed, changes = FLIGHTS[flight]
    extra = f" --flight-seed {flight_seed} --changes {changes}" if flight_seed is not None else ""
    return f"olsplat sim make --preset {preset} --seed {seed}{extra}"


def _expected(preset, seed: int, flight: str) -> dict[str, Any]:
    """What scene.json says of the flight ``_command`` makes (JSON-normalised)."""
    from olsplat_sim.change_spec import ChangeSpec
    from olsplat_sim.make import MakeOptions

    flight_seed, changes = FLIGHTS[flight]
    fields = {"preset": asdict(preset), "seed": seed, "flight_seed": flight_seed, "options": asdict(MakeOptions())}
    if changes is not None:
        fields["changes"] = ChangeSpec.parse(changes, preset.size_m).to_json()
    return json.loads(json.dumps(fields))


def _state(folder: Path, preset, seed: int, flight: str) -> str:
    """ "reuse" (scene.json is what the flight's command writes), "make" (no scene.json: absent or
    unfinished) or "other"."""
    try:
        found = json.loads((folder / "scene.json").read_text())
    except FileNotFoundError:
        return "make"
    except (OSError, ValueError):
        return "other"
    expected = _expected(preset, seed, flight)
    if "changes" in expected:
        found = {**found, "changes": (found.get("changes") or {}).get("spec")}
    return "reuse" if all(found.get(k) == v for k, v in expected.items()) else "other"


def check_flights(work: Path, preset_name: str, views: int | None, seeds: list[int]) -> int:
    """How many of the seeds' flights are to be made; OlsplatInputError naming the first folder
    that holds another scene (before any work)."""
    from ..errors import OlsplatInputError

    preset, to_make = _preset(preset_name, views), 0
    for seed in seeds:
        for flight in FLIGHTS:
            folder = work / f"{preset_name}{seed}" / flight
            state = _state(folder, preset, seed, flight)
            if state == "other":
                raise OlsplatInputError(
                    f"{folder}: holds another scene than `{_command(preset_name, seed, flight)}` makes; remove it "
                    "or choose another --work"
                )
            to_make += state == "make"
    return to_make


def _flights(work: Path, preset_name: str, views: int | None, seed: int) -> dict[str, Path]:
    """The seed's three flight folders, made unless reusable (``check_flights`` first)."""
    from olsplat_sim.change_spec import ChangeSpec
    from olsplat_sim.make import make_dataset

    from ..outputs import empty_output_folder

    check_flights(work, preset_name, views, [seed])
    preset = _preset(preset_name, views)
    folders = {flight: work / f"{preset_name}{seed}" / flight for flight in FLIGHTS}
    for flight, folder in folders.items():
        if _state(folder, preset, seed, flight) == "make":
            flight_seed, changes = FLIGHTS[flight]
            spec = ChangeSpec.parse(changes, preset.size_m) if changes else None
            empty_output_folder(folder, force=True)
            make_dataset(preset, seed, folder, flight_seed=flight_seed, changes=spec, log=lambda *_: None)
            print(f"  made {folder} ({_command(preset_name, seed, flight)})", flush=True)
    return folders


def _aggregate(folder: Path, method: str, flights: dict[str, Path]) -> Path:
    """``olsplat aggregate --scene a --scene b --scene c --out FOLDER/METHOD --method METHOD
    --per-flight``, unless its done.json names the same method and scenes."""
    from ..outputs import empty_output_folder
    from ..tools import aggregate
    from .paper import _parse

    out = folder / method
    key = {"method": method, "scenes": {k: hashlib.sha256((f / "scene.json").read_bytes()).hexdigest()
                                        for k, f in flights.items()}}  # fmt: skip
    try:
        if json.loads((out / "done.json").read_text()) == key:
            return out
    except (OSError, ValueError):
        pass
    empty_output_folder(out, force=True)
    argv = [a for f in flights.values() for a in ("--scene", str(f))]
    started = time.perf_counter()
    aggregate.run_aggregate(_parse(aggregate.add_parser, "aggregate", [*argv, "--method", method, "--out", str(out),
                                                                      "--per-flight"]))  # fmt: skip
    (out / "done.json").write_text(json.dumps(key))
    print(f"  aggregated {out} in {time.perf_counter() - started:.0f} s", flush=True)
    return out


def prepare(work: Path, preset: str, views: int | None, seed: int) -> Seed:
    """A seed's flights and runs (made or reused), its truth and every method's scores."""
    from ..aggregate.change import change_score
    from ..scene import read_ply
    from ..storage import LanguageMap

    flights = _flights(work, preset, views, seed)
    runs = {method: _aggregate(work / f"{preset}{seed}", method, flights) for method in RUNS}
    truth = flights["b"] / "truth" / "changes"
    records = json.loads((truth / "changes.json").read_text())["changes"]
    change_id = np.load(truth / "map_changed.npz")["change_id"]
    means = np.asarray(read_ply(flights["a"] / "map" / "point_cloud.ply").means, np.float64)
    size = json.loads((flights["a"] / "scene.json").read_text())["preset"]["size_m"]

    def maps(run: Path, flight: str):
        return LanguageMap.load(run / "flights" / flight / "language_map.npz")

    ours, projection = runs["outlangsplat"], runs["projection"]
    scores = {
        "ours": {"changed": change_score(maps(ours, "f0"), maps(ours, "f1")),
                 "unchanged": change_score(maps(ours, "f0"), maps(ours, "f2"))},
        "projection difference": {"changed": feature_difference(maps(projection, "f0"), maps(projection, "f1")),
                                  "unchanged": feature_difference(maps(projection, "f0"), maps(projection, "f2"))},
        "heatmap difference": {"changed": best_view_difference(projection / "store", len(means), "f0", "f1"),
                               "unchanged": best_view_difference(projection / "store", len(means), "f0", "f2")},
    }  # fmt: skip
    truth_score = (change_id >= 0).astype(np.float32)
    scores[CEILING] = {"changed": truth_score, "unchanged": np.zeros_like(truth_score)}
    visible = metrics.visible_changes(truth / "masks", len(records))
    text = text_truth({f: maps(ours, f) for f in ("f0", "f1", "f2")}, means, change_id, records, visible)
    return Seed(seed, means, change_id, visible, float(size) ** 2, scores, text)


# --- scoring -----------------------------------------------------------------------------------


def score_seed(data: Seed, method: str, params) -> dict[str, Any]:
    """One method's figures on one seed with ``params`` (``ChangeParams``): the changed pair's
    detections and the unchanged pair's instances (count and per km²)."""
    from ..query.change import change_instances

    found = change_instances(data.means, data.scores[method]["changed"], params)
    alarms = change_instances(data.means, data.scores[method]["unchanged"], params)
    return _figures(data, [inst.members for inst in found], len(alarms))


def _figures(data: Seed, found: list[np.ndarray], alarms: int) -> dict[str, Any]:
    row = metrics.detections(found, data.change_id, data.visible)
    row["unchanged_instances"] = alarms
    row["false_alarms_per_km2"] = metrics.per_km2(alarms, data.area_m2)
    return row


def _params(candidate: float, object_score: float, min_area_m2: float = 0.0):
    from ..query.change import ChangeParams

    return ChangeParams(candidate=candidate, object_score=object_score, min_area_m2=min_area_m2)


def tune(train: list[Seed]) -> dict[str, Any]:
    """Each method's cuts by the protocol's rule (``change_metrics.choose``) over the grid of
    ``QUANTILES`` x ``RATIOS`` x ``AREAS``: {method: {"rows": [...], "chosen": row}}. The
    clusters depend only on the candidate cut, so they are made once per cut and pair and
    filtered for each object cut and size: the instances ``change_instances`` gives for each
    setting (tests/bench/test_bench_change.py holds the two equal)."""
    from ..query.change import change_clusters, changes_among
    from ..query.localize import ground_density

    density = [ground_density(d.means) for d in train]  # once per seed: the map does not change
    out = {}
    for method in METHODS:
        cuts = metrics.candidate_cuts([d.scores[method]["unchanged"] for d in train])
        rows = []
        for quantile, cut in cuts.items():
            clusters = []
            for d, g in zip(train, density, strict=True):
                rule = _params(cut, cut).for_density(g)
                clusters.append({pair: change_clusters(d.means, d.scores[method][pair], cut, rule.cluster_radius,
                                                       rule.min_points)
                                 for pair in ("changed", "unchanged")})  # fmt: skip
            for area in metrics.AREAS:
                for ratio in metrics.RATIOS:
                    figures = []
                    for d, made, g in zip(train, clusters, density, strict=True):
                        fewest = _params(cut, cut * ratio, area).for_density(g).min_gaussians
                        found = changes_among(d.means, made["changed"], cut * ratio, fewest)
                        alarms = changes_among(d.means, made["unchanged"], cut * ratio, fewest)
                        figures.append(_figures(d, [inst.members for inst in found], len(alarms)))
                    rows.append({"quantile": quantile, "ratio": ratio, "candidate": cut, "object_score": cut * ratio,
                                 "min_area_m2": area, "alarms": sum(f["unchanged_instances"] for f in figures),
                                 "f1": _mean([f["f1"] for f in figures]),
                                 "instances": sum(f["instances"] for f in figures)})  # fmt: skip
        out[method] = {"rows": rows, "chosen": metrics.choose(rows)}
    return out


def _mean(values: list[float]) -> float:
    """The mean of the defined values, NaN when none is."""
    kept = [v for v in values if not math.isnan(v)]
    return sum(kept) / len(kept) if kept else math.nan


def _cell(summary: dict[str, Any], digits: int) -> str:
    if math.isnan(summary["mean"]):
        return "—"
    text = f"{summary['mean']:.{digits}f}"
    for key in ("t95", "bootstrap95"):
        if summary[key]:
            text += f" [{summary[key][0]:.{digits}f}, {summary[key][1]:.{digits}f}]"
    return text


def tables(per_seed: dict[str, dict[str, dict]], tuned: dict[str, Any], seeds: list[int]) -> tuple[list[str], dict]:
    """Markdown lines (per-seed counts, means with intervals, paired differences) and figures."""
    names = [*REPORTED, *TEXT_ROWS]  # the text rows: "changes in view" are the arrivals in view
    summaries = {m: {k: metrics.summary([per_seed[m][str(s)][k] for s in seeds]) for k in CLAIMED} for m in names}
    lines = ["| seed | method | instances | true positives | changes in view | found | unchanged-pair instances |",
             "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for s in seeds:
        for m in names:
            r = per_seed[m][str(s)]
            lines.append(f"| {s} | {m} | {r['instances']} | {r['true_positives']} | {r['changes']} | {r['found']} | "
                         f"{r['unchanged_instances']} |")  # fmt: skip
    lines += ["", f"Mean over {len(seeds)} held-out seeds [95 % t interval] [95 % bootstrap interval] (precision over "
              "the seeds with instances):", "",
              "| method | candidate / object cut | precision | recall | F1 | false alarms per km² |",
              "| --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for m in names:
        c, figure = tuned[m], summaries[m]
        cuts = (
            f"{c['candidate']:.3g} / {c['object_score']:.3g}"
            + (f", {c['members']} members" if "members" in c else "")
            + (f", ≥ {c['min_area_m2']:g} m²" if c.get("min_area_m2") else "")
        )
        cells = [_cell(figure[k], 2) for k in ("precision", "recall", "f1")]
        lines.append(f"| {m} | {cuts} | {' | '.join(cells)} | {_cell(figure['false_alarms_per_km2'], 0)} |")
    lines += ["", "Paired differences, ours − baseline, per held-out seed (win: both 95 % intervals on ours' better "
              "side of zero; false alarms: lower is better):", "",
              "| baseline | metric | ours − baseline | t 95 % | bootstrap 95 % | seeds | verdict |",
              "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    comparisons = []
    for baseline in METHODS[1:]:
        for key in CLAIMED:
            ours = [per_seed["ours"][str(s)][key] for s in seeds]
            theirs = [per_seed[baseline][str(s)][key] for s in seeds]
            row = {"baseline": baseline, "metric": key,
                   **metrics.paired(ours, theirs, lower_is_better=key == "false_alarms_per_km2")}  # fmt: skip
            comparisons.append(row)
            digits = 0 if key == "false_alarms_per_km2" else 2

            def interval(value, digits=digits) -> str:
                return f"[{value[0]:+.{digits}f}, {value[1]:+.{digits}f}]" if value else "—"

            diff = "—" if math.isnan(row["difference"]) else f"{row['difference']:+.{digits}f}"
            lines.append(f"| {baseline} | {key} | {diff} | {interval(row['t95'])} | {interval(row['bootstrap95'])} | "
                         f"{row['seeds']} | **{row['verdict']}** |")  # fmt: skip
    return lines, {"summary": summaries, "paired": comparisons}


def run(args: argparse.Namespace) -> int:
    from olsplat_sim.presets import PRESETS

    from ..errors import OlsplatInputError
    from ..query.change import TEXT_PARAMS, ChangeParams
    from .paper import parse_seeds

    seeds = parse_seeds(args.seeds, "--seeds", training=False)
    train = parse_seeds(args.train_seeds, "--train-seeds", training=True)
    if args.views is not None and args.views < 2:
        raise OlsplatInputError(f"--views must be >= 2, got {args.views}")
    preset = PRESETS[args.preset]
    views = args.views or preset.n_views
    started = time.perf_counter()
    to_make = check_flights(args.work, args.preset, args.views, [*train, *seeds])
    print(f"plan: preset {args.preset} ({views} views a flight, {preset.size_m:g} m town); training seeds {train}, "
          f"then held-out seeds {seeds}; per seed 3 flights ({to_make} of {3 * (len(train) + len(seeds))} to make) "
          f"and 2 aggregations under {args.work}")  # fmt: skip

    print(f"training seeds {train}:", flush=True)
    training = [prepare(args.work, args.preset, args.views, s) for s in train]
    tuning = tune(training)
    tuned = {m: tuning[m]["chosen"] for m in METHODS}
    text_tuning = tune_text([(d.means, d.scores["ours"], d.text) for d in training if d.text is not None])
    tuned[TEXT_ROWS[0]] = text_tuning["chosen"]
    choices = {"train_seeds": train, "methods": tuning, "text": {"query": TEXT, **text_tuning}}
    (args.work / "tune.json").write_text(json.dumps(_plain(choices), indent=1))
    print(f"cuts chosen on the training seeds ({time.perf_counter() - started:.0f} s; fewest no-change instances, "
          "then the best mean F1):")  # fmt: skip
    for m in METHODS:
        c = tuned[m]
        print(f"  {m}: candidate {c['candidate']:.4g} (q {c['quantile']}), object {c['object_score']:.4g} "
              f"(x{c['ratio']}), at least {c['min_area_m2']:g} m²: training F1 {c['f1']:.3f}, no-change instances "
              f"{c['alarms']}")  # fmt: skip
    c = tuned[TEXT_ROWS[0]]
    print(f'  "{TEXT}" appeared (ours): candidate {c["candidate"]:.3g}, object {c["object_score"]:.3g}, '
          f"{c['members']} members: training F1 {c['f1']:.3f}, no-change instances {c['alarms']}")  # fmt: skip

    defaults, ceiling = ChangeParams(), ChangeParams(candidate=0.5, object_score=0.5)
    tuned[DEFAULTS] = {"candidate": defaults.candidate, "object_score": defaults.object_score,
                       "min_area_m2": defaults.min_area_m2}  # fmt: skip
    tuned[CEILING] = {"candidate": ceiling.candidate, "object_score": ceiling.object_score}
    tuned[TEXT_ROWS[1]] = {"candidate": TEXT_PARAMS.candidate, "object_score": TEXT_PARAMS.object_score,
                           "members": TEXT_PARAMS.min_gaussians}  # fmt: skip
    text_params = {row: params_of(tuned[row]["candidate"], tuned[row]["object_score"], tuned[row]["members"])
                   for row in TEXT_ROWS}  # fmt: skip
    per_seed: dict[str, dict[str, dict]] = {m: {} for m in (*REPORTED, *TEXT_ROWS)}
    print(f"held-out seeds {seeds}:", flush=True)
    for s in seeds:
        data = prepare(args.work, args.preset, args.views, s)
        for m in METHODS:
            chosen = tuned[m]
            per_seed[m][str(s)] = score_seed(data, m, _params(chosen["candidate"], chosen["object_score"],
                                                              chosen["min_area_m2"]))  # fmt: skip
        per_seed[DEFAULTS][str(s)] = score_seed(data, "ours", defaults)
        per_seed[CEILING][str(s)] = score_seed(data, CEILING, ceiling)
        for row, params in text_params.items():
            assert data.text is not None
            per_seed[row][str(s)] = score_text(data.means, data.scores["ours"], data.text, params)
            per_seed[row][str(s)]["false_alarms_per_km2"] = metrics.per_km2(
                per_seed[row][str(s)]["unchanged_instances"], data.area_m2
            )
        for m, rows in per_seed.items():
            r = rows[str(s)]
            print(
                f"  seed {s} {m}: {r['instances']} instances, {r['true_positives']} true; {r['found']} of "
                f"{r['changes']} changes in view found; {r['unchanged_instances']} on the unchanged pair"
            )
    lines, figures = tables(per_seed, tuned, seeds)
    title = (
        f"`olsplat bench change --preset {args.preset} --seeds {','.join(map(str, seeds))} --train-seeds "
        f"{','.join(map(str, train))}` ({views} views a flight; {time.perf_counter() - started:.0f} s)"
    )
    text = "\n".join([title, "", *lines]) + "\n"
    print()
    print(text)
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(text)
        print(f"tables -> {args.md}")
    if args.json:
        document = {"preset": args.preset, "views": views, "seeds": seeds, "train_seeds": train,
                    "town_m2": preset.size_m**2, "min_pixels": metrics.MIN_PIXELS, "tuned": tuned,
                    "per_seed": per_seed, **figures}  # fmt: skip
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(_plain(document), indent=1))
        print(f"figures -> {args.json}")
    return 0


def _plain(value: Any) -> Any:
    """``value`` with numpy scalars as Python numbers, NaN and infinities as null (strict JSON)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    return None if isinstance(value, float) and not math.isfinite(value) else value
