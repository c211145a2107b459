"""``olsplat sim train-structure``: the self-supervised MinkUNet shipped with olsplat.

SegContrast's objective (``olsplat_nodes.structure.segcontrast``) on the 3D branch's point sets
of simulator maps of training seeds (>= TRAINING_SEED_BASE, never an evaluation seed): each map
is made exactly as ``olsplat sim make --seed S`` makes map/point_cloud.ply (no frame is
rendered), reduced to the branch's point set (opacity > tau_o, voxel downsampling) and put in
its ground frame. No label of the simulator is read. Seeded: the same command gives the same
network up to float rounding.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from olsplat_nodes.structure.ground_frame import ground_frame
from olsplat_nodes.structure.points import structural_points
from olsplat_nodes.structure.segcontrast import (
    PretrainConfig,
    TrainingMap,
    pretrain,
    save_checkpoint,
    segments,
)

from .make import prior_map
from .presets import PRESETS
from .region_samples import TRAINING_SEED_BASE


def training_maps(seeds: list[int], preset: str = "small", config: PretrainConfig = PretrainConfig(), log=print):
    """One TrainingMap per seed: the branch's point set of the seed's map, segmented."""
    bad = [s for s in seeds if s < TRAINING_SEED_BASE]
    if bad:
        raise ValueError(f"pre-training uses training seeds only (>= {TRAINING_SEED_BASE}), got {bad}")
    maps = []
    for seed in seeds:
        start = time.perf_counter()
        gaussians, centres = prior_map(PRESETS[preset], seed)
        points = structural_points(gaussians)
        frame = ground_frame(points, centres)
        segment = segments(frame, config)
        maps.append(TrainingMap(frame, segment, f"{preset}{seed}"))
        log(f"map {preset}{seed}: {len(gaussians):,} Gaussians -> {len(points):,} points (voxel {points.voxel:.3f} m), "
            f"{segment.max() + 1} segments over {np.mean(segment >= 0):.0%} of the points "
            f"({time.perf_counter() - start:.0f} s)")  # fmt: skip
    return maps


def train_structure(out: Path, n_seeds: int, preset: str, config: PretrainConfig, log=print) -> Path:
    start = time.perf_counter()
    seeds = list(range(TRAINING_SEED_BASE, TRAINING_SEED_BASE + n_seeds))
    maps = training_maps(seeds, preset, config, log)
    log(f"pre-training a MinkUNet (cr {config.cr}) for {config.steps} windows on {torch.get_num_threads()} thread(s)")
    model = pretrain(maps, config, log)
    trained_on = f"olsplat simulator maps, preset {preset}, seeds {seeds[0]}..{seeds[-1]} (no labels)"
    save_checkpoint(model, out, config, trained_on, half=True)  # the shipped file stays small
    size = out.stat().st_size / 1e6
    log(f"done in {time.perf_counter() - start:.0f} s -> {out} ({size:.1f} MB, {model.out_channels}-d features)")
    return out
