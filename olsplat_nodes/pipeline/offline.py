"""The method end to end on a scene folder, offline: aggregate views into a language map, and
evaluate a map against the scene's annotations. Same inputs for every method, so the
comparisons are fair: the map, the SfM cameras, the frames and one region/feature cache.

Methods (names as in the design card):
- ``outlangsplat``: adaptive Top-K, pixel quality q_sum * q_eff, valid mask, tau_d, consistency
  iterations;
- ``outlangsplat-noquality`` (no q_sum * q_eff), ``outlangsplat-noconsistency`` (T = 0);
- ``topk`` (Dr.Splat-style): the same Top-K contributions, no reliability weighting, no tau_d,
  plain weighted mean;
- ``projection`` (LUDVIG-style): every contribution of every pixel (Top-K cap 32 and 100 %
  coverage, which holds all but a sliver of the weight), alpha*T-weighted mean, nothing else;
- ``vala`` (VALA-style): the same contributions, a per-view mass gate (the fewest Gaussians
  holding 95 % of the view's contribution; VALA's own threshold is not published here) and a
  streaming update weighted by each observation's cosine agreement, in flight order.
"""

from __future__ import annotations

import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ..aggregate import AggregationConfig, ObservationStore, observe_view, stack_levels
from ..aggregate.snapshot import LanguageMap
from ..encoders import encode_regions
from ..encoders.bank import load_bank, save_bank
from ..errors import OlsplatInputError
from ..raster import RasterConfig, rasterize
from ..regions import RegionConfig, propose_regions
from ..scene import Camera, read_colmap, read_ply
from ..structure.branch import StructuralBranch, StructureConfig


@dataclass(frozen=True)
class Method:
    aggregation: AggregationConfig
    raster: RasterConfig


_PLAIN = AggregationConfig(use_quality=False, tau_d=0.0, iterations=0)
METHODS = {
    "outlangsplat": Method(AggregationConfig(), RasterConfig()),
    "outlangsplat-noquality": Method(replace(AggregationConfig(), use_quality=False), RasterConfig()),
    "outlangsplat-noconsistency": Method(replace(AggregationConfig(), iterations=0), RasterConfig()),
    "topk": Method(_PLAIN, RasterConfig()),
    "projection": Method(_PLAIN, RasterConfig(topk_min=32, topk_max=32, topk_coverage=1.0)),
    "vala": Method(replace(_PLAIN, mass_gate=0.95, combine="streaming_cosine"), RasterConfig()),
}


def method(name: str) -> Method:
    if name not in METHODS:
        raise OlsplatInputError(f"unknown method {name!r}; known: {', '.join(METHODS)}")
    return METHODS[name]


@dataclass
class Scene:
    folder: Path
    ply: Path
    cameras: list[Camera]

    @staticmethod
    def open(folder: str | Path) -> Scene:
        folder = Path(folder)
        ply = folder / "map" / "point_cloud.ply"
        missing = [str(p) for p in (ply, folder / "sparse" / "0", folder / "images") if not p.exists()]
        if missing:
            raise OlsplatInputError(f"{folder}: not a scene folder (missing {', '.join(missing)})")
        return Scene(folder, ply, read_colmap(folder / "sparse" / "0"))

    def image(self, camera: Camera) -> np.ndarray:
        path = self.folder / "images" / camera.name
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise OlsplatInputError(f"{path}: missing or not an image")
        if bgr.shape[:2] != (camera.height, camera.width):
            raise OlsplatInputError(
                f"{path}: {bgr.shape[1]}x{bgr.shape[0]}, but its camera says {camera.width}x{camera.height}"
            )
        return np.ascontiguousarray(bgr[..., ::-1])


def view_features(scene: Scene, camera: Camera, encoder, region_config: RegionConfig = RegionConfig()):
    """(label maps [L, H, W], bank per level) of one view, from the scene's cache when it holds
    this encoder's features (``olsplat encode``), else computed and cached."""
    cache = scene.folder / "cache" / "encode" / f"{Path(camera.name).stem}.npz"
    cached = load_bank(cache, encoder.name)
    if cached is not None:
        return cached
    image = scene.image(camera)
    levels = propose_regions(image, region_config)
    bank = encode_regions(image, levels, encoder)
    save_bank(cache, levels.label_maps, bank)
    # through float16 as the cache stores them: computed and cached runs give the same numbers
    return levels.label_maps, [f.astype(np.float16).astype(np.float32) for f in bank.features]


_POINT_FEATURES: dict[tuple, tuple] = {}  # (scene folder, map file state, what shapes the points) -> (points, features)


def _structural_branch(scene: Scene, gaussians, structure: StructureConfig) -> StructuralBranch:
    """A fresh 3D branch (untrained h_theta) over the map's point set and point features, which
    are computed once per map and kept for the process: an eval that sweeps lambda_f or runs
    the feature ablation pays for them once, not once per run."""
    stat = scene.ply.stat()
    key = (scene.folder.resolve(), stat.st_mtime_ns, stat.st_size, structure.tau_o, structure.voxel, structure.minkunet)
    if key not in _POINT_FEATURES:
        _POINT_FEATURES.clear()  # one map at a time: these are large
        built = StructuralBranch.build(gaussians, np.array([c.center for c in scene.cameras]), structure)
        _POINT_FEATURES[key] = (built.points, built.features)
    return StructuralBranch(*_POINT_FEATURES[key], structure)


def add_view(
    gaussians, camera: Camera, label_maps, bank, chosen: Method, store: ObservationStore, branch=None
) -> dict[str, float]:
    """One view into the store: render its Top-K, fuse its bank with the 3D branch (if any),
    observe, append. Returns the seconds of each stage (rasterize, fuse, observe, append)."""
    t0 = time.perf_counter()
    rendered = rasterize(gaussians, camera, chosen.raster)
    t1 = time.perf_counter()
    if branch is not None:
        bank = branch.fuse_view(camera, rendered.depth, label_maps, bank)
    t2 = time.perf_counter()
    slots, stacked = stack_levels(label_maps, bank)
    observations = observe_view(rendered.topk_ids, rendered.topk_weights, slots, len(gaussians), chosen.aggregation)
    t3 = time.perf_counter()
    store.append(camera.name, observations, stacked)
    t4 = time.perf_counter()
    return {
        "rasterize": t1 - t0,
        "fuse": t2 - t1,
        "observe": t3 - t2,
        "append": t4 - t3,
        "kept": float(len(observations)),
    }


def aggregate_scene(
    scene: Scene,
    method_name: str,
    encoder,
    out: Path,
    progress=None,
    codebook: int | None = None,
    features_of: Callable[[Camera], tuple] | None = None,
    structure: StructureConfig | None = None,
) -> dict:
    """Aggregate every view into a language map at ``out/language_map.npz`` (in the codebook
    form with ``codebook`` centres when given); returns timing figures. ``features_of(camera)``
    gives a view's (label maps, bank per level); default: ``view_features`` with ``encoder``.
    With ``structure``, region banks are fused with the 3D branch before aggregation."""
    chosen = method(method_name)
    gaussians = read_ply(scene.ply)
    store = ObservationStore(out / "store", len(gaussians))
    if len(store):
        raise OlsplatInputError(f"{out / 'store'} already holds {len(store)} views: choose a new --out")
    start = time.perf_counter()
    branch = _structural_branch(scene, gaussians, structure) if structure else None
    cameras = progress(scene.cameras) if progress else scene.cameras
    for camera in cameras:
        label_maps, bank = features_of(camera) if features_of else view_features(scene, camera, encoder)
        add_view(gaussians, camera, label_maps, bank, chosen, store, branch)
    features, observed = store.refine(None, chosen.aggregation, only_touched=False)
    if features is None:
        raise OlsplatInputError(f"{scene.folder}: no view observed any Gaussian")
    LanguageMap.from_features(features, observed, encoder.name).save(out / "language_map.npz", codebook)
    seconds = time.perf_counter() - start
    return {
        "seconds": seconds,
        "views_per_second": len(scene.cameras) / seconds,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "observed_gaussians": int(observed.sum()),
    }
