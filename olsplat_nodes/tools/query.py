"""``olsplat query``: one text against a language map: heatmap, mask and located instances."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("query", help="ask a language map for a text: heatmap, mask, instances")
    parser.add_argument("--map", required=True, type=Path, help="language_map.npz (olsplat aggregate)")
    parser.add_argument("--scene", required=True, type=Path, help="the scene the map was made from")
    parser.add_argument("text", help='what to find, e.g. "red roof buildings"')
    parser.add_argument("--view", help="view to render (name or index; default: the first)")
    parser.add_argument("--negatives", help="comma-separated texts to beat (default: the scene's other queries, else canonical)")
    parser.add_argument("--out", type=Path, help="write heatmap and mask PNGs here")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import cv2

    from ..aggregate.snapshot import LanguageMap
    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate.scene_eval import label_texts, load_queries
    from ..pipeline import Scene
    from ..scene import read_ply, select_view
    from ..viz import colorize, write_png
    from ..query import CANONICAL_NEGATIVES, heatmaps, relevancy_mask, render_feature_map
    from ..query.localize import instances_in_3d, regions_in_view

    text = args.text.strip()
    if not text:
        raise OlsplatInputError("the query text is empty")
    scene = Scene.open(args.scene)
    language_map = LanguageMap.load(args.map)
    spec = language_map.encoder
    encoder = encoder_from_spec("shipped" if spec.startswith("olsplat-cnn64:") else spec)
    gaussians = read_ply(scene.ply)
    if len(gaussians) != len(language_map.features):
        raise OlsplatInputError(f"{args.map}: {len(language_map.features)} Gaussians, the scene's map has {len(gaussians)}")
    if args.negatives:
        negatives = [t.strip() for t in args.negatives.split(",") if t.strip()]
    elif (scene.folder / "queries.json").exists():
        labels, queries = load_queries(scene.folder)
        negatives = [t for t in label_texts(labels, queries) if t != text]
    else:
        negatives = list(CANONICAL_NEGATIVES)
    embeddings = encoder.encode_text([text, *negatives])
    features = language_map.features.astype(np.float32)
    relevance = features @ embeddings.T  # [N, 1 + negatives]
    chosen = (relevance.argmax(1) == 0) & language_map.observed
    instances = instances_in_3d(gaussians.means, chosen)
    print(f'"{text}": {int(chosen.sum()):,} Gaussians pick it over {len(negatives)} negatives; {len(instances)} instances in 3D')
    for i, inst in enumerate(instances[:20]):
        c, lo, hi = inst.centre, inst.box_min, inst.box_max
        print(f"  3D #{i}: centre ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) m, box {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} x {hi[2] - lo[2]:.1f} m, {inst.gaussians} Gaussians")
    camera = select_view(scene.cameras, args.view if args.view is not None else 0)
    feature_map, alpha = render_feature_map(gaussians, features, camera)
    maps = heatmaps(feature_map, embeddings)
    mask = relevancy_mask(maps[0], maps[1:], alpha)
    regions = regions_in_view(mask)
    print(f"view {camera.name}: {int(mask.sum()):,} pixels, {len(regions)} regions")
    for i, region in enumerate(regions[:20]):
        print(f"  2D #{i}: box {region.box}, {region.pixels} px")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        image = scene.image(camera)[..., ::-1].astype(np.float32)
        heat = colorize(maps[0], alpha > 0.5, -1.0, 1.0).astype(np.float32)
        stem = f"{Path(camera.name).stem}_{'_'.join(text.split())}"
        write_png(args.out / f"{stem}_heatmap.png", (0.45 * image + 0.55 * heat).astype(np.uint8))
        overlay = image.copy()
        overlay[mask] = 0.4 * overlay[mask] + 0.6 * np.array([0, 220, 255])
        for region in regions:
            x0, y0, x1, y1 = region.box
            cv2.rectangle(overlay, (x0, y0), (x1 - 1, y1 - 1), (0, 255, 0), 1)
        write_png(args.out / f"{stem}_mask.png", overlay.astype(np.uint8))
        print(f"pictures -> {args.out}")
    return 0
