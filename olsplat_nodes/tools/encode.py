"""``olsplat encode``: regions and region features for every view of a scene folder.

Writes ``SCENE/cache/encode/<encoder>/<view>.npz`` per view (``encoders.bank.encode_cache_file``:
one folder per encoder, ``regions`` without one) with ``label_maps`` [L, H, W] int32 (coarse to
fine) and, when encoders are given, ``features_<l>`` [R_l, D] float16 per level (unit rows)
plus the ``encoder`` name; ``--png`` also writes ``SCENE/cache/encode/<view>_regions.png``,
the view with each level's region boundaries drawn over it. Views already in the cache are
skipped unless ``--force``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import OlsplatInputError
from .method_names import DEFAULT_ENCODER


def level_counts(levels: int) -> tuple[int, ...]:
    """Region counts per level at 640x480 for ``levels`` levels, finest 240, x3.2 apart."""
    if not 1 <= levels <= 6:
        raise OlsplatInputError(f"--levels must be 1..6, got {levels}")
    return tuple(max(2, int(round(240 / 3.2 ** (levels - 1 - i)))) for i in range(levels))


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("encode", help="multi-level regions and region features for a scene's views")
    parser.add_argument("--scene", required=True, type=Path, help="folder with images/ (and sparse/0/)")
    parser.add_argument(
        "--encoders",
        default=DEFAULT_ENCODER,
        help="comma-separated encoders: folders made by 'olsplat export-clip' or names of shipped encoders "
        f"(olsplat-cnn64, olsplat-vit48; default {DEFAULT_ENCODER}); 'shipped': both shipped encoders fused; "
        "'none': regions only",
    )
    parser.add_argument("--weights", help="comma-separated fusion weights (default: equal; the paper: 0.6,0.4)")
    parser.add_argument(
        "--fusion",
        choices=["concat", "sum"],
        default="concat",
        help="concat: stack the weighted features (encoders trained apart); sum: add them (one shared space)",
    )
    parser.add_argument("--levels", type=int, default=3, help="region levels (default 3)")
    parser.add_argument("--png", action="store_true", help="also write region overlays")
    parser.add_argument("--limit", type=int, help="only the first N views")
    parser.add_argument("--force", action="store_true", help="recompute views already in the cache")
    parser.set_defaults(run=run)


def _views(scene: Path) -> list[Path]:
    images = scene / "images"
    if not images.is_dir():
        raise OlsplatInputError(f"{scene}: no images/ folder")
    files = sorted(p for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if not files:
        raise OlsplatInputError(f"{images}: no .jpg or .png images")
    return files


def _overlay(image_rgb: np.ndarray, label_maps: np.ndarray) -> np.ndarray:
    """BGR picture: one panel per level, region boundaries in yellow."""
    import cv2

    panels = []
    for level, labels in enumerate(label_maps):
        panel = np.ascontiguousarray(image_rgb[..., ::-1])
        edge = np.zeros(labels.shape, bool)
        edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
        edge[1:, :] |= labels[1:, :] != labels[:-1, :]
        panel[edge] = (0, 230, 255)
        cv2.putText(
            panel,
            f"level {level}: {labels.max() + 1} regions",
            (8, 22),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (255, 255, 255),
            2,
        )
        panels.append(panel)
    return np.concatenate(panels, axis=1)


def _cached_labels(cache_file: Path, key: str, encoder_name: str | None) -> np.ndarray | None:
    """The label maps of a cache file made from this image with these settings (and this
    encoder, when one is used), else None (made again)."""
    if not cache_file.exists():
        return None
    with np.load(cache_file) as data:
        if "regions" not in data or str(data["regions"]) != key:
            return None
        if encoder_name is not None and ("encoder" not in data or str(data["encoder"]) != encoder_name):
            return None
        return data["label_maps"]


def run(args: argparse.Namespace) -> int:
    import cv2
    from tqdm import tqdm

    from ..encoders import encode_regions
    from ..encoders.bank import encode_cache_file, save_bank, view_key
    from ..encoders.spec import encoder_from_spec
    from ..regions import RegionConfig, propose_regions
    from ..viz import write_png

    config = RegionConfig(level_counts=level_counts(args.levels))
    views = _views(args.scene)[: args.limit]  # checks the scene before anything is written in it
    encoder = None if args.encoders == "none" else encoder_from_spec(args.encoders, args.weights, args.fusion)
    cache = args.scene / "cache" / "encode"
    cache.mkdir(parents=True, exist_ok=True)
    encoded = 0
    for path in tqdm(views, desc="encode", unit="view"):
        target = encode_cache_file(args.scene, path.stem, encoder.name if encoder is not None else None)
        key = view_key(path, repr(config))
        labels = None if args.force else _cached_labels(target, key, encoder.name if encoder is not None else None)
        if labels is not None and not args.png:
            continue
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise OlsplatInputError(f"{path}: not a readable image")
        image = np.ascontiguousarray(bgr[..., ::-1])
        if labels is None:
            levels = propose_regions(image, config)
            bank = encode_regions(image, levels, encoder) if encoder is not None else None
            save_bank(target, levels.label_maps, bank, key)
            labels = levels.label_maps
            encoded += 1
        if args.png:  # also for views taken from the cache: the pictures are what was asked for
            write_png(cache / f"{path.stem}_regions.png", _overlay(image, labels))
    print(f"{len(views)} views ({encoded} encoded, {len(views) - encoded} from the cache) -> {target.parent}")
    return 0
