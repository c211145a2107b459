"""The map coverage of flights' views (``method.coverage``): the figures ``min_coverage`` and
``min_height_m`` were chosen from.

    python -m olsplat_nodes.bench.coverage --map MAP.ply SOURCE [SOURCE ...]

A SOURCE is a replay log or scene folder (``source_kind: replay``) or a folder of geotagged
photos (``exif_folder``); each view is rendered as the accumulator renders it (the default
method's Top-K) and its coverage and height above the map's ground are printed, then a summary
line per source.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def coverage_of_source(map_ply: Path, source: Path) -> list[tuple[str, float, float]]:
    """(view name, coverage, height) of every frame of ``source`` over the map ``map_ply``."""
    from ..method import named_method
    from ..method.coverage import map_coverage
    from ..raster import rasterize
    from ..scene import read_ply
    from ..sources import open_source

    gaussians = read_ply(map_ply)
    method = named_method("outlangsplat")
    kind = "replay" if source.suffix == ".mcap" or (source / "sparse").is_dir() else "exif_folder"
    rows = []
    with open_source({"source_kind": kind, "source": str(source), "fast": True}) as frames:
        for frame in frames:
            rendered = rasterize(gaussians, frame.camera, method.raster)
            assert rendered.topk_ids is not None
            seen = map_coverage(rendered.alpha, rendered.topk_ids, gaussians.means[:, 2], frame.camera.center[2])
            rows.append((frame.name, seen.coverage, seen.height_m))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--map", required=True, type=Path, help="the prior map (INRIA PLY)")
    parser.add_argument("sources", nargs="+", type=Path)
    args = parser.parse_args(argv)
    for source in args.sources:
        rows = coverage_of_source(args.map, source)
        for name, coverage, height in rows:
            print(f"{source.name}/{name}: coverage {coverage:.3f}, height {height:.1f}")
        cov = np.array([r[1] for r in rows])
        heights = np.array([r[2] for r in rows])
        print(
            f"== {source} over {args.map}: {len(rows)} views, coverage min {cov.min():.3f} median "
            f"{np.median(cov):.3f} max {cov.max():.3f}; height min {np.nanmin(heights, initial=np.inf):.1f} "
            f"median {np.nanmedian(heights) if np.isfinite(heights).any() else float('nan'):.1f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
