"""The one compiled part of olsplat: the heatmap compositing kernel (olsplat_nodes/raster/native/).

Optional: when it cannot be built (no C compiler), the install goes on and ``rasterize`` uses the
numba kernel for heatmaps too. Everything else is configured in pyproject.toml.
"""

import platform

from setuptools import Extension, setup

flags = ["-O3", "-ffast-math", "-fopenmp"]
if platform.machine() in ("x86_64", "AMD64"):
    flags += ["-mavx2", "-mfma"]  # the loader checks the CPU has them before using the library

setup(
    ext_modules=[
        Extension(
            "olsplat_nodes.raster._heatmap_native",
            sources=["olsplat_nodes/raster/native/heatmap_composite.c"],
            extra_compile_args=flags,
            extra_link_args=["-fopenmp"],
            optional=True,
        )
    ]
)
