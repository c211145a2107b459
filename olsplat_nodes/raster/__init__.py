"""CPU Gaussian rasterizer (numba, tile-based) with per-pixel adaptive Top-K contributions."""

from .config import RasterConfig
from .project import Projected, project
from .rasterize import RenderResult, rasterize

__all__ = ["Projected", "RasterConfig", "RenderResult", "project", "rasterize"]
