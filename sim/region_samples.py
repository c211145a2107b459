"""Labelled region crops from simulator views: training data and zero-shot test data.

For each view of a generated scene: render it as the camera would see it, cut it into
regions with the project's proposer (so the crops look like the ones the pipeline makes),
and keep the regions whose pixels mostly carry one ground-truth label. Seeds below
``TRAINING_SEED_BASE`` are for evaluation; the shipped encoders are trained on seeds at or
above it and never see an evaluation scene.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from olsplat_nodes.encoders import CropConfig, region_crops
from olsplat_nodes.raster import rasterize
from olsplat_nodes.regions import RegionConfig, propose_regions

from .annotate import label_maps
from .flight import FlightFrame, FlightSpec, plan_flight
from .labels import LABELS
from .make import BACKGROUND
from .scene import generate_scene
from .sensor import SensorSpec, apply_sensor, exposure_gains, to_uint8

TRAINING_SEED_BASE = 1000

# what people call each label: training captions (the evaluation queries' own texts are not
# all here, so zero-shot accuracy also measures how the text tower generalises)
CAPTIONS = {
    "red roof buildings": [
        "a red roof",
        "a building with a red roof",
        "a red-roofed house",
        "red roof tiles",
        "a house with a red roof",
    ],
    "blue roof buildings": [
        "a blue roof",
        "a building with a blue roof",
        "a blue-roofed house",
        "blue roof tiles",
        "a house with a blue roof",
    ],
    "white roof buildings": [
        "a white roof",
        "a building with a white roof",
        "a white house",
        "a white-roofed building",
        "white roof",
    ],
    "grey roof buildings": [
        "a grey roof",
        "a gray roof",
        "a building with a grey roof",
        "a dark roof",
        "a house with a gray roof",
    ],
    "road": ["a road", "an asphalt road", "a street", "a road with lane markings", "asphalt"],
    "lawn": ["a lawn", "grass", "a green lawn", "a grass field", "a garden lawn"],
    "tree": ["a tree", "tree crowns", "a tree canopy", "green trees", "a leafy tree"],
    "car": ["a car", "a parked car", "a vehicle", "a car on the street", "an automobile"],
    "parking lot": ["a parking lot", "a car park", "parking spaces", "an empty parking area", "parking bays"],
    "bare ground": ["bare ground", "bare soil", "dirt", "a dirt path", "sand and soil"],
    "pavement": ["a pavement", "a sidewalk", "a concrete plaza", "a paved area", "concrete paving"],
}


@dataclass
class RegionSamples:
    crops: dict[str, np.ndarray]  # crop style name -> [N, S, S, 3] uint8
    labels: np.ndarray  # [N] int index into LABELS
    purity: np.ndarray  # [N] fraction of the region's labelled pixels that carry its label


def collect(
    seeds: list[int],
    views_per_seed: int,
    crop_styles: dict[str, tuple[int, CropConfig]],
    n_gaussians: int = 150_000,
    size_m: float = 110.0,
    image: tuple[int, int] = (320, 240),
    min_purity: float = 0.75,
    min_pixels: int = 40,
    plan_frames: Callable[[float, float, np.random.Generator], list[FlightFrame]] | None = None,
) -> RegionSamples:
    """Region crops (one array per named crop style: size and CropConfig) with their majority labels.

    ``plan_frames(size_m, altitude_m, rng)``: the views of each seed instead of the default flight
    (``views_per_seed`` views at ``altitude_m``, drawn in [60, 90] m per seed); ``sim.train_pair``
    uses it for nadir-only low views and oblique-only high views.
    """
    crops: dict[str, list[np.ndarray]] = {name: [] for name in crop_styles}
    labels, purities = [], []
    sensor = SensorSpec()
    regions_config = RegionConfig(level_counts=(40, 120, 400))  # many regions per view: more, varied samples
    for seed in seeds:
        rng = np.random.default_rng(seed)
        truth = generate_scene(n_gaussians, size_m, seed)
        altitude = float(rng.uniform(60, 90))
        if plan_frames is None:
            frames = plan_flight(size_m, FlightSpec(views_per_seed, image[0], image[1], altitude_m=altitude), rng)
        else:
            frames = plan_frames(size_m, altitude, rng)
        gains = exposure_gains(len(frames), sensor, rng)
        for frame, gain in zip(frames, gains, strict=True):
            result = rasterize(truth.gaussians, frame.camera, background=BACKGROUND)
            assert result.topk_ids is not None and result.topk_weights is not None  # kept by default
            picture = to_uint8(apply_sensor(result.rgb, gain, sensor, rng))
            truth_labels, _ = label_maps(
                result.topk_ids, result.topk_weights, result.alpha, truth.label, truth.instance
            )
            levels = propose_regions(picture, regions_config)
            valid = truth_labels >= 0
            for level_map in levels.label_maps:
                table = np.zeros((level_map.max() + 1, len(LABELS)))
                np.add.at(table, (level_map[valid], truth_labels[valid]), 1)
                total = table.sum(1)
                majority = table.argmax(1)
                purity = table.max(1) / np.maximum(total, 1)
                keep = np.flatnonzero((total >= min_pixels) & (purity >= min_purity))
                if not len(keep):
                    continue
                for name, (size, config) in crop_styles.items():
                    crops[name].append(region_crops(picture, level_map, size, config)[keep])
                labels.append(majority[keep])
                purities.append(purity[keep])
    return RegionSamples(
        crops={name: np.concatenate(c) for name, c in crops.items()},
        labels=np.concatenate(labels).astype(np.int64),
        purity=np.concatenate(purities).astype(np.float32),
    )
