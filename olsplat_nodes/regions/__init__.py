"""Multi-level image regions (the 2D branch's partition of each view)."""

from .levels import RegionLevels, relabel_contiguous
from .superpixel_merge import RegionConfig, propose_regions

__all__ = ["RegionConfig", "RegionLevels", "propose_regions", "relabel_contiguous"]
