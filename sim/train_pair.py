"""Train an encoder pair that stands in for two independently trained aerial CLIPs (issue 43 part 3).

The shipped pair (``sim.train_encoders``) is one encoder twice: same seeds, views, captions and
loss. This pair differs where two real models trained by different people differ:

- **A** ``olsplat-nadir32``: the CNN image tower on tight 32 px crops (box + 25 %, outside faded),
  nadir views only at 0.6x the per-seed altitude (36-54 m), object captions (``CAPTIONS``),
  training seeds 3000-3009, init seed 30.
- **B** ``olsplat-oblique48``: the ViT image tower on wide 48 px crops (box + 60 %, lightly
  faded), oblique and orbit views only (pitch 30-60 degrees from nadir) at 1.4x the altitude
  (84-126 m), material and surface captions (``MATERIAL_CAPTIONS``) of which 15 % of the
  training crops carry a wrong label's, drawn at random (noisy web captions), training seeds
  4000-4009, init seed 40.

Both on clean world v1 renders (``region_samples.collect``), so that the world v2 flights are a
shift neither has seen. Towers, loss, augmentation and export are ``sim.train_encoders``'s.
Seeded: the same command gives the same models up to float rounding.

**Training budget rule** (fixed before training; part of the evaluation protocol):

1. Each encoder is trained in one seeded run of ``RUNG_EPOCHS[-1]`` epochs at a fixed number of
   views per seed, with a checkpoint at each rung of ``RUNG_EPOCHS`` (0.25 ... 16 epochs; the
   step ``ceil(rung * steps per epoch)``). The one-cycle learning rate spans the whole run, so a
   rung of this 16-epoch run is not the end of a shorter run (its rate is still high early on):
   that is intended, the ladder is one run and one schedule.
2. The **validation score** of a rung is the mean over the validation seeds ``VALIDATION_SEEDS``
   (2000-2002; small preset, world v1, default flight, all views) of ``olsplat eval --methods
   outlangsplat`` mIoU with that rung's exported encoder alone (2D features). Never a seed below
   1000, never a held-out seed.
3. ``pair_budget.choose_rungs``: target T = ``TARGET_MIOU`` = 55 mIoU (the middle of the 50-65
   range real aerial CLIPs reach on UAV scenes, so that held-out seeds, which may differ, stay in
   range). Each encoder's rung is the smallest whose validation score reaches T; one that never
   reaches T keeps its best-scoring rung. If the two chosen scores differ by more than
   ``MAX_GAP_MIOU`` (3 mIoU), the stronger steps down to its rung, at or below its chosen one,
   whose score is nearest the weaker's (the earlier on a tie). The validation region accuracy of
   each rung (as ``zeroshot.evaluate``: regions of purity >= 0.75, nearest of one query per label)
   is still measured and reported, never used.
4. Scoring is lazy (``pair_budget.next_to_score``): each encoder's rungs are scored from the lowest
   upward, stopping at the first that reaches T. Every rung below the chosen one is then scored,
   and the step-down only ever looks at those, so the choice equals that of scoring every rung.

History: the first rule (before 2026-11-27) chose by validation region accuracy (T = 0.75, within
3 points): A at 1.56 epochs (0.703, stepped down to match B) and B at its last rung, 8 epochs
(0.697), whose outlangsplat mIoU on the validation seeds then came out 41.2 and 50.8: equal region
accuracy is not equal mIoU.

Command: ``python -m olsplat_sim.train_pair --work DIR [--out DIR] [--scenes DIR]``
(``olsplat sim train-pair``): trains both ladders in two processes (one torch thread each; a rung's
towers are saved in ``DIR/NAME/rungs/EPOCHS`` as soon as the run reaches it) while it exports and
scores the rungs the scan needs (``DIR/scores.json``, kept: a rerun continues where it stopped;
a training run that was cut off starts again, the same seeded run); writes ``DIR/train_pair.json``
and, with ``--out``, the two chosen encoders to ``OUT/NAME``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import copy
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from olsplat_nodes.encoders import CropConfig
from olsplat_nodes.encoders.tokenizer import WordTokenizer

from .flight import FlightFrame, FlightSpec, plan_flight
from .labels import LABELS, QUERIES
from .pair_budget import (
    MAX_GAP_MIOU,
    TARGET_MIOU,
    VALIDATION_SEEDS,
    ScoreCache,
    choose_rungs,
    next_to_score,
    score_encoder,
    validation_scenes,
)
from .region_samples import CAPTIONS, TRAINING_SEED_BASE, RegionSamples, collect
from .train_encoders import CONTEXT, MEAN, STD, Design, export_design, train_design, vocabulary
from .zeroshot import label_queries

RUNG_EPOCHS = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0)
IMAGE = (320, 240)  # the renders' size, as region_samples.collect's default

# what a surface is made of, per label: the second encoder's captions. The query words
# (zeroshot.label_queries and labels.QUERIES: red, roof, building, white, tree, car, parking,
# lot, bare, ground, pavement, ...) each occur in some caption, so B's whole-word text tower knows them.
MATERIAL_CAPTIONS = {
    "red roof buildings": [
        "terracotta tiles",
        "red clay tiles",
        "a red tiled roof",
        "red painted building walls",
        "weathered terracotta",
    ],
    "blue roof buildings": [
        "blue glazed tiles",
        "blue painted metal sheets",
        "a blue metal roof",
        "blue coated steel",
        "blue building panels",
    ],
    "white roof buildings": [
        "white membrane roofing",
        "white painted concrete",
        "a white flat roof",
        "white plaster building",
        "bright white coating",
    ],
    "grey roof buildings": [
        "grey slate",
        "dark grey shingles",
        "a grey slate roof",
        "grey building render",
        "gray bitumen sheets",
    ],
    "road": ["asphalt surface", "dark tarmac", "a road of asphalt", "painted lane lines on tarmac", "smooth bitumen"],
    "lawn": ["mown grass", "short green turf", "a lawn of mown grass", "trimmed turf", "grass lawn texture"],
    "tree": ["foliage", "dense leaves", "tree foliage", "leafy canopy texture", "dark green leaves"],
    "car": ["painted metal", "glossy car paint", "car body metal", "metal and glass", "a painted car roof"],
    "parking lot": [
        "parking lot asphalt",
        "striped asphalt bays",
        "lined parking surface",
        "marked tarmac lot",
        "white lines on asphalt",
    ],
    "bare ground": ["packed earth", "exposed bare ground", "dry soil", "loose gravel and dirt", "bare brown earth"],
    "pavement": ["concrete slabs", "paving stones", "pavement tiles", "grey concrete paving", "stone pavement"],
}


@dataclass(frozen=True)
class PairDesign:
    design: Design  # name, crop size, CropConfig, tower kind
    seeds: tuple[int, ...]  # training scenes
    init_seed: int  # weights, batch order and augmentation
    views: Literal["nadir", "oblique"]  # which views of each flight: nadir, or oblique + orbit
    altitude_scale: float  # times the per-seed altitude collect draws in [60, 90] m
    captions: dict[str, list[str]]
    caption_noise: float  # share of training crops given a wrong label's captions

    @property
    def domain(self) -> str:
        return f"{self.views} views at {self.altitude_scale:g}x altitude"


DESIGN_A = PairDesign(
    Design("olsplat-nadir32", 32, CropConfig(context=0.25, fade=0.7), "cnn"),
    tuple(range(3000, 3010)), 30, "nadir", 0.6, CAPTIONS, 0.0,
)  # fmt: skip
DESIGN_B = PairDesign(
    Design("olsplat-oblique48", 48, CropConfig(context=0.6, fade=0.4), "vit"),
    tuple(range(4000, 4010)), 40, "oblique", 1.4, MATERIAL_CAPTIONS, 0.15,
)  # fmt: skip
PAIR = (DESIGN_A, DESIGN_B)


def view_planner(pair_design: PairDesign, views: int):
    """``collect``'s ``plan_frames``: ``views`` frames of one kind from a default-pattern flight of
    ``2 * views`` views at ``altitude_scale`` times the drawn altitude (half of a flight is nadir,
    the other half oblique lawnmower and orbit)."""
    keep = ("nadir",) if pair_design.views == "nadir" else ("oblique", "orbit")

    def plan(size_m: float, altitude_m: float, rng: np.random.Generator) -> list[FlightFrame]:
        spec = FlightSpec(2 * views, IMAGE[0], IMAGE[1], altitude_m=pair_design.altitude_scale * altitude_m)
        return [f for f in plan_flight(size_m, spec, rng) if f.kind in keep][:views]

    return plan


def noisy_labels(labels: np.ndarray, share: float, seed: int, n_labels: int = len(LABELS)) -> np.ndarray:
    """[N] labels where each crop, with probability ``share``, takes another label drawn uniformly."""
    rng = np.random.default_rng(seed)
    flip = rng.random(len(labels)) < share
    other = (labels + rng.integers(1, n_labels, len(labels))) % n_labels  # never the true label
    return np.where(flip, other, labels).astype(labels.dtype)


def _tokenizer(vocab: list[str]) -> WordTokenizer:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "vocab.json"
        path.write_text(json.dumps(vocab))
        return WordTokenizer(path, CONTEXT)


@torch.no_grad()
def tower_accuracy(image_tower, text_tower, tokenizer: WordTokenizer, crops: np.ndarray, labels: np.ndarray) -> float:
    """Region accuracy of torch towers (eval mode) on uint8 crops [N, S, S, 3] with labels [N]:
    each crop takes the label of the nearest of ``label_queries()`` (as ``zeroshot.evaluate``)."""
    pixels = torch.from_numpy(crops).permute(0, 3, 1, 2).float() / 255.0
    pixels = (pixels - torch.tensor(MEAN)[:, None, None]) / torch.tensor(STD)[:, None, None]
    images = torch.cat([image_tower(pixels[i : i + 512]) for i in range(0, len(pixels), 512)])
    texts = text_tower(torch.from_numpy(tokenizer(label_queries())))
    predicted = (torch.nn.functional.normalize(images, dim=-1) @ torch.nn.functional.normalize(texts, dim=-1).T).argmax(
        1
    )
    return float((predicted.numpy() == labels).mean())


def collect_training(pair_design: PairDesign, n_seeds: int, views: int) -> RegionSamples:
    """The design's training crops, labels already noisy when its captions are."""
    seeds = list(pair_design.seeds[:n_seeds])
    d = pair_design.design
    samples = collect(seeds, views, {d.name: (d.image_size, d.crop)}, plan_frames=view_planner(pair_design, views))
    if pair_design.caption_noise > 0:
        samples.labels = noisy_labels(samples.labels, pair_design.caption_noise, pair_design.init_seed)
    return samples


def rung_folder(work: Path, name: str, epochs: float) -> Path:
    return work / name / "rungs" / f"{epochs:g}"


def read_ladder(work: Path, name: str) -> dict:
    """``work``/NAME/ladder.json as the training run leaves it (``rungs`` grows as the run goes)."""
    path = work / name / "ladder.json"
    return json.loads(path.read_text()) if path.is_file() else {"rungs": [], "complete": False}


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def train_rungs(pair_design: PairDesign, work: Path, n_seeds: int = 10, views: int = 16, validation_views: int = 8,
                rungs: Sequence[float] = RUNG_EPOCHS, log=print,
                validation_seeds: Sequence[int] = VALIDATION_SEEDS) -> dict:  # fmt: skip
    """One seeded run of ``ceil(rungs[-1])`` epochs. At each rung, at once: its towers (eval-mode
    copies, pickled) to ``rung_folder``/towers.pt and {"epochs", "step", "accuracy" (validation
    region accuracy), "seconds"} to ``work``/NAME/ladder.json. Returns the ladder."""
    d = pair_design.design
    start = time.perf_counter()
    validation = collect(list(validation_seeds), validation_views, {d.name: (d.image_size, d.crop)})
    samples = collect_training(pair_design, n_seeds, views)
    collected = time.perf_counter() - start
    log(f"{d.name}: {len(samples.labels)} training crops, {len(validation.labels)} validation crops "
        f"({collected:.0f} s)")  # fmt: skip
    tokenizer = _tokenizer(vocabulary(pair_design.captions))
    steps_per_epoch = math.ceil(len(samples.labels) / 256)
    at_step: dict[int, list[float]] = {}  # a tiny run may put two rungs on one step
    for r in rungs:
        at_step.setdefault(max(1, math.ceil(r * steps_per_epoch)), []).append(r)
    epochs = math.ceil(max(rungs))
    ladder: dict[str, Any] = {
        "encoder": d.name, "crops": len(samples.labels), "validation_crops": len(validation.labels),
        "steps_per_epoch": steps_per_epoch, "epochs": epochs, "collect_seconds": collected, "rungs": [],
        "complete": False,
    }  # fmt: skip
    path = work / d.name / "ladder.json"
    _write_json(path, ladder)

    def keep(step: int, image_tower, text_tower) -> None:
        if step not in at_step:
            return
        towers = copy.deepcopy(image_tower).eval(), copy.deepcopy(text_tower).eval()
        accuracy = tower_accuracy(*towers, tokenizer, validation.crops[d.name], validation.labels)
        for rung in at_step[step]:
            folder = rung_folder(work, d.name, rung)
            folder.mkdir(parents=True, exist_ok=True)
            torch.save({"image": towers[0], "text": towers[1]}, folder / "towers.pt")
            seconds = time.perf_counter() - start
            ladder["rungs"].append({"epochs": rung, "step": step, "accuracy": accuracy, "seconds": seconds})
            log(f"{d.name} rung {rung:g} epochs (step {step}): validation region accuracy {accuracy:.3f}")
        _write_json(path, ladder)

    train_design(d, samples, tokenizer, epochs, pair_design.init_seed, log, pair_design.captions, keep)
    ladder["complete"] = True
    ladder["seconds"] = time.perf_counter() - start
    _write_json(path, ladder)
    return ladder


def export_rung(pair_design: PairDesign, work: Path, epochs: float, out: Path | None = None,
                trained_on_text: str | None = None) -> Path:  # fmt: skip
    """The rung's towers as an ONNX encoder folder: ``out``/NAME (default: in the rung's folder)."""
    towers = torch.load(rung_folder(work, pair_design.design.name, epochs) / "towers.pt", weights_only=False)
    target = out if out is not None else rung_folder(work, pair_design.design.name, epochs)
    return export_design(pair_design.design, towers["image"], towers["text"], vocabulary(pair_design.captions),
                         target, trained_on_text)  # fmt: skip


def trained_on(pair_design: PairDesign, n_seeds: int, views: int, rung: dict, epochs: int) -> str:
    seeds = pair_design.seeds[:n_seeds]
    captions = "object captions (CAPTIONS)" if pair_design.captions is CAPTIONS else "material captions"
    noise = f", {pair_design.caption_noise:.0%} of crops with a wrong label's captions" * (
        pair_design.caption_noise > 0
    )
    per_seed = ", ".join(f"{seed}: {v:.1f}" for seed, v in rung["miou"].items())
    return (
        f"olsplat simulator world v1 renders, seeds {seeds[0]}-{seeds[-1]}, {views} {pair_design.domain} per seed; "
        f"{captions}{noise}; init seed {pair_design.init_seed}; rung {rung['epochs']:g} epochs (step {rung['step']}) "
        f"of a {epochs}-epoch one-cycle run, chosen by validation outlangsplat mIoU {rung['miou_mean']:.1f} "
        f"(seeds {per_seed}; small preset, world v1) (validation region accuracy {rung['accuracy']:.3f})"
    )


class _Running:
    """A training run found by its pid file (``work``/NAME/train.pid), as a ``Popen`` for ``run_pair``."""

    def __init__(self, pid: int):
        self.pid = pid

    @staticmethod
    def find(work: Path, name: str, file: str = "train.pid") -> _Running | None:
        path = work / name / file
        try:
            pid = int(path.read_text())
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except (OSError, ValueError):
            return None
        return _Running(pid) if "train_pair" in cmdline and name in cmdline else None

    def poll(self) -> int | None:
        return None if Path(f"/proc/{self.pid}").exists() else 0

    def terminate(self) -> None:
        os.kill(self.pid, signal.SIGTERM)

    def wait(self) -> None:
        while self.poll() is None:
            time.sleep(0.5)


def _train_process(p: PairDesign, work: Path, n_seeds: int, views: int, validation_views: int,
                   rungs: Sequence[float], validation_seeds: Sequence[int]) -> subprocess.Popen:  # fmt: skip
    log_file = (work / p.design.name / "train.log").open("a")
    cmd = [sys.executable, "-m", "olsplat_sim.train_pair", "--work", str(work), "--train", p.design.name,
           "--seeds", str(n_seeds), "--views", str(views), "--validation-views", str(validation_views),
           "--rungs", ",".join(f"{r:g}" for r in rungs),
           "--validation-seeds", ",".join(map(str, validation_seeds)), "--threads", "1"]  # fmt: skip
    return subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT)


def run_pair(work: Path, out: Path | None = None, scenes_dir: Path | None = None, n_seeds: int = 10,
             views: int = 16, validation_views: int = 8, rungs: Sequence[float] = RUNG_EPOCHS, log=print,
             validation_seeds: Sequence[int] = VALIDATION_SEEDS, score=score_encoder, start_training=_train_process,
             poll_seconds: float = 20.0, jobs: int = 1) -> dict:  # fmt: skip
    """The budget rule end to end (module docstring): both ladders trained in two processes while
    the rungs the lazy scan needs are exported and scored one at a time (lowest epochs first);
    an encoder's training stops once its scan is over. Chosen rungs go to ``out``/NAME when given.
    Returns the report, also written to ``work``/train_pair.json."""
    start = time.perf_counter()
    work.mkdir(parents=True, exist_ok=True)
    other = _Running.find(work, "", "run.pid")
    if other is not None and other.pid != os.getpid():
        raise RuntimeError(f"another train_pair run (pid {other.pid}) works in {work}: wait for it or stop it")
    (work / "run.pid").write_text(str(os.getpid()))
    scenes = validation_scenes(scenes_dir or work / "scenes", validation_seeds, log)
    cache = ScoreCache(work / "scores.json")
    names = [p.design.name for p in PAIR]

    def scores(name: str) -> list[float | None]:
        return [cache.mean(name, r) for r in rungs]

    procs: dict = {}
    for p in PAIR:
        name = p.design.name
        if not read_ladder(work, name)["complete"] and next_to_score(scores(name)) is not None:
            (work / name).mkdir(parents=True, exist_ok=True)
            running = _Running.find(work, name)
            if running is not None:
                procs[name] = running
                log(f"{name}: training still running (pid {running.pid}): following it")
            else:
                procs[name] = start_training(p, work, n_seeds, views, validation_views, rungs, validation_seeds)
                log(f"{name}: training (log {work / name / 'train.log'})")
    # a training run outlives a failure here: a rerun follows it (its pid file)
    in_flight: dict[concurrent.futures.Future, tuple[int, float, float]] = {}  # -> (design, epochs, start)
    with concurrent.futures.ThreadPoolExecutor(max(1, jobs)) as pool:
        while True:
            for future in [f for f in in_flight if f.done()]:
                k, epochs, started = in_flight.pop(future)
                per_seed = future.result()
                cache.put(PAIR[k].design.name, epochs, per_seed, time.perf_counter() - started)
                mean = sum(per_seed.values()) / len(per_seed)
                log(f"{PAIR[k].design.name} rung {epochs:g} epochs: validation mIoU {mean:.1f} {per_seed} "
                    f"({time.perf_counter() - started:.0f} s)")  # fmt: skip
            busy = {(k, e) for k, e, _ in in_flight.values()}
            ready, waiting = [], []
            for k, p in enumerate(PAIR):
                name = p.design.name
                i = next_to_score(scores(name))
                if i is None:
                    if name in procs and procs[name].poll() is None:
                        log(f"{name}: scan over, training stopped (later rungs are not needed)")
                        procs[name].terminate()
                        procs[name].wait()
                    continue
                # the scan's next rung not yet scored nor being scored (with jobs > 1 it may run ahead)
                j = next((j for j in range(i, len(rungs)) if scores(name)[j] is None and (k, rungs[j]) not in busy),
                         None)  # fmt: skip
                if j is None:
                    continue
                if any(r["epochs"] == rungs[j] for r in read_ladder(work, name)["rungs"]):
                    ready.append((rungs[j], k))
                else:
                    waiting.append(name)
            if not ready and not waiting and not in_flight:
                break
            if ready and len(in_flight) < max(1, jobs):
                epochs, k = min(ready)
                p = PAIR[k]
                started = time.perf_counter()
                folder = export_rung(p, work, epochs)
                crops = work / p.design.name / "crops"
                in_flight[pool.submit(score, folder, scenes, log, crops=crops)] = (k, epochs, started)
                continue
            for name in waiting if not in_flight else []:
                proc = procs.get(name)
                if proc is None or proc.poll() is not None:
                    raise RuntimeError(f"{name}: rung not trained and no training running (see {work / name})")
            if in_flight:
                concurrent.futures.wait(in_flight, timeout=poll_seconds, return_when="FIRST_COMPLETED")
            else:
                time.sleep(poll_seconds)

    all_scores = [scores(n) for n in names]
    chosen = choose_rungs(all_scores[0], all_scores[1])
    report: dict = {"rule": "validation outlangsplat mIoU (sim/train_pair.py)", "target_miou": TARGET_MIOU,
                    "max_gap_miou": MAX_GAP_MIOU, "rung_epochs": list(rungs),
                    "validation_seeds": list(validation_seeds), "scenes": [str(s) for s in scenes],
                    "designs": {}}  # fmt: skip
    for p, k in zip(PAIR, chosen, strict=True):
        name = p.design.name
        ladder = read_ladder(work, name)
        entries = []
        for r in ladder["rungs"]:
            entry = {key: r[key] for key in ("epochs", "step", "accuracy")}
            per_seed = cache.get(name, r["epochs"])
            if per_seed is not None:
                entry["miou"] = per_seed
                entry["miou_mean"] = sum(per_seed.values()) / len(per_seed)
            entries.append(entry)
        rung = next(e for e in entries if e["epochs"] == rungs[k])
        report["designs"][name] = {
            "crops": ladder.get("crops"), "steps_per_epoch": ladder.get("steps_per_epoch"),
            "training_complete": ladder["complete"], "ladder": entries, "chosen": rung,
            "train_seconds": ladder.get("seconds", max((r["seconds"] for r in ladder["rungs"]), default=0.0)),
            "score_seconds": cache.seconds(name),
        }  # fmt: skip
        unknown = sorted({w for text, _, _ in QUERIES for w in _tokenizer(vocabulary(p.captions)).unknown_words(text)})
        report["designs"][name]["unknown_query_words"] = unknown
        log(f"{name}: chosen rung {rung['epochs']:g} epochs (step {rung['step']}), validation mIoU "
            f"{rung['miou_mean']:.1f} {rung['miou']}, region accuracy {rung['accuracy']:.3f}")  # fmt: skip
        if out is not None:
            text = trained_on(p, n_seeds, views, rung, math.ceil(max(rungs)))
            folder = export_rung(p, work, rung["epochs"], out, text)
            sums = write_checksums(folder)
            report["designs"][name]["shipped"] = {"folder": str(folder), "SHA256SUMS": sums.read_text()}
            log(f"{name} -> {folder}")
    report["seconds"] = time.perf_counter() - start
    _write_json(work / "train_pair.json", report)
    (work / "run.pid").unlink(missing_ok=True)
    return report


def write_checksums(folder: Path) -> Path:
    """``SHA256SUMS`` of the folder's files, in ``sha256sum`` format (name order), as the shipped assets'."""
    import hashlib

    names = sorted(p.name for p in folder.iterdir() if p.is_file() and p.name != "SHA256SUMS")
    lines = [f"{hashlib.sha256((folder / n).read_bytes()).hexdigest()}  {n}\n" for n in names]
    (folder / "SHA256SUMS").write_text("".join(lines))
    return folder / "SHA256SUMS"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m olsplat_sim.train_pair", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--work", type=Path, required=True, help="work folder: rungs, scores.json, train_pair.json")
    parser.add_argument("--out", type=Path, help="export the chosen encoders to OUT/NAME (e.g. the package's assets)")
    parser.add_argument("--scenes", type=Path, help="folder of the validation scenes valS (default WORK/scenes; "
                        "made with olsplat sim make --preset small --world v1 when missing)")  # fmt: skip
    parser.add_argument("--seeds", type=int, default=10, help="training scenes per design (A: 3000, ...; B: 4000, ...)")
    parser.add_argument("--views", type=int, default=16, help="views per scene")
    parser.add_argument("--validation-views", type=int, default=8, help="views per scene for the region accuracy")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per training run (default 1)")
    parser.add_argument("--jobs", type=int, default=1, help="rungs scored at once (default 1; more may score a "
                        "rung the scan turns out not to need, never changing the choice)")  # fmt: skip
    parser.add_argument("--train", metavar="NAME", help=argparse.SUPPRESS)  # one training run (internal)
    parser.add_argument("--rungs", help=argparse.SUPPRESS)
    parser.add_argument("--validation-seeds", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not 1 <= args.seeds <= 10:
        raise SystemExit(f"--seeds must be 1-10 (each design owns ten training seeds), got {args.seeds}")
    rungs = tuple(float(r) for r in args.rungs.split(",")) if args.rungs else RUNG_EPOCHS
    seeds = tuple(int(s) for s in args.validation_seeds.split(",")) if args.validation_seeds else VALIDATION_SEEDS
    if not set(seeds) <= set(VALIDATION_SEEDS):
        raise SystemExit(f"validation seeds must be some of {VALIDATION_SEEDS}, got {seeds}")
    torch.set_num_threads(args.threads)
    if args.train:
        design = next((p for p in PAIR if p.design.name == args.train), None)
        if design is None:
            raise SystemExit(f"--train: one of {', '.join(p.design.name for p in PAIR)}, got {args.train!r}")
        pid_file = args.work / design.design.name / "train.pid"
        pid_file.parent.mkdir(parents=True, exist_ok=True)
        pid_file.write_text(str(os.getpid()))
        try:
            train_rungs(design, args.work, args.seeds, args.views, args.validation_views, rungs, _flush_print, seeds)
        finally:
            pid_file.unlink(missing_ok=True)
        return 0
    run_pair(args.work, args.out, args.scenes, args.seeds, args.views, args.validation_views, rungs, _flush_print,
             seeds, jobs=args.jobs)  # fmt: skip
    return 0


def _flush_print(message: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} {message}", flush=True)


assert TRAINING_SEED_BASE <= min(min(p.seeds) for p in PAIR)  # never an evaluation seed

if __name__ == "__main__":
    raise SystemExit(main())
