"""Encoders named on a command line: "shipped", shipped names, or exported folders."""

from __future__ import annotations

from pathlib import Path

from ..errors import OlsplatInputError
from .fusion import FusedEncoder
from .onnx_encoder import OnnxEncoder
from .shipped import DEFAULT_WEIGHTS, SHIPPED, default_encoder, shipped_encoder


def encoder_from_spec(spec: str = "shipped", weights: str | None = None, fusion: str = "concat"):
    """'shipped' -> both shipped encoders fused (lambda_2D = 0.6); else comma-separated shipped
    names or folders made by ``olsplat export-clip``, fused with ``weights`` when several."""
    parsed = [float(w) for w in weights.split(",")] if weights else None
    try:
        if spec == "shipped":
            return default_encoder(tuple(parsed) if parsed else DEFAULT_WEIGHTS)
        members = [shipped_encoder(p) if p in SHIPPED else OnnxEncoder(Path(p)) for p in spec.split(",")]
        return FusedEncoder(members, parsed, fusion) if len(members) > 1 or parsed else members[0]
    except ValueError as exc:
        raise OlsplatInputError(str(exc)) from None
