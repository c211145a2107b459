"""``olsplat bench encode``: seconds per 640x480 view for regions and for region features.

Encoders: the folders given with ``--encoders``, and with ``--vit-b32`` a CLIP ViT-B/32 of
random weights exported on the fly (the size of RemoteCLIP/GeoRSCLIP: what real encoders
cost on this machine). The view is a frame of ``--scene`` or, without one, a render of a
generated town.
"""

from __future__ import annotations

import argparse
import gzip
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError


def _frame(scene: Path | None) -> np.ndarray:
    import cv2

    if scene is not None:
        files = sorted((scene / "images").glob("*.jpg"))
        bgr = cv2.imread(str(files[len(files) // 2])) if files else None
        if bgr is None:
            raise OlsplatInputError(f"{scene / 'images'}: no readable JPEG frame")
        return cv2.resize(bgr, (640, 480))[..., ::-1].copy()
    from olsplat_sim import generate_scene

    from ..raster import rasterize
    from ..scene import Camera, intrinsics, look_at

    town = generate_scene(300_000, 130.0, 0)
    camera = Camera("bench", 640, 480, intrinsics(686.0, 686.0, 320, 240), look_at([0, -50, 70], [0, 0, 0]))
    return (np.clip(rasterize(town.gaussians, camera, want_topk=False).rgb, 0, 1) * 255).astype(np.uint8)


def vit_b32_random(folder: Path) -> Path:
    """Export a ViT-B/32-sized CLIP with random weights (and a synthetic 49,408-token vocabulary)."""
    import torch

    from ..encoders.clip_model import ClipConfig, ClipModel
    from ..encoders.export import export_model
    from ..encoders.tokenizer import CLIP_MERGES, bytes_to_unicode

    symbols = list(bytes_to_unicode().values())
    merges = [f"{a} {b}" for a in symbols for b in symbols][:CLIP_MERGES]  # right size, arbitrary content
    vocab = folder / "synthetic_merges.txt.gz"
    with gzip.open(vocab, "wt", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "\n".join(merges) + "\n")
    torch.manual_seed(0)
    config = ClipConfig(512, 224, 32, 768, 12, 77, 49408, 512, 12)
    return export_model(ClipModel(config), vocab, folder / "vit-b32-random", "vit-b32-random")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("encode", help="seconds per view for regions and region features")
    parser.add_argument("--scene", type=Path, help="take the view from this scene's images/")
    parser.add_argument("--encoders", help="comma-separated encoder folders")
    parser.add_argument(
        "--vit-b32", action="store_true", help="also time a random-weight ViT-B/32 (exports ~600 MB to a temp folder)"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..encoders import encode_regions
    from ..encoders.onnx_encoder import OnnxEncoder
    from ..regions import propose_regions

    image = _frame(args.scene)
    start = time.perf_counter()
    levels = propose_regions(image)
    print(
        f"regions: {time.perf_counter() - start:.2f} s for {sum(levels.counts)} regions in {levels.n_levels} levels "
        f"{levels.counts}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        folders = [Path(p) for p in args.encoders.split(",")] if args.encoders else []
        if args.vit_b32:
            start = time.perf_counter()
            folders.append(vit_b32_random(Path(tmp)))
            print(f"exported a random ViT-B/32 in {time.perf_counter() - start:.0f} s")
        for folder in folders:
            encoder = OnnxEncoder(folder)
            encode_regions(image, levels, encoder)  # warm-up
            start = time.perf_counter()
            encode_regions(image, levels, encoder)
            seconds = time.perf_counter() - start
            print(
                f"features, {encoder.name} ({encoder.dim}-d, {encoder.input_size} px crops): {seconds:.2f} s per view "
                f"({seconds / sum(levels.counts) * 1e3:.1f} ms per region)"
            )
    return 0
