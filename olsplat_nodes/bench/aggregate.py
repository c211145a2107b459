"""``olsplat bench aggregate``: seconds per view and peak memory of the aggregation on a scene.

Per view: rasterize (adaptive Top-K), observe (pixel quality, mixtures), append (fsync'd store
segment). Region features come from the scene's encode cache (``olsplat encode``; computed and
cached first when missing, not timed here: ``olsplat bench encode`` times them). Then one full
refinement over everything, the language map write, the store's size on disk and the process's
peak RSS.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("aggregate", help="aggregation seconds per view, refinement, store size, peak RSS")
    parser.add_argument("--scene", required=True, type=Path, help="a scene folder")
    parser.add_argument("--method", default="outlangsplat", help="the method to time")
    parser.add_argument("--views", type=int, help="use the first N views (default: all)")
    parser.set_defaults(run=run)


def _size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 1e6


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..encoders.spec import encoder_from_spec
    from ..method import add_view, named_method
    from ..pipeline import Scene, view_features
    from ..raster import rasterize
    from ..scene import read_ply
    from ..storage import ObservationStore
    from ..storage.snapshot import LanguageMap

    scene = Scene.open(args.scene)
    chosen = named_method(args.method)
    encoder = encoder_from_spec()
    cameras = scene.cameras[: args.views]
    gaussians = read_ply(scene.ply)
    features = [view_features(scene, c, encoder) for c in tqdm(cameras, desc="features (cached)", unit="view")]
    rasterize(gaussians, cameras[0], chosen.raster)  # warm-up: numba compile, page faults
    times: dict[str, list[float]] = {"rasterize": [], "observe": [], "append": []}
    kept = []
    with tempfile.TemporaryDirectory() as tmp:
        store = ObservationStore(Path(tmp) / "store", len(gaussians), writer=True)
        for camera, (label_maps, bank) in zip(cameras, features, strict=True):
            stages = add_view(gaussians, camera, label_maps, bank, chosen, store)
            for key in times:
                times[key].append(stages[key])
            kept.append(stages["kept"])
        t0 = time.perf_counter()
        refined, observed = store.refine(None, chosen.aggregation, only_touched=False)
        refine_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        LanguageMap.from_features(refined, observed, encoder.name).save(Path(tmp) / "language_map.npz")
        save_seconds = time.perf_counter() - t0
        store_mb, map_mb = _size_mb(Path(tmp) / "store"), (Path(tmp) / "language_map.npz").stat().st_size / 1e6
        shutil.rmtree(Path(tmp) / "store")
    c = cameras[0]
    per_view = sum(np.mean(v) for v in times.values())
    print(
        f"scene {scene.folder.name}: {len(gaussians):,} Gaussians, {len(cameras)} views of {c.width}x{c.height}, "
        f"method {args.method}"
    )
    for key, values in times.items():
        print(f"  {key:10s} {np.mean(values):.3f} s/view (p95 {np.percentile(values, 95):.3f})")
    print(f"  per view   {per_view:.3f} s ({1 / per_view:.2f} views/s); {np.mean(kept):,.0f} Gaussians kept per view")
    print(
        f"  refine     {refine_seconds:.1f} s for all {len(cameras)} views ({int(observed.sum()):,} Gaussians observed)"
    )
    print(
        f"  map write  {save_seconds:.2f} s; language map {map_mb:.0f} MB; store {store_mb:.0f} MB "
        f"({store_mb / len(cameras):.1f} MB/view)"
    )
    print(f"  peak RSS   {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0
