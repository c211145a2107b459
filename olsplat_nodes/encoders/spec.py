"""Encoders named on a command line: shipped names, "shipped" (both fused), or exported folders.

The default is ``DEFAULT_SPEC``, the first shipped encoder alone (D = 64): on the training seeds
it beat the two shipped encoders fused (docs/evaluation.md, "The 3D branch", Table 6), and it is
one encoder per frame instead of two, with half the bytes per feature everywhere after it."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from ..errors import OlsplatInputError
from .fusion import FusedEncoder
from .onnx_encoder import OnnxEncoder
from .shipped import DEFAULT_WEIGHTS, REGISTERED, default_encoder, shipped_encoder

DEFAULT_SPEC = "olsplat-cnn64"


def encoder_from_spec(
    spec: str = DEFAULT_SPEC,
    weights: str | Sequence[float] | None = None,
    fusion: Literal["concat", "sum"] = "concat",
    threads: int = 0,
):
    """The default: the shipped olsplat-cnn64 alone. 'shipped' -> both shipped encoders fused
    (lambda_2D = 0.6, the paper's two-encoder fusion); else comma-separated shipped
    names or folders made by ``olsplat export-clip``, fused with ``weights`` (lambda_2D per
    encoder, as numbers or as the command line's "0.6,0.4") when several. ``threads``:
    onnxruntime's intra-op threads per encoder (0 = one per core; a node sharing the CPU with
    others wants 1)."""
    try:
        parsed = [float(w) for w in (weights.split(",") if isinstance(weights, str) else weights)] if weights else None
    except ValueError:
        raise OlsplatInputError(f"fusion weights must be numbers such as 0.6,0.4, got {weights!r}") from None
    try:
        if spec == "shipped":
            return default_encoder(tuple(parsed) if parsed else DEFAULT_WEIGHTS, threads)
        members = [
            shipped_encoder(p, threads) if p in REGISTERED else OnnxEncoder(Path(p), threads) for p in spec.split(",")
        ]
        return FusedEncoder(members, parsed, fusion) if len(members) > 1 or parsed else members[0]
    except ValueError as exc:
        raise OlsplatInputError(str(exc)) from None


def encoder_fingerprint(spec: str = DEFAULT_SPEC) -> str:
    """sha256 (hex) over the files of every model a spec names (as ``encoder_from_spec`` reads it:
    'shipped', shipped names, or exported folders), in order, each file's name and bytes: a saved
    result made with other weights under the same name does not match. ``SHA256SUMS`` is left
    out (it is derived from the rest)."""
    import hashlib

    from .shipped import ASSETS, SHIPPED

    names = list(SHIPPED) if spec == "shipped" else spec.split(",")
    digest = hashlib.sha256()
    for name in names:
        folder = ASSETS / name if name in REGISTERED else Path(name)
        for path in sorted(folder.iterdir()) if folder.is_dir() else []:
            if path.is_file() and path.name != "SHA256SUMS":
                digest.update(f"{name}/{path.name}\0".encode())
                digest.update(path.read_bytes())
    return digest.hexdigest()
