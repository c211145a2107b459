"""CPU Gaussian rasterizer (numba, tile-based) with per-pixel adaptive Top-K contributions."""

import numba

# open3d ships an old TBB; if it is loaded first, numba would try it, warn and fall back. Ask for
# OpenMP first so the threading layer is the same whatever was imported before.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]  # type: ignore[attr-defined]  # set at import

from .config import RasterConfig  # noqa: E402
from .project import Projected, project  # noqa: E402
from .rasterize import RenderResult, rasterize  # noqa: E402

__all__ = ["Projected", "RasterConfig", "RenderResult", "project", "rasterize"]
