"""``olsplat render``: one view of a map to an npz (and optionally a picture)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "render",
        help="render one view of a Gaussian map",
        description="Render one view; the npz holds rgb [H,W,3] float32 0..1, alpha [H,W], depth [H,W] "
        "(camera z, metres), topk_ids [H,W,32] int32 (-1 padded) and topk_weights [H,W,32] float32.",
    )
    parser.add_argument("--ply", required=True, type=Path, help="INRIA-layout Gaussian PLY")
    parser.add_argument("--cameras", required=True, type=Path, help="COLMAP model folder or transforms.json")
    parser.add_argument("--view", required=True, help="image name (or file name / stem) or index")
    parser.add_argument("--out", required=True, type=Path, help="output .npz")
    parser.add_argument("--png", type=Path, help="also write the RGB picture here")
    parser.add_argument(
        "--allow-nonfinite",
        action="store_true",
        help="render although some Gaussians hold NaN/inf (they are skipped; Top-K ids still index the file)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..durable import write_atomic
    from ..errors import OlsplatInputError
    from ..outputs import output_file
    from ..raster import rasterize
    from ..scene import read_cameras, read_ply, select_view
    from ..viz import rgb_to_bgr8, write_png

    out = output_file(args.out, ".npz")  # the name numpy would write, and the one printed
    png = output_file(args.png, ".png", "--png") if args.png else None
    gaussians = read_ply(args.ply, on_nonfinite="keep" if args.allow_nonfinite else "error")
    camera = select_view(read_cameras(args.cameras), args.view)
    result = rasterize(gaussians, camera)
    if result.n_visible == 0:
        raise OlsplatInputError(
            f"no Gaussian of {args.ply} is in view of camera {camera.name}: are the map and the cameras "
            f"({args.cameras}) of the same scene, in the same coordinate frame?"
        )
    topk_ids, topk_weights = result.topk_ids, result.topk_weights
    assert topk_ids is not None and topk_weights is not None  # kept by default (want_topk)
    write_atomic(  # whole or absent
        out,
        lambda f: np.savez_compressed(
            f, rgb=result.rgb, alpha=result.alpha, depth=result.depth, topk_ids=topk_ids, topk_weights=topk_weights
        ),
    )
    if png is not None:
        write_png(png, rgb_to_bgr8(result.rgb))
    written = f"{out}" + (f" and {png}" if png is not None else "")
    print(f"rendered {camera.name} ({camera.width}x{camera.height}, {result.n_visible} Gaussians in view) -> {written}")
    return 0
