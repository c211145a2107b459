"""``olsplat encode``: regions and region features for every view of a scene folder.

Writes ``SCENE/cache/encode/<view>.npz`` per view with ``label_maps`` [L, H, W] int32 (coarse to
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
        default="shipped",
        help="comma-separated encoders: folders made by 'olsplat export-clip' or names of shipped encoders "
        "(olsplat-cnn64, olsplat-vit48); 'shipped' (default): both shipped encoders fused; 'none': regions only",
    )
    parser.add_argument("--weights", help="comma-separated fusion weights (default: equal; the paper: 0.6,0.4)")
    parser.add_argument("--fusion", choices=["concat", "sum"], default="concat")
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


def _same_regions(cache_file: Path, regions: str) -> bool:
    """Whether a cache file was made with these region settings (else it is made again)."""
    with np.load(cache_file) as data:
        return "regions" in data and str(data["regions"]) == regions


def run(args: argparse.Namespace) -> int:
    import cv2
    from tqdm import tqdm

    from ..encoders import encode_regions
    from ..encoders.bank import save_bank
    from ..regions import RegionConfig, propose_regions

    config = RegionConfig(level_counts=level_counts(args.levels))
    from ..encoders.spec import encoder_from_spec

    encoder = None if args.encoders == "none" else encoder_from_spec(args.encoders, args.weights, args.fusion)
    cache = args.scene / "cache" / "encode"
    cache.mkdir(parents=True, exist_ok=True)
    views = _views(args.scene)[: args.limit]
    for path in tqdm(views, desc="encode", unit="view"):
        target = cache / f"{path.stem}.npz"
        if target.exists() and not args.force and _same_regions(target, repr(config)):
            continue
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise OlsplatInputError(f"{path}: not a readable image")
        image = np.ascontiguousarray(bgr[..., ::-1])
        levels = propose_regions(image, config)
        bank = encode_regions(image, levels, encoder) if encoder is not None else None
        save_bank(target, levels.label_maps, bank, repr(config))
        if args.png:
            cv2.imwrite(str(cache / f"{path.stem}_regions.png"), _overlay(image, levels.label_maps))
    print(f"{len(views)} views -> {cache}")
    return 0
