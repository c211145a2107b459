"""``olsplat bench compression``: what compressing the language map costs in query accuracy.

From an aggregation folder (``olsplat aggregate --out DIR``: DIR/store), the refined float32
features are recomputed from the store and scored on the scene's annotations as float32, as
float16 (the snapshot's form) and through codebooks of K centres (``aggregate.codebook``),
with the bytes per Gaussian each form takes.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("compression", help="query accuracy of float32 / float16 / codebook language maps")
    parser.add_argument("--scene", required=True, type=Path, help="a scene folder")
    parser.add_argument(
        "--aggregated", required=True, type=Path, help="an `olsplat aggregate --out` folder (its store/)"
    )
    parser.add_argument("--method", default="outlangsplat", help="the method the folder was aggregated with")
    parser.add_argument("--codebooks", default="256,1024,4096", help="comma-separated K")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..aggregate.codebook import compress, decompress, fit_codebook
    from ..encoders.spec import encoder_from_spec
    from ..errors import OlsplatInputError
    from ..evaluate import evaluate_map
    from ..method import named_method
    from ..pipeline import Scene
    from ..scene import read_ply
    from ..storage import ObservationStore
    from ..storage.snapshot import LanguageMap

    scene = Scene.open(args.scene)
    encoder = encoder_from_spec()
    n = len(read_ply(scene.ply))
    if not (args.aggregated / "store" / "views").is_dir():
        raise OlsplatInputError(
            f"{args.aggregated / 'store'}: no aggregated views (run `olsplat aggregate --out` first)"
        )
    store = ObservationStore(args.aggregated / "store", n)
    if not len(store):
        raise OlsplatInputError(f"{args.aggregated / 'store'}: no aggregated views")
    features, observed = store.refine(None, named_method(args.method).aggregation, only_touched=False)
    unit = LanguageMap.from_features(features, observed, encoder.name).features.astype(np.float32)  # float16 -> back
    norms = np.linalg.norm(features, axis=1, keepdims=True)
    exact = np.where(norms > 0, features / np.maximum(norms, 1e-12), 0).astype(np.float32)
    d = features.shape[1]
    forms = {"float32": (exact, 4 * d), "float16": (unit, 2 * d)}
    for k in (int(x) for x in args.codebooks.split(",") if x.strip()):
        t0 = time.perf_counter()
        centres = fit_codebook(exact, k)
        codes = compress(exact, centres)
        print(f"codebook K={k}: fitted and applied in {time.perf_counter() - t0:.0f} s")
        forms[f"codebook {k}"] = (decompress(codes, centres), 2 + 2 * k * d / n)
    print(f"{scene.folder.name}: {n:,} Gaussians x {d} dims, {len(store)} views")
    for name, (values, bytes_per) in forms.items():
        r = evaluate_map(scene, LanguageMap(values, observed, encoder.name), encoder)
        print(
            f"  {name:14s} {bytes_per:7.1f} B/Gaussian  mIoU {r['mIoU']:5.1f}  mAcc {r['mAcc']:5.1f}  Loc@50 "
            f"{r['loc50']:5.1f}"
        )
    return 0
