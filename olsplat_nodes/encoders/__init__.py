"""2D vision-language encoders: the contract, region crops, fusion and per-view feature banks."""

from .bank import FeatureBank, encode_regions
from .base import VisionLanguageEncoder, normalize
from .crops import CropConfig, region_crops
from .fusion import FusedEncoder

__all__ = [
    "CropConfig",
    "FeatureBank",
    "FusedEncoder",
    "VisionLanguageEncoder",
    "encode_regions",
    "normalize",
    "region_crops",
]
