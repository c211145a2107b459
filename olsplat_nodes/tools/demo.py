"""``olsplat demo``: the main job of ``make demo``.

For now: generate a town, save it as a user would have it (INRIA PLY + COLMAP model), read
both back through the same readers ``olsplat render`` uses, render a small UAV flight and
write RGB, depth and Top-K pictures. Later issues re-point it at the full pipeline.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ..raster import rasterize
from ..scene import Camera, intrinsics, look_at, read_cameras, read_ply, write_colmap, write_ply
from ..viz import colorize, rgb_to_bgr8, topk_panel, write_png


def flight_cameras(size_m: float, altitude_m: float = 80.0, width: int = 960, height: int = 720) -> list[Camera]:
    """A nadir view over the centre and four oblique (45 degree) views from the sides."""
    focal = 0.5 * width / np.tan(np.radians(35.0))  # 70 degree horizontal field of view
    K = intrinsics(focal, focal, width / 2, height / 2)
    cameras = [Camera("nadir.png", width, height, K, look_at([0, 0, altitude_m], [0, 0, 0], (0, 1, 0)))]
    for i, azimuth in enumerate(np.radians([270, 0, 90, 180])):
        eye = np.array([np.cos(azimuth) * altitude_m, np.sin(azimuth) * altitude_m, altitude_m])
        cameras.append(Camera(f"oblique_{i}.png", width, height, K, look_at(eye, [0, 0, 0], (0, 0, 1))))
    return cameras


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("demo", help="generate a town, render a flight, write pictures")
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (default: out)")
    parser.add_argument("--gaussians", type=int, default=300_000, help="size of the generated map")
    parser.add_argument("--seed", type=int, default=0)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from olsplat_sim import generate_scene

    out: Path = args.out
    (out / "scene").mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    town = generate_scene(args.gaussians, size_m=150.0, seed=args.seed)
    write_ply(out / "scene" / "town.ply", town.gaussians)
    write_colmap(out / "scene" / "sparse" / "0", flight_cameras(town.size_m))
    print(f"generated {len(town.gaussians):,} Gaussians in {time.perf_counter() - start:.1f} s -> {out / 'scene'}")

    gaussians = read_ply(out / "scene" / "town.ply")
    cameras = read_cameras(out / "scene")
    rasterize(gaussians, cameras[0])  # compile (or load the cache) before timing
    for camera in cameras:
        start = time.perf_counter()
        result = rasterize(gaussians, camera)
        seconds = time.perf_counter() - start
        stem = out / Path(camera.name).stem
        write_png(f"{stem}_rgb.png", rgb_to_bgr8(result.rgb))
        write_png(f"{stem}_depth.png", colorize(result.depth, result.alpha > 0.5))
        write_png(f"{stem}_topk.png", topk_panel(result.topk_ids, result.topk_weights))
        print(
            f"{camera.name:15s} {camera.width}x{camera.height}  {seconds:.3f} s  "
            f"{result.n_visible:,} Gaussians in view  mean K {np.mean((result.topk_ids >= 0).sum(-1)):.1f}"
        )
    print(f"pictures in {out}/ (*_rgb.png, *_depth.png, *_topk.png)")
    return 0
