"""``olsplat bench raster``: seconds per view, throughput, and the speed-up over the reference.

Scenes are generated towns (``olsplat_sim.generate_scene``) of 150 m x 150 m seen by an oblique
(45 degree) camera 90 m up and 90 m out, 70 degree horizontal field of view, so that nearly
the whole map is in view: the hardest case for one view. Each figure is the median of
``--repeat`` renders after one warm-up render (numba compilation excluded).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..scene import Camera, Gaussians


def bench_camera(width: int, height: int) -> Camera:
    from ..scene import Camera, intrinsics, look_at

    focal = 0.5 * width / np.tan(np.radians(35.0))
    pose = look_at([0.0, -90.0, 90.0], [0.0, 0.0, 0.0], (0.0, 0.0, 1.0))
    return Camera(f"bench_{width}x{height}", width, height, intrinsics(focal, focal, width / 2, height / 2), pose)


def _median_render(gaussians: Gaussians, camera: Camera, want_topk: bool, repeat: int):
    """(median seconds, the last result). Like a streaming node, each render's outputs are
    released before the next one, so the allocator recycles the pages (a first render in a
    process also pays ~0.4 s of page faults for the 177 MB of Top-K outputs at 960x720)."""
    from ..raster import rasterize

    result = rasterize(gaussians, camera, want_topk=want_topk)
    runs = []
    for _ in range(repeat):
        del result
        start = time.perf_counter()
        result = rasterize(gaussians, camera, want_topk=want_topk)
        runs.append(time.perf_counter() - start)
    return statistics.median(runs), result


def reference_speedup(threads: int) -> tuple[float, float]:
    """(reference seconds, fast seconds) on a scene small enough for the reference."""
    from olsplat_sim import generate_scene

    from ..raster._reference import rasterize_reference

    gaussians = generate_scene(3_000, size_m=150.0, seed=1).gaussians
    camera = bench_camera(64, 48)
    start = time.perf_counter()
    rasterize_reference(gaussians, camera)
    reference = time.perf_counter() - start
    fast, _ = _median_render(gaussians, camera, True, 20)
    return reference, fast


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("raster", help="rasterizer speed per view and throughput")
    parser.add_argument(
        "--gaussians", type=int, nargs="+", default=[100_000, 1_000_000], help="map sizes (generated towns)"
    )
    parser.add_argument(
        "--sizes", nargs="+", default=["640x480", "960x720", "1280x960"], help="image sizes, WIDTHxHEIGHT"
    )
    parser.add_argument("--repeat", type=int, default=5, help="renders per case (the median is printed)")
    parser.add_argument("--skip-reference", action="store_true", help="skip the slow reference comparison")
    parser.add_argument("--json", type=Path, help="also write one row per case here")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import numba

    from olsplat_sim import generate_scene

    threads = numba.get_num_threads()
    print(
        f"machine: {platform.processor() or platform.machine()}, {threads} numba threads, python "
        f"{platform.python_version()}"
    )
    print(
        f"{'gaussians':>10} {'image':>9} {'in view':>9} {'tiles x G':>10} {'s/view':>7} {'s/view':>8} "
        f"{'evals':>6} {'Mevals/s':>9} {'list':>7} {'Mpairs/s':>9} {'project':>8} {'bin':>6} {'compos.':>8}"
    )
    print(
        f"{'':>10} {'':>9} {'':>9} {'':>10} {'top-K':>7} {'no top-K':>8} {'(M)':>6} {'per core':>9} "
        f"{'pairs(M)':>7} {'per core':>9} {'(s)':>8} {'(s)':>6} {'(s)':>8}"
    )
    rows: list[dict] = []
    for n in args.gaussians:
        gaussians = generate_scene(n, size_m=150.0, seed=0).gaussians
        for size in args.sizes:
            width, height = (int(v) for v in size.split("x"))
            camera = bench_camera(width, height)
            with_topk, result = _median_render(gaussians, camera, True, args.repeat)
            without_topk, _ = _median_render(gaussians, camera, False, args.repeat)
            per_core = with_topk * threads * 1e6
            stages = result.seconds
            print(
                f"{len(gaussians):>10,} {size:>9} {result.n_visible:>9,} {result.n_intersections:>10,} "
                f"{with_topk:>7.3f} {without_topk:>8.3f} {result.n_evaluations / 1e6:>6.1f} "
                f"{result.n_evaluations / per_core:>9.1f} {result.n_tile_pairs / 1e6:>7.1f} "
                f"{result.n_tile_pairs / per_core:>9.1f} "
                f"{stages['project']:>8.3f} {stages['bin']:>6.3f} {stages['composite']:>8.3f}"
            )
            rows.append(
                {
                    "gaussians": len(gaussians),
                    "width": width,
                    "height": height,
                    "in_view": result.n_visible,
                    "s_per_view_topk": with_topk,
                    "s_per_view": without_topk,
                    "evaluations": result.n_evaluations,
                    "evals_per_s_per_core": result.n_evaluations / (with_topk * threads),
                    "threads": threads,
                    "stages_s": stages,
                }
            )
    if not args.skip_reference:
        reference, fast = reference_speedup(threads)
        print(
            f"reference (numpy, 64x48, 3,000 Gaussians): {reference:.2f} s; fast: {fast * 1e3:.2f} ms; speed-up "
            f"{reference / fast:,.0f}x"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print("evals: Gaussian-pixel pairs whose sigma was computed (each Gaussian only over its alpha >= 1/255 box);")
    print("list pairs: the pairs a per-pixel loop over the tile lists (gsplat's loop) tests for the same image;")
    print("  a Gaussian is listed in the tiles of its 3-sigma square that its alpha >= 1/255 box reaches")
    print("  (until 2026-11-27 every tile of the square, as gsplat lists it: more pairs);")
    print("rates per core divide by (s/view with top-K) x threads; stage times are of the median top-K run.")
    return 0
