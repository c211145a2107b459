"""The encoder contract of the 2D semantic branch.

A vision-language encoder embeds images (region crops) and texts into one space; both come
out L2-normalised so that a dot product is a cosine similarity. Several encoders are fused
by ``fusion.FusedEncoder``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class VisionLanguageEncoder(Protocol):
    name: str
    dim: int  # embedding dimension
    input_size: int  # square crop side the image tower expects, pixels

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        """[B, S, S, 3] uint8 RGB crops (S = input_size) -> [B, dim] float32, unit rows."""
        ...

    def encode_text(self, texts: list[str]) -> np.ndarray:
        """Texts -> [T, dim] float32, unit rows."""
        ...


def normalize(vectors: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Rows scaled to unit L2 norm (zero rows stay zero)."""
    vectors = np.asarray(vectors, np.float32)
    return vectors / np.maximum(np.linalg.norm(vectors, axis=-1, keepdims=True), eps)
