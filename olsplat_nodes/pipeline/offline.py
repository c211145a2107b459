"""The method end to end on a scene folder, offline (``olsplat aggregate`` / ``eval``): every
view through the same per-view step the live accumulator runs, then one refinement, into a
language map. Same inputs for every method, so the comparisons are fair: the map, the SfM
cameras, the frames and one region/feature cache. Views that do not see the prior map are
refused as the live accumulator refuses them (``method.coverage``): a WARN per view, and an
error when the run's first ``OFF_MAP_VIEWS`` views all are."""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..durable import DiskRunway
from ..errors import OlsplatInputError
from ..memory import peak_rss_mb
from ..method import Method
from ..method.coverage import CoverageGate, MapCoverage, off_map_error
from ..method.render_ahead import RenderAhead
from ..method.view_step import ViewOffMap, view_observations
from ..scene import Camera, Gaussians, read_ply
from ..storage import LanguageMap
from ..storage.store import segment_bytes
from ..storage.tiles import TiledStore, TileGrid, Tiling
from ..structure.branch import StructuralBranch, StructureConfig
from ..structure.points import StructuralPoints
from .scene_folder import Scene, view_features

log = logging.getLogger(__name__)

# Views after which a run's disk need is estimated again (bytes per view so far x views left):
# the first estimate early, then as far views (which see more Gaussians) come in.
DISK_CHECKS = (5, 25, 50, 100, 150, 200, 300, 400)
OFF_MAP_VIEWS = 5  # the run stops when its first this many views are all refused (the accumulator's default)

# (scene folder, map file state, what shapes the points) -> (points, features): the 3D branch's
# point features are costly and the same for every run over one map.
_POINT_FEATURES: dict[tuple, tuple[StructuralPoints, np.ndarray]] = {}


def _structural_branch(scene: Scene, gaussians: Gaussians, structure: StructureConfig) -> StructuralBranch:
    """A fresh 3D branch (untrained h_theta) over the map's point set and point features, which
    are computed once per map and kept for the process: an eval that sweeps lambda_f or runs
    the feature ablation pays for them once, not once per run."""
    stat = scene.ply.stat()
    key = (scene.folder.resolve(), stat.st_mtime_ns, stat.st_size, structure.tau_o, structure.voxel, structure.minkunet)
    if key not in _POINT_FEATURES:
        _POINT_FEATURES.clear()  # one map at a time: these are large
        built = StructuralBranch.build(gaussians, np.array([c.center for c in scene.cameras]), structure)
        _POINT_FEATURES[key] = (built.points, built.features)
    points, features = _POINT_FEATURES[key]
    return StructuralBranch(points, features, structure)


def aggregate_scene(
    scene: Scene,
    method: Method,
    encoder,
    out: Path,
    progress: Callable[[list[Camera]], Iterable[Camera]] | None = None,
    codebook: int | None = None,
    features_of: Callable[[Camera], tuple] | None = None,
    structure: StructureConfig | None = None,
    tile_m: float = 0.0,
) -> dict:
    """Aggregate every view into a language map at ``out/language_map.npz`` (in the codebook
    form with ``codebook`` centres when given); returns timing figures. ``features_of(camera)``
    gives a view's (label maps, bank per level); default: ``view_features`` with ``encoder``.
    With ``structure``, region banks are fused with the 3D branch before aggregation. With
    ``tile_m`` > 0 the store is kept per ground tile of that size (``storage/tiles.py``):
    the same map."""
    return aggregate_flights([scene], method, encoder, out, progress, codebook, features_of, structure, tile_m)


def disk_warning(out: Path, written: int, done: int, total: int, free: int, margin: float = 1.2) -> str | None:
    """What to tell the user when a run will not fit on its disk at its rate so far (``written``
    bytes of store for ``done`` of ``total`` views, ``free`` bytes left, ``margin`` for views that
    see more than the first ones: ``DiskRunway``, as the live accumulator); None when it fits. A
    warning, not an error: the rate is an estimate, and space can be made while the run goes on."""
    need = DiskRunway(written, max(done, 1), margin).need(total - done)
    if need <= free:
        return None
    return (
        f"{out}: the store will need ~{need / 2**30:.1f} GB more for the {total - done} views left "
        f"({written / max(done, 1) / 2**20:.1f} MB per view so far), and its disk has {free / 2**30:.1f} GB "
        "free: the run will stop with a full disk unless space is made"
    )


def flight_view_name(flight: int, flights: int, camera: Camera) -> str:
    """A view's name in the store: its camera's, or with several flights ``f<flight>/<name>``
    (two flights of one area may name their frames alike; each view must be recorded once)."""
    return camera.name if flights == 1 else f"f{flight}/{camera.name}"


def same_prior_map(scenes: list[Scene]) -> Gaussians:
    """The prior map the flights share (the first scene's); OlsplatInputError naming the scene
    whose map differs: flights go into one language map only over the same Gaussians."""
    gaussians = read_ply(scenes[0].ply)
    for other in scenes[1:]:
        theirs = read_ply(other.ply)
        if len(theirs) != len(gaussians) or not np.array_equal(theirs.means, gaussians.means):
            raise OlsplatInputError(
                f"{other.ply}: not the prior map of {scenes[0].ply} ({len(theirs):,} against "
                f"{len(gaussians):,} Gaussians, or other centres): flights are aggregated into one "
                "map only over the same map"
            )
    return gaussians


def aggregate_flights(
    scenes: list[Scene],
    method: Method,
    encoder,
    out: Path,
    progress: Callable[[list[Camera]], Iterable[Camera]] | None = None,
    codebook: int | None = None,
    features_of: Callable[[Camera], tuple] | None = None,
    structure: StructureConfig | None = None,
    tile_m: float = 0.0,
    gate: CoverageGate | None = CoverageGate(),  # noqa: B008 - frozen, a value
) -> dict:
    """``aggregate_scene`` over several flights of one prior map, into one language map: every
    view of every flight, flight after flight, recorded once under ``flight_view_name``. A view
    ``gate`` refuses is logged (WARN) and left out; when the first ``OFF_MAP_VIEWS`` views all
    are, ``OlsplatInputError`` says the views do not overlap the map (None: every view is taken)."""
    gaussians = same_prior_map(scenes)
    store = TiledStore(out / "store", Tiling.of(gaussians.means, TileGrid(tile_m)), writer=True)
    if len(store):
        raise OlsplatInputError(f"{out / 'store'} already holds {len(store)} views: choose a new --out")
    start = time.perf_counter()
    total, done, written = sum(len(scene.cameras) for scene in scenes), 0, 0
    first: list[tuple[str, MapCoverage | None]] = []  # the first views' figures when refused (None: taken)
    refused_views = 0
    # the next view rendered while this one's features and observations are made (the same
    # observations, bit for bit: method/render_ahead.py); not where numba's layer forbids it
    ahead = RenderAhead(gaussians, method) if RenderAhead.available() else None
    try:
        for flight, scene in enumerate(scenes):
            branch = _structural_branch(scene, gaussians, structure) if structure else None
            upcoming = list(scene.cameras)
            cameras = progress(scene.cameras) if progress else scene.cameras
            for index, camera in enumerate(cameras):
                if ahead is not None and index + 1 < len(upcoming):
                    ahead.start(upcoming[index + 1])
                rendered = ahead.take(camera) if ahead is not None else None
                label_maps, bank = features_of(camera) if features_of else view_features(scene, camera, encoder)
                name = flight_view_name(flight, len(scenes), camera)
                try:
                    observations, stacked, _stages = view_observations(
                        gaussians, camera, label_maps, bank, method, branch, gate, rendered
                    )
                except ViewOffMap as refusal:
                    log.warning("%s; left out", refusal)
                    refused_views += 1
                    if len(first) < OFF_MAP_VIEWS:
                        first.append((name, refusal.seen))
                    refused = [(n, seen) for n, seen in first if isinstance(seen, MapCoverage)]
                    if len(refused) == OFF_MAP_VIEWS:  # the first views, every one refused
                        raise OlsplatInputError(off_map_error(refused, refusal.gate, str(scenes[0].ply))) from None
                    continue
                if len(first) < OFF_MAP_VIEWS:
                    first.append((name, None))
                store.append(name, observations, stacked)
                done, written = done + 1, written + segment_bytes(observations, stacked)
                if done in DISK_CHECKS and done < total:
                    warning = disk_warning(out, written, done, total, shutil.disk_usage(out).free)
                    if warning:
                        log.warning(warning)
    finally:
        if ahead is not None:
            ahead.close()
    # unit float16 rows range by range, as the live refiner keeps them (bit-identical to unit_rows
    # of the float32 result, without its [N, D] float32 array and copy: 2.7 GB for the large map)
    features, observed = store.refine(method.aggregation, encoder.name)
    if features is None:
        raise OlsplatInputError(f"{', '.join(str(s.folder) for s in scenes)}: no view observed any Gaussian")
    LanguageMap(features, observed, encoder.name).save(out / "language_map.npz", codebook)
    seconds = time.perf_counter() - start
    views = sum(len(scene.cameras) for scene in scenes)
    return {
        "seconds": seconds,
        "views_per_second": views / seconds,
        "peak_rss_mb": peak_rss_mb(),
        "observed_gaussians": int(observed.sum()),
        "tiles": len(store.tiling),
        "views_refused": refused_views,  # left out: they did not see the map
    }
