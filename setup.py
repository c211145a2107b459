"""The compiled part of olsplat: the C kernels in olsplat_nodes/native/ (heatmap and Top-K
compositing, relevance over float16 rows), one extension loaded with ctypes.

Optional: when it cannot be built (no C compiler), the install goes on and the numba kernels
serve instead. Everything else is configured in pyproject.toml.
"""

import platform

from setuptools import Extension, setup

flags = ["-O3", "-ffast-math", "-fopenmp"]
if platform.machine() in ("x86_64", "AMD64"):
    flags += ["-mavx2", "-mfma", "-mf16c"]  # the loader checks the CPU has them before using the library

SOURCES = ["module.c", "heatmap_composite.c", "topk_composite.c", "winning_rows.c"]

setup(
    ext_modules=[
        Extension(
            "olsplat_nodes.native._kernels",
            sources=[f"olsplat_nodes/native/{name}" for name in SOURCES],
            depends=[f"olsplat_nodes/native/{name}" for name in ("simd.h", "tile_pass.h")],
            extra_compile_args=flags,
            extra_link_args=["-fopenmp"],
            optional=True,
        )
    ]
)
