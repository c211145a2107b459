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

1. Each encoder is trained in one seeded run of ``RUNG_EPOCHS[-1]`` epochs (one-cycle learning
   rate over the whole run) at a fixed number of views per seed; a checkpoint is kept at each
   rung of ``RUNG_EPOCHS`` (epochs, fractions allowed: the step ``ceil(rung * steps per epoch)``).
2. At each rung its **validation region accuracy** is measured on validation seeds
   ``VALIDATION_SEEDS`` (2000-2002: never used for training or testing), world v1 renders of the
   default flight, like ``zeroshot.evaluate``: regions of purity >= 0.75 from every proposer level,
   each labelled by the nearest of one query text per label (``zeroshot.label_queries``).
3. ``choose_rungs``: each encoder's rung is the smallest whose validation accuracy reaches the
   target ``TARGET_ACCURACY`` (T); if the two chosen rungs' accuracies differ by more than
   ``MAX_GAP`` (3 points), the stronger one steps down to the rung, at or below its own, whose
   accuracy is nearest the weaker one's (where it crosses it); an encoder that never reaches T
   keeps its last rung. A gap still above ``MAX_GAP`` is reported: the run is deterministic, so a
   finer ladder between the two rungs (a checkpoint at every step) reproduces it and stops it at
   the step where it crosses.

T = 0.75 validation region accuracy, chosen so that one encoder alone lands in the 50-65 mIoU
range real aerial CLIPs reach on UAV scenes (RemoteCLIP / RS5M: 50-59 in the paper). The map from
region accuracy to pipeline mIoU is not known. Calibration, measured before training: the shipped
olsplat-cnn64 scores 0.935 on this validation measure (olsplat-vit48 0.861) where ``olsplat bench
diagnose`` gives it 0.83 on small0 at 78 mIoU; so T = 0.75 here is about 0.665 on diagnose's
measure (x 0.83 / 0.935). Two guesses of the map from there bracket the pipeline mIoU:
proportional (78 * 0.665 / 0.83 = 62) and IoU-like (IoU ~ a / (2 - a), scaled to 78 at 0.83: 55).
To be checked with ``olsplat eval`` on the validation seeds (never on the held-out seeds below 1000).

Command: ``python -m olsplat_sim.train_pair [--out DIR] [--seeds N] [--views N]``.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from olsplat_nodes.encoders import CropConfig
from olsplat_nodes.encoders.tokenizer import WordTokenizer

from .flight import FlightFrame, FlightSpec, plan_flight
from .labels import LABELS, QUERIES
from .region_samples import CAPTIONS, TRAINING_SEED_BASE, RegionSamples, collect
from .train_encoders import ASSETS, CONTEXT, MEAN, STD, Design, export_design, train_design, vocabulary
from .zeroshot import label_queries

VALIDATION_SEEDS = (2000, 2001, 2002)
TARGET_ACCURACY = 0.75
MAX_GAP = 0.03
RUNG_EPOCHS = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
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


def choose_rungs(
    acc_a: Sequence[float], acc_b: Sequence[float], target: float = TARGET_ACCURACY, max_gap: float = MAX_GAP
) -> tuple[int, int]:
    """(rung index of A, of B) by the training budget rule (module docstring, step 3)."""
    if not len(acc_a) or not len(acc_b):
        raise ValueError(f"choose_rungs needs an accuracy per rung for both encoders, got {acc_a!r} and {acc_b!r}")

    def first_reaching(acc: Sequence[float], level: float) -> int:
        return next((i for i, a in enumerate(acc) if a >= level), len(acc) - 1)

    chosen = [first_reaching(acc_a, target), first_reaching(acc_b, target)]
    accs = (acc_a, acc_b)
    gap = accs[0][chosen[0]] - accs[1][chosen[1]]
    if abs(gap) > max_gap:
        strong = 0 if gap > 0 else 1
        weak_acc = accs[1 - strong][chosen[1 - strong]]
        # its rung where it crosses the weaker one's accuracy: the nearest to it, earlier on a tie
        chosen[strong] = min(range(chosen[strong] + 1), key=lambda i: (abs(accs[strong][i] - weak_acc), i))
    return chosen[0], chosen[1]


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


class _Stop(Exception):
    """Raised by a checkpoint callback to end a run early (a refined ladder needs no more steps)."""


def train_ladder(pair_design: PairDesign, samples: RegionSamples, validation: RegionSamples,
                 rungs: Sequence[float] = RUNG_EPOCHS, log=print, steps: Sequence[int] | None = None,
                 schedule_epochs: int | None = None) -> list[dict]:  # fmt: skip
    """One seeded run of ``schedule_epochs`` (default: the last rung, rounded up) epochs; per rung:
    {"epochs", "step", "accuracy", "towers"} (the towers' eval-mode copies at that step,
    ``accuracy`` on ``validation``). ``steps``: rungs as optimizer steps instead of epochs; the run
    ends after the last one. The same design and samples give the same run whatever the rungs."""
    d = pair_design.design
    tokenizer = _tokenizer(vocabulary(pair_design.captions))
    steps_per_epoch = math.ceil(len(samples.labels) / 256)
    at_step: dict[int, list[float]] = {}  # a tiny run may put two rungs on one step
    for r in rungs if steps is None else []:
        at_step.setdefault(max(1, math.ceil(r * steps_per_epoch)), []).append(r)
    for step in steps or []:
        at_step.setdefault(step, []).append(step / steps_per_epoch)
    last = max(at_step) if steps else None
    ladder: list[dict] = []

    def keep(step: int, image_tower, text_tower) -> None:
        if step not in at_step:
            return
        towers = copy.deepcopy(image_tower).eval(), copy.deepcopy(text_tower).eval()
        accuracy = tower_accuracy(*towers, tokenizer, validation.crops[d.name], validation.labels)
        for epochs in at_step[step]:
            ladder.append({"epochs": epochs, "step": step, "accuracy": accuracy, "towers": towers})
            log(f"{d.name} rung {epochs:.3g} epochs (step {step}): validation region accuracy {accuracy:.3f}")
        if last is not None and step >= last:
            raise _Stop

    epochs = schedule_epochs or math.ceil(max(rungs))
    try:
        train_design(d, samples, tokenizer, epochs, pair_design.init_seed, log, pair_design.captions, keep)
    except _Stop:
        pass
    return ladder


def refine_stronger(ladders: list[list[dict]], chosen: tuple[int, int], samples: list[RegionSamples],
                    validation: RegionSamples, rungs: Sequence[float] = RUNG_EPOCHS,
                    log=print) -> dict | None:  # fmt: skip
    """The budget rule's last step: when the chosen rungs are more than ``MAX_GAP`` apart, re-run
    the stronger encoder (the same run, deterministic) with a checkpoint at every step between its
    rung below and its chosen rung, and stop it at the first step whose validation accuracy reaches
    the weaker one's. Returns {"encoder" (0 or 1), "rung", "fine" (the refined ladder)} or None
    when nothing is to refine (gap within ``MAX_GAP``, or the chosen rung is the first)."""
    accs = [ladders[i][chosen[i]]["accuracy"] for i in (0, 1)]
    if abs(accs[0] - accs[1]) <= MAX_GAP:
        return None
    strong = 0 if accs[0] > accs[1] else 1
    k = chosen[strong]
    if k == 0 or ladders[strong][k - 1]["step"] >= ladders[strong][k]["step"]:
        return None
    low, high = ladders[strong][k - 1]["step"], ladders[strong][k]["step"]
    fine = train_ladder(PAIR[strong], samples[strong], validation, rungs, log, steps=range(low + 1, high + 1),
                        schedule_epochs=math.ceil(max(rungs)))  # fmt: skip
    rung = next((r for r in fine if r["accuracy"] >= accs[1 - strong]), ladders[strong][k])
    return {"encoder": strong, "rung": rung, "fine": fine}


def trained_on(pair_design: PairDesign, n_seeds: int, views: int, rung: dict) -> str:
    seeds = pair_design.seeds[:n_seeds]
    captions = "object captions (CAPTIONS)" if pair_design.captions is CAPTIONS else "material captions"
    noise = f", {pair_design.caption_noise:.0%} of crops with a wrong label's captions" * (
        pair_design.caption_noise > 0
    )
    return (
        f"olsplat simulator world v1 renders, seeds {seeds[0]}-{seeds[-1]}, {views} {pair_design.domain} per seed; "
        f"{captions}{noise}; init seed {pair_design.init_seed}; rung {rung['epochs']:.3g} epochs (step {rung['step']}) "
        f"(validation region accuracy {rung['accuracy']:.3f} on seeds {VALIDATION_SEEDS[0]}-{VALIDATION_SEEDS[-1]})"
    )


def train_pair(out: Path = ASSETS, n_seeds: int = 10, views: int = 16, validation_views: int = 8,
               rungs: Sequence[float] = RUNG_EPOCHS, log=print,
               validation_seeds: Sequence[int] = VALIDATION_SEEDS) -> dict:  # fmt: skip
    """Train both designs on their ladders, choose the rungs, export them to ``out``/NAME
    (``validation_seeds``: fewer for a quick test run, never others).

    Returns the report: per design its crops, ladder (epochs, step, accuracy), chosen rung and
    seconds; written to ``out``/train_pair.json when ``out`` is not the package's assets."""
    if not validation_seeds or not set(validation_seeds) <= set(VALIDATION_SEEDS):
        raise ValueError(f"validation seeds must be some of {VALIDATION_SEEDS}, got {validation_seeds!r}")
    start = time.perf_counter()
    validation = collect(
        list(validation_seeds), validation_views, {p.design.name: (p.design.image_size, p.design.crop) for p in PAIR}
    )
    seconds = time.perf_counter() - start
    log(f"validation: {len(validation.labels)} region crops from seeds {tuple(validation_seeds)} ({seconds:.0f} s)")
    report: dict = {"target": TARGET_ACCURACY, "max_gap": MAX_GAP, "validation_seeds": tuple(validation_seeds),
                    "validation_crops": len(validation.labels), "designs": {}}  # fmt: skip
    ladders, all_samples = [], []
    for p in PAIR:
        started = time.perf_counter()
        samples = collect_training(p, n_seeds, views)
        collected = time.perf_counter() - started
        log(f"{p.design.name}: {len(samples.labels)} training crops in {collected:.0f} s")
        ladder = train_ladder(p, samples, validation, rungs, log)
        ladders.append(ladder)
        all_samples.append(samples)
        report["designs"][p.design.name] = {
            "crops": len(samples.labels),
            "collect_seconds": collected,
            "train_seconds": time.perf_counter() - started - collected,
            "ladder": [{k: r[k] for k in ("epochs", "step", "accuracy")} for r in ladder],
        }
    chosen = choose_rungs([r["accuracy"] for r in ladders[0]], [r["accuracy"] for r in ladders[1]])
    rungs_chosen = [ladders[i][chosen[i]] for i in (0, 1)]
    refined = refine_stronger(ladders, chosen, all_samples, validation, rungs, log)
    if refined is not None:
        rungs_chosen[refined["encoder"]] = refined["rung"]
        report["designs"][PAIR[refined["encoder"]].design.name]["refined_ladder"] = [
            {k: r[k] for k in ("epochs", "step", "accuracy")} for r in refined["fine"]
        ]
    out.mkdir(parents=True, exist_ok=True)
    for p, rung in zip(PAIR, rungs_chosen, strict=True):
        image_tower, text_tower = rung["towers"]
        folder = export_design(
            p.design, image_tower, text_tower, vocabulary(p.captions), out, trained_on(p, n_seeds, views, rung)
        )
        write_checksums(folder)
        report["designs"][p.design.name]["chosen"] = {k: rung[k] for k in ("epochs", "step", "accuracy")}
        log(
            f"{p.design.name}: rung {rung['epochs']:.3g} epochs (step {rung['step']}), "
            f"validation accuracy {rung['accuracy']:.3f} -> {folder}"
        )
    for p in PAIR:
        unknown = sorted({w for text, _, _ in QUERIES for w in _tokenizer(vocabulary(p.captions)).unknown_words(text)})
        report["designs"][p.design.name]["unknown_query_words"] = unknown
    report["seconds"] = time.perf_counter() - start
    log(f"done in {report['seconds']:.0f} s")
    if out.resolve() != ASSETS.resolve():
        (out / "train_pair.json").write_text(json.dumps(report, indent=1))
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
    parser.add_argument("--out", type=Path, help="output folder (default: the package's encoders/assets)")
    parser.add_argument("--seeds", type=int, default=10, help="training scenes per design (A: 3000, ...; B: 4000, ...)")
    parser.add_argument("--views", type=int, default=16, help="views per scene")
    parser.add_argument("--validation-views", type=int, default=8, help="views per validation scene (2000-2002)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    if not 1 <= args.seeds <= 10:
        raise SystemExit(f"--seeds must be 1-10 (each design owns ten training seeds), got {args.seeds}")
    torch.set_num_threads(args.threads)
    train_pair(args.out or ASSETS, args.seeds, args.views, args.validation_views)
    return 0


assert TRAINING_SEED_BASE <= min(min(p.seeds) for p in PAIR)  # never an evaluation seed

if __name__ == "__main__":
    raise SystemExit(main())
