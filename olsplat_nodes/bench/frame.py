"""``olsplat bench frame``: the seconds of every stage one camera frame goes through, in one
process, as the graph's nodes run them (the region encoder's regions and features, the
accumulator's Top-K rasterization, observations, store segment and photo), with the nodes'
thread setting (``--threads``, default 1 as in the launch files) and their region levels
(``--levels``, default the finest only, as the region encoder makes them) and encoder
(``--encoders``, default the region encoder's).

The first view warms up (numba compilation, page faults) and is not counted; the figures are
means over the next ``--views``. ``--json FILE`` writes ``{stage: seconds}`` plus ``total``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ..tools.method_names import DEFAULT_ENCODER

STAGES = ("regions", "features", "rasterize", "observe", "store", "photo")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("frame", help="seconds per stage of one frame through the graph's core")
    parser.add_argument("--scene", required=True, type=Path, help="a scene folder (map/, sparse/0, images/)")
    parser.add_argument("--views", type=int, default=8, help="views measured after the warm-up one")
    parser.add_argument("--threads", type=int, default=1, help="numba, onnxruntime and OpenCV threads")
    parser.add_argument("--levels", default="240", help="regions per level at 640x480, comma-separated")
    parser.add_argument(
        "--encoders", default=DEFAULT_ENCODER, help=f"encoder spec as for olsplat encode (default {DEFAULT_ENCODER})"
    )
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import cv2
    import numba

    from ..aggregate import observe_view, stack_levels
    from ..encoders import encode_regions
    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..method import named_method
    from ..pipeline import Scene
    from ..raster import rasterize
    from ..regions import RegionConfig, propose_regions
    from ..scene import read_ply
    from ..storage import ObservationStore, save_view

    if args.views < 1 or args.threads < 1:
        raise OlsplatInputError(f"--views and --threads must be positive, got {args.views}, {args.threads}")
    try:
        region_config = RegionConfig(level_counts=tuple(int(x) for x in args.levels.split(",")))
    except ValueError as exc:
        raise OlsplatInputError(f"--levels: {exc}") from None
    scene = Scene.open(args.scene)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    cv2.setNumThreads(args.threads)
    encoder = encoder_from_spec(args.encoders, threads=args.threads)
    method = named_method("outlangsplat")
    gaussians = read_ply(scene.ply)
    cameras = scene.cameras[: args.views + 1]
    seconds: dict[str, list[float]] = {stage: [] for stage in STAGES}
    with tempfile.TemporaryDirectory() as tmp:
        store = ObservationStore(Path(tmp) / "store", len(gaussians), writer=True)
        for i, camera in enumerate(cameras):
            image = scene.image(camera)
            clock = [time.perf_counter()]
            levels = propose_regions(image, region_config)
            clock.append(time.perf_counter())
            bank = encode_regions(image, levels, encoder)
            clock.append(time.perf_counter())
            rendered = rasterize(gaussians, camera, method.raster, want_rgb=False)  # as the accumulator
            clock.append(time.perf_counter())
            assert rendered.topk_ids is not None and rendered.topk_weights is not None
            slots, stacked = stack_levels(levels.label_maps, bank.features)
            observations = observe_view(
                rendered.topk_ids, rendered.topk_weights, slots, len(gaussians), method.aggregation
            )
            clock.append(time.perf_counter())
            store.append(camera.name, observations, stacked)
            clock.append(time.perf_counter())
            save_view(Path(tmp) / "views", i, camera, image)
            clock.append(time.perf_counter())
            if i > 0:  # the first view warms up
                for stage, spent in zip(STAGES, np.diff(clock), strict=True):
                    seconds[stage].append(float(spent))
    means = {stage: round(float(np.mean(values)), 4) for stage, values in seconds.items()}
    total = round(sum(means.values()), 4)
    c = cameras[0]
    print(
        f"{scene.folder.name}: {len(gaussians):,} Gaussians, {c.width}x{c.height}, {len(cameras) - 1} views, "
        f"{args.threads} thread(s), levels {list(region_config.level_counts)}"
    )
    for stage in STAGES:
        print(f"  {stage:10s} {means[stage]:6.3f} s")
    print(f"  {'total':10s} {total:6.3f} s per frame")
    if args.json:
        args.json.write_text(json.dumps({**means, "total": total}, indent=1))
    return 0
