"""The compact encoders that ship inside the package (trained by ``olsplat sim train-encoders``).

They know the simulator's world only: a stand-in that lets the pipeline run offline until the
user exports RemoteCLIP / GeoRSCLIP with ``olsplat export-clip``.
"""

from __future__ import annotations

from pathlib import Path

from .fusion import FusedEncoder
from .onnx_encoder import OnnxEncoder

ASSETS = Path(__file__).resolve().parent / "assets"
SHIPPED = ("olsplat-cnn64", "olsplat-vit48")
# the independent pair (issue 43): disjoint seeds, views and captions (``python -m olsplat_sim.train_pair``);
# loadable by name, never part of the default or of "shipped"
INDEPENDENT_PAIR = ("olsplat-nadir32", "olsplat-oblique48")
REGISTERED = SHIPPED + INDEPENDENT_PAIR
DEFAULT_WEIGHTS = (0.6, 0.4)  # the paper's lambda_2D = 0.6 for the first encoder


def shipped_encoder(name: str, threads: int = 0) -> OnnxEncoder:
    """A shipped encoder; ``threads``: onnxruntime's intra-op threads (0 = one per core)."""
    if name not in REGISTERED:
        raise ValueError(f"no shipped encoder {name!r}; shipped: {', '.join(REGISTERED)}")
    return OnnxEncoder(ASSETS / name, threads)


def default_encoder(weights: tuple[float, ...] = DEFAULT_WEIGHTS, threads: int = 0) -> FusedEncoder:
    """Both shipped encoders fused with lambda_2D = weights[0]."""
    return FusedEncoder([shipped_encoder(n, threads) for n in SHIPPED], list(weights))
