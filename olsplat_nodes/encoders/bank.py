"""Region features of one view: every region of every level through the encoder(s)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..regions import RegionLevels
from .base import VisionLanguageEncoder
from .crops import CropConfig, region_crops
from .fusion import FusedEncoder


@dataclass
class FeatureBank:
    features: list[np.ndarray]  # per level l: [counts[l], D] float32, unit rows; row r = region r
    encoder: str  # the encoder (or fusion) that made them

    @property
    def dim(self) -> int:
        return self.features[0].shape[1]


def encode_regions(
    image_rgb: np.ndarray,  # [H, W, 3] uint8
    levels: RegionLevels,
    encoder: VisionLanguageEncoder | FusedEncoder,
    crop_config: CropConfig = CropConfig(),
    batch: int = 64,
) -> FeatureBank:
    """Crop every region of every level and embed it (see ``crops`` for how crops are made).

    An encoder with a ``crop_config`` of its own (shipped ones say how they were trained)
    gets crops made that way; others get ``crop_config``.
    """
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
        raise ValueError(f"image must be [H, W, 3] uint8 RGB, got shape {image_rgb.shape} dtype {image_rgb.dtype}")
    members = encoder.encoders if isinstance(encoder, FusedEncoder) else [encoder]
    features = []
    for label_map in levels.label_maps:
        # each member gets crops its own way: its input size and, if it has one, its crop style
        crops = [region_crops(image_rgb, label_map, m.input_size, getattr(m, "crop_config", None) or crop_config) for m in members]
        chunks = []
        for start in range(0, len(crops[0]), batch):
            part = [c[start : start + batch] for c in crops]
            chunks.append(encoder.encode_crops(part) if isinstance(encoder, FusedEncoder) else encoder.encode_images(part[0]))
        features.append(np.concatenate(chunks).astype(np.float32))
    return FeatureBank(features, encoder.name)
