"""``olsplat export-clip``: turn an open_clip checkpoint into ONNX files olsplat can run."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "export-clip",
        help="export an open_clip CLIP ViT checkpoint (RemoteCLIP, GeoRSCLIP, ...) to ONNX",
        description="Writes image.onnx, text.onnx, vocab.txt.gz and encoder.json into --out.",
    )
    parser.add_argument("--checkpoint", required=True, type=Path, help="open_clip state dict (.pt/.bin)")
    parser.add_argument("--vocab", required=True, type=Path, help="BPE merges file (bpe_simple_vocab_16e6.txt.gz)")
    parser.add_argument("--out", required=True, type=Path, help="folder for the ONNX towers, vocabulary and manifest")
    parser.add_argument("--name", help="encoder name (default: the checkpoint's file name)")
    parser.add_argument(
        "--activation",
        choices=["gelu", "quick_gelu"],
        default="gelu",
        help="MLP activation: gelu for open_clip 'ViT-B-32' models (RemoteCLIP), quick_gelu for models "
        "built with pretrained='openai' (GeoRSCLIP/RS5M)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..extras import require

    for module in ("torch", "onnx", "onnxscript"):
        require(module, "olsplat export-clip", "export")
    from ..encoders.export import export_clip

    try:
        out = export_clip(args.checkpoint, args.vocab, args.out, args.activation, args.name)
    except ValueError as exc:
        raise OlsplatInputError(str(exc)) from None
    print(f"exported {args.checkpoint} -> {out}")
    return 0
