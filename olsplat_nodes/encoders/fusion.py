"""Fusing several vision-language encoders (the paper's eq. 2d_feature_fusion).

The paper fuses two CLIP-family encoders as f = λ φ_R + (1 - λ) φ_S with λ = 0.6. A sum only
means something when both share one embedding space (RemoteCLIP and GeoRSCLIP are both
fine-tuned from the same CLIP, so roughly they do): mode ``"sum"``. Encoders trained apart
(our shipped compact ones) do not share a space, so the default mode ``"concat"`` stacks
sqrt(w_i) φ_i: the dot product of two such vectors is Σ w_i cos_i, the same weighted fusion
applied to the similarities, valid for any encoders and dimensions. Either way the result is
L2-normalised again.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import reduce
from typing import Literal

import numpy as np

from .base import VisionLanguageEncoder, normalize


class FusedEncoder:
    def __init__(
        self,
        encoders: Sequence[VisionLanguageEncoder],
        weights: list[float] | None = None,
        mode: Literal["concat", "sum"] = "concat",
    ):
        if not encoders:
            raise ValueError("FusedEncoder needs at least one encoder")
        weights = [1.0 / len(encoders)] * len(encoders) if weights is None else list(weights)
        if len(weights) != len(encoders) or any(w < 0 for w in weights) or sum(weights) <= 0:
            raise ValueError(f"need one non-negative weight per encoder, got weights={weights}")
        if mode == "sum" and len({e.dim for e in encoders}) > 1:
            raise ValueError(f"mode='sum' needs encoders of one dimension, got {[e.dim for e in encoders]}")
        if mode not in ("concat", "sum"):
            raise ValueError(f"mode must be 'concat' or 'sum', got mode={mode!r}")
        total = float(sum(weights))
        self.encoders, self.weights, self.mode = encoders, [w / total for w in weights], mode
        self.name = "+".join(f"{e.name}:{w:.2f}" for e, w in zip(encoders, self.weights, strict=True))
        self.dim = encoders[0].dim if mode == "sum" else sum(e.dim for e in encoders)

    def _fuse(self, parts: list[np.ndarray]) -> np.ndarray:
        if self.mode == "sum":
            return normalize(reduce(np.add, [w * p for w, p in zip(self.weights, parts, strict=True)]))
        return normalize(np.concatenate([np.sqrt(w) * p for w, p in zip(self.weights, parts, strict=True)], axis=-1))

    def encode_crops(self, crops: list[np.ndarray]) -> np.ndarray:
        """One [B, S_i, S_i, 3] crop batch per member encoder (its size, its crop style) -> [B, dim]."""
        return self._fuse([e.encode_images(c) for e, c in zip(self.encoders, crops, strict=True)])

    def encode_text(self, texts: list[str]) -> np.ndarray:
        return self._fuse([e.encode_text(texts) for e in self.encoders])

    def unknown_words(self, text: str) -> list[str]:
        """Words of ``text`` that no member encoder knows (one that knows a word carries it)."""
        per_member = [list(getattr(e, "unknown_words", lambda _t: [])(text)) for e in self.encoders]
        common = set.intersection(*(set(words) for words in per_member))
        return [w for w in dict.fromkeys(per_member[0]) if w in common]
