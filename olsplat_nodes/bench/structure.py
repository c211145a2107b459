"""``olsplat bench structure``: the 3D branch's cost on a scene.

Once per map: opacity filter + voxel downsampling, then the point features (geometric
descriptors; with ``--minkunet``, also a MinkUNet: "shipped" = the packaged self-supervised
one, "random" = random weights of SegContrast's full size, or a checkpoint file).
Per view: visibility + region pooling, the h_theta update and the fusion (region features
from the scene's cache; the view's depth from the rasterizer, not timed here).
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("structure", help="3D branch: seconds once per map and per view")
    parser.add_argument("--scene", required=True, type=Path, help="a scene folder")
    parser.add_argument("--views", type=int, default=10, help="views to time (default 10)")
    parser.add_argument(
        "--minkunet",
        nargs="?",
        const="shipped",
        help="also time a MinkUNet over the point set: shipped (default), random (SegContrast's full size) or a file",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..encoders.spec import encoder_from_spec
    from ..pipeline import Scene, view_features
    from ..raster import rasterize
    from ..scene import read_ply
    from ..structure.branch import StructuralBranch, minkunet_path
    from ..structure.descriptors import geometric_descriptors
    from ..structure.minkunet import MinkUNet, load_minkunet, minkunet_point_features
    from ..structure.points import structural_points

    scene = Scene.open(args.scene)
    gaussians = read_ply(scene.ply)
    centres = np.array([c.center for c in scene.cameras])
    t0 = time.perf_counter()
    points = structural_points(gaussians)
    t1 = time.perf_counter()
    descriptors = geometric_descriptors(points, centres)
    t2 = time.perf_counter()
    print(
        f"scene {scene.folder.name}: {len(gaussians):,} Gaussians -> {len(points):,} points (voxel {points.voxel:.3f})"
    )
    print(
        f"  once per map: points {t1 - t0:.1f} s, geometric descriptors {t2 - t1:.1f} s ({descriptors.shape[1]} dims)"
    )
    if args.minkunet:
        model = MinkUNet(4) if args.minkunet == "random" else load_minkunet(minkunet_path(args.minkunet) or "")
        t0 = time.perf_counter()
        features = minkunet_point_features(model, points, centres)
        print(
            f"  once per map: MinkUNet ({args.minkunet}, {sum(p.numel() for p in model.parameters()) / 1e6:.2f} M "
            f"parameters) {time.perf_counter() - t0:.1f} s ({features.shape[1]} dims, {len(points):,} points)"
        )
    branch = StructuralBranch(points, descriptors)
    encoder = encoder_from_spec()
    seconds = []
    for camera in scene.cameras[: args.views]:
        label_maps, bank = view_features(scene, camera, encoder)
        depth = rasterize(gaussians, camera, want_topk=False).depth
        t0 = time.perf_counter()
        branch.fuse_view(camera, depth, label_maps, bank)
        seconds.append(time.perf_counter() - t0)
    print(
        f"  per view: {np.mean(seconds):.3f} s (pooling + h_theta update + fusion; "
        f"p95 {np.percentile(seconds, 95):.3f}); "
        f"distillation loss first/last view {branch.losses[0]:.3f}/{branch.losses[-1]:.3f}"
    )
    print(f"  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0
