"""The compiled part of olsplat: the C kernels in olsplat_nodes/native/ (heatmap and Top-K
compositing, relevance over float16 rows), one extension loaded with ctypes.

Optional: when it cannot be built (no C compiler), the install goes on and the numba kernels
serve instead.

Also the package list: every folder under olsplat_nodes/ (found, so that a new subpackage cannot be
left out of the wheel; namespace discovery also lists the data folders, assets/ and launcher/files/,
whose files pyproject.toml's package-data names) and the two folders installed under other names,
msgs/ -> olsplat_msgs and sim/ -> olsplat_sim (pyproject.toml's package-dir). Everything else is
configured in pyproject.toml.
"""

import platform

from setuptools import Extension, find_namespace_packages, setup

flags = ["-O3", "-ffast-math", "-fopenmp"]
if platform.machine() in ("x86_64", "AMD64"):
    flags += ["-mavx2", "-mfma", "-mf16c"]  # the loader checks the CPU has them before using the library

SOURCES = ["module.c", "heatmap_composite.c", "topk_composite.c", "winning_rows.c"]

setup(
    packages=[
        *find_namespace_packages(include=["olsplat_nodes", "olsplat_nodes.*"], exclude=["*.__pycache__"]),
        "olsplat_msgs",
        "olsplat_sim",
    ],
    ext_modules=[
        Extension(
            "olsplat_nodes.native._kernels",
            sources=[f"olsplat_nodes/native/{name}" for name in SOURCES],
            depends=[f"olsplat_nodes/native/{name}" for name in ("simd.h", "tile_pass.h")],
            extra_compile_args=flags,
            extra_link_args=["-fopenmp"],
            optional=True,
        )
    ],
)
