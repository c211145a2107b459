"""What a flight's encoders see: per-region and per-surface labels of an annotated scene, from
which ``agreement`` computes its statistics.

For each view: the region proposer's finest level (the regions the method gives features to),
each encoder's label per region (the nearest of the scene's label texts, as a query would
pick), the annotation's label per region (its majority label, kept when it covers at least
``min_purity`` of the region), and the view angle at the region's centre. Surfaces are what a
person would call one thing on the ground: an annotated instance (a building, a tree, a car),
or for stuff (road, lawn, ...) one label within one ``cell_m`` x ``cell_m`` cell of the ground
plane z = 0 (the pixel's ray meets the plane there). A surface's label in a view is the
majority of its pixels' region labels.

Coordinates: cameras as ``scene.Camera`` (OpenCV axes: x right, y down, z forward; world z up);
angles in degrees; the off-nadir angle of a ray is its angle to straight down.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...encoders.bank import encode_regions
from ...regions import RegionConfig, propose_regions
from ...scene import Camera
from ..annotations import read_annotation
from ..scene_eval import label_texts, load_queries

_INSTANCE_BASE = 10**12  # surface ids: (label + 1) * base + instance, or + _STUFF + cell code
_STUFF = 5 * 10**11
_CELL_OFFSET = 10**5  # cell indices shifted to be >= 0 (a town of up to 100 km at 1 m cells)


@dataclass(frozen=True)
class FlightRecords:
    """Labels of one flight's regions and surfaces, one row each; ``predicted`` maps an encoder's
    name to its labels in the same rows. Label ints index ``labels``."""

    labels: tuple[str, ...]
    region_view: np.ndarray  # [R] int view index
    region_truth: np.ndarray  # [R] int
    region_off_nadir_deg: np.ndarray  # [R] float, at the region's centroid
    region_predicted: dict[str, np.ndarray] = field(default_factory=dict)  # name -> [R] int
    surface: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [M] surface id
    surface_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [M]
    surface_truth: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [M]
    surface_predicted: dict[str, np.ndarray] = field(default_factory=dict)  # name -> [M] int


def pixel_rays(camera: Camera) -> np.ndarray:
    """[H, W, 3] unit world directions of the rays through the pixel centres (no distortion:
    the simulator's cameras are pinhole)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64) + 0.5
    local = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    world = local @ camera.world_from_camera[:3, :3].T
    return world / np.linalg.norm(world, axis=-1, keepdims=True)


def off_nadir_deg(rays: np.ndarray) -> np.ndarray:
    """[...] angle in degrees between each unit ray [..., 3] and straight down (0, 0, -1)."""
    return np.degrees(np.arccos(np.clip(-rays[..., 2], -1.0, 1.0)))


def ground_cells(camera: Camera, rays: np.ndarray, cell_m: float) -> np.ndarray:
    """[H, W, 2] int cell (x, y) where each pixel's ray meets z = 0; rays that never do (at or
    above the horizon) get the cell of a point far away, which no other view shares by chance."""
    centre = camera.center
    down = np.minimum(rays[..., 2], -1e-6)
    reach = -centre[2] / down
    points = centre[:2] + rays[..., :2] * reach[..., None]
    return np.floor(points / cell_m).astype(np.int64)


def surface_ids(labels: np.ndarray, instances: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """[H, W] int64 surface id of each labelled pixel (-1 where ``labels`` is -1): the annotated
    instance where there is one, else the label within the ground cell."""
    label_part = (labels.astype(np.int64) + 1) * _INSTANCE_BASE
    cell_code = (np.clip(cells[..., 0] + _CELL_OFFSET, 0, 2 * _CELL_OFFSET) * 10**6) + np.clip(
        cells[..., 1] + _CELL_OFFSET, 0, 2 * _CELL_OFFSET
    )
    ids = np.where(instances >= 0, label_part + instances, label_part + _STUFF + cell_code)
    return np.where(labels >= 0, ids, -1)


def region_truth(region_map: np.ndarray, labels: np.ndarray, n_labels: int, min_purity: float) -> np.ndarray:
    """[R] majority label of each region of ``region_map`` ([H, W] ids 0..R-1), -1 where the
    majority label covers less than ``min_purity`` of the region's pixels (or none)."""
    regions = int(region_map.max()) + 1
    valid = (labels >= 0) & (region_map >= 0)
    counts = np.zeros((regions, n_labels), np.int64)
    np.add.at(counts, (region_map[valid], labels[valid]), 1)
    sizes = np.bincount(region_map[region_map >= 0], minlength=regions)
    best = counts.argmax(1)
    pure = counts[np.arange(regions), best] >= min_purity * np.maximum(sizes, 1)
    return np.where(pure & (counts.sum(1) > 0), best, -1)


def majority_per_surface(
    ids: np.ndarray, pixel_labels: Mapping[str, np.ndarray], n_labels: int, min_px: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The surfaces of one view with at least ``min_px`` pixels ([S] ids) and each encoder's
    majority label over their pixels (name -> [S] int)."""
    valid = ids >= 0
    surfaces, inverse, sizes = np.unique(ids[valid], return_inverse=True, return_counts=True)
    keep = sizes >= min_px
    out = {}
    for name, per_pixel in pixel_labels.items():
        counts = np.zeros((len(surfaces), n_labels), np.int64)
        np.add.at(counts, (inverse, per_pixel[valid]), 1)
        out[name] = counts.argmax(1)[keep]
    return surfaces[keep], out


def collect_flight(
    folder: Path,
    cameras: Sequence[Camera],
    image_of: Callable[[Camera], np.ndarray],
    encoders: Mapping[str, Any],
    *,
    region_config: RegionConfig | None = None,
    min_purity: float = 0.5,
    cell_m: float = 8.0,
    min_surface_px: int = 20,
) -> FlightRecords:
    """``FlightRecords`` of the annotated views ``cameras`` of the scene in ``folder`` (its
    ``queries.json`` names the labels, ``annotations/<view>.json`` holds each view's truth)."""
    labels, queries = load_queries(folder)
    texts = label_texts(labels, queries)
    text_features = {name: np.asarray(enc.encode_text(texts), np.float32) for name, enc in encoders.items()}
    region_config = region_config or RegionConfig()
    rows: dict[str, list] = {key: [] for key in ("view", "truth", "angle", "surface", "surface_view", "surface_truth")}
    region_pred: dict[str, list] = {name: [] for name in encoders}
    surface_pred: dict[str, list] = {name: [] for name in encoders}
    for index, camera in enumerate(cameras):
        image = image_of(camera)
        truth_labels, instances = read_annotation(folder / "annotations" / f"{Path(camera.name).stem}.json", labels)
        levels = propose_regions(image, region_config)
        finest = levels.label_maps[-1]
        truth = region_truth(finest, truth_labels, len(labels), min_purity)
        kept = np.flatnonzero(truth >= 0)
        rays = pixel_rays(camera)
        angles = off_nadir_deg(rays)
        sizes = np.bincount(finest.ravel(), minlength=len(truth))
        mean_angle = np.bincount(finest.ravel(), weights=angles.ravel(), minlength=len(truth)) / np.maximum(sizes, 1)
        pixel_labels = {}
        for name, encoder in encoders.items():
            features = encode_regions(image, levels, encoder).features[-1]
            per_region = np.argmax(features @ text_features[name].T, axis=1)
            region_pred[name].append(per_region[kept])
            pixel_labels[name] = per_region[finest]
        rows["view"].append(np.full(len(kept), index))
        rows["truth"].append(truth[kept])
        rows["angle"].append(mean_angle[kept])
        ids = surface_ids(truth_labels, instances, ground_cells(camera, rays, cell_m))
        surfaces, majority = majority_per_surface(ids, pixel_labels, len(labels), min_surface_px)
        rows["surface"].append(surfaces)
        rows["surface_view"].append(np.full(len(surfaces), index))
        rows["surface_truth"].append(surfaces // _INSTANCE_BASE - 1)
        for name in encoders:
            surface_pred[name].append(majority[name])

    def cat(parts: list, dtype) -> np.ndarray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

    return FlightRecords(
        labels=tuple(labels),
        region_view=cat(rows["view"], np.int64),
        region_truth=cat(rows["truth"], np.int64),
        region_off_nadir_deg=cat(rows["angle"], np.float64),
        region_predicted={name: cat(parts, np.int64) for name, parts in region_pred.items()},
        surface=cat(rows["surface"], np.int64),
        surface_view=cat(rows["surface_view"], np.int64),
        surface_truth=cat(rows["surface_truth"], np.int64),
        surface_predicted={name: cat(parts, np.int64) for name, parts in surface_pred.items()},
    )


def flight_geometry(cameras: Sequence[Camera]) -> dict[str, float]:
    """How the flight varies its viewpoint: camera height range (world z, metres above the
    scene's z = 0), its largest step between consecutive frames, and the optical axis's
    off-nadir angle (median and max, degrees)."""
    heights = np.array([c.center[2] for c in cameras])
    axes = np.array([c.world_from_camera[:3, 2] for c in cameras])
    tilt = off_nadir_deg(axes / np.linalg.norm(axes, axis=1, keepdims=True))
    return {
        "views": len(cameras),
        "height_min_m": float(heights.min()),
        "height_max_m": float(heights.max()),
        "height_range_m": float(np.ptp(heights)),
        "height_step_max_m": float(np.abs(np.diff(heights)).max()) if len(heights) > 1 else 0.0,
        "tilt_median_deg": float(np.median(tilt)),
        "tilt_max_deg": float(tilt.max()),
    }
