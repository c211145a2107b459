"""``olsplat warm-up``: compile every numba kernel the nodes run, once, after an install.

numba compiles a kernel on its first call and keeps the machine code in its cache
(``__pycache__`` beside the sources, or ``NUMBA_CACHE_DIR``). On a fresh install the graph's
first minute would otherwise be spent compiling on the drone's two cores: measured here, a
`bench graph --rate 1` on a cold cache aggregated 32 of 60 frames, on a warm one 59. The nodes
warm their per-frame kernels before they say they are ready, but the refiner's and the query
server's compile while a flight streams. This command runs the real code paths of every node
on the simulator's tiny flight (a few seconds to make): regions and features, the per-view
step of the method and of VALA (the two observation kernels), the refiner's first and later
passes as the refiner calls them, and a ground-station query with a heatmap. ``make setup``
runs it; run it after ``pip install`` on a drone, before the first flight.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "warm-up", help="compile the nodes' kernels once after an install (numba's cache), before a first flight"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="olsplat_warm_up_") as work:
        stages = warm_up_all(Path(work))
    for stage, seconds in stages.items():
        print(f"  {stage:<36} {seconds:6.1f} s")
    print(f"kernels compiled (or found in numba's cache) in {time.perf_counter() - start:.1f} s")
    return 0


def warm_up_all(work: Path) -> dict[str, float]:
    """Run every node's kernels once on the tiny flight made in ``work``; returns seconds per stage."""
    from olsplat_sim.make import make_dataset
    from olsplat_sim.presets import PRESETS

    from ..encoders.spec import encoder_from_spec
    from ..method import add_view, named_method, warm_up
    from ..method.live import LiveMap
    from ..nodes.region_encoder import warm_up as warm_up_regions
    from ..pipeline import Scene
    from ..pipeline.scene_folder import view_features
    from ..query.answer import answer_query
    from ..query.heatmap import FeatureImages
    from ..query.localize import VoxelIndex, default_cluster_radius
    from ..query.winners import gather_verdicts
    from ..regions import RegionConfig
    from ..scene import read_ply
    from ..storage import LanguageMap, ObservationStore

    stages: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        stages[stage] = now - clock
        clock = now

    make_dataset(PRESETS["tiny"], 0, work / "scene", log=lambda *_: None)
    scene = Scene.open(work / "scene")
    gaussians = read_ply(scene.ply)
    encoder = encoder_from_spec()
    lap("tiny flight made")
    warm_up_regions(encoder, RegionConfig(level_counts=(240,), work_scale=0.5))  # the node's defaults
    views = [view_features(scene, camera, encoder) for camera in scene.cameras[:3]]
    lap("regions and features")
    language_map = None
    for name in ("outlangsplat", "vala"):
        method = named_method(name)
        warm_up(gaussians, method)  # the accumulator's own warm-up: what it compiles is cached now, not at its start
        store = ObservationStore(work / name, len(gaussians), writer=True)
        for camera, (label_maps, bank) in zip(scene.cameras[:2], views[:2], strict=True):
            add_view(gaussians, camera, label_maps, bank, method, store)
        # the refiner's calls: a first exact pass, a fold of a new view, the final exact pass
        live = LiveMap(store)
        live.update(method.aggregation, exact=True)
        add_view(gaussians, scene.cameras[2], *views[2], method, store)
        live.update(method.aggregation, exact=False)
        if language_map is None and live.features is not None and live.observed is not None:
            language_map = LanguageMap(live.features, live.observed, encoder.name)
        live.update(method.aggregation, exact=True)
        lap(f"per-view step + refiner, {name}")
    if language_map is None:
        raise RuntimeError(f"{scene.folder}: the tiny flight's views observed no Gaussian")
    images = FeatureImages(64 * 2**20)
    for _ in range(2):  # the first renders the view, the second is answered from the cache
        answer_query(language_map, gaussians, encoder, "road", camera=scene.cameras[0], images=images, image_key=0)
    radius = default_cluster_radius(gaussians.means)  # as the query server clusters: through its voxel index
    answer_query(
        language_map,
        gaussians,
        encoder,
        "road",
        cluster_radius=radius,
        voxel_index=VoxelIndex.build(gaussians.means, radius),
    )
    # a codebook map's query (drone launch files: refiner codebook > 0) gathers the centres'
    # verdicts per Gaussian: the same argument types as QueryFeatures.winners passes
    gather_verdicts(np.zeros(2, np.bool_), np.zeros(4, np.int32), np.zeros(0, np.bool_))
    gather_verdicts(np.zeros(2, np.bool_), np.zeros(4, np.int32), np.zeros(4, np.bool_))
    lap("query, relevance and heatmap")
    return stages
