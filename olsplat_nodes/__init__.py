"""olsplat: open-vocabulary 3D scene understanding for UAVs on a CPU.

Subpackages: ``scene`` (map and camera I/O), ``raster`` (CPU rasterizer with Top-K), ``bench``
(benchmark scripts); the node wrappers, transport and launcher arrive with their issues.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
