"""The C kernels' portable path: built without AVX2, FMA and F16C (as on an ARM flight computer,
where ``setup.py`` passes no x86 flags), the heatmap and Top-K kernels take their scalar code,
which the x86 build never runs. The same sources are compiled here that way and loaded in place
of the installed library; the tests of test_native.py and test_topk_native.py then hold for it
against the numba kernels."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import sysconfig
from pathlib import Path

import pytest

import olsplat_nodes
from olsplat_nodes.raster import RasterConfig, heatmap_native, topk_native

from . import test_native, test_topk_native

SOURCES = ["module.c", "heatmap_composite.c", "topk_composite.c", "winning_rows.c"]  # as setup.py


@pytest.fixture(scope="module")
def portable(tmp_path_factory) -> ctypes.CDLL:
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler here (the extension is optional; the numba kernels serve)")
    folder = Path(olsplat_nodes.__file__).parent / "native"
    out = tmp_path_factory.mktemp("portable") / "kernels.so"
    # setup.py's flags without the x86 ones
    command = [compiler, "-O3", "-ffast-math", "-fopenmp", "-shared", "-fPIC", "-o", str(out)]
    command += ["-I", sysconfig.get_paths()["include"]]  # module.c's Python.h
    subprocess.run(command + [str(folder / name) for name in SOURCES], check=True, capture_output=True)
    library = ctypes.CDLL(str(out))
    assert library.built_with_avx2() == 0
    return library


@pytest.fixture
def with_portable(portable, monkeypatch):
    monkeypatch.setattr(heatmap_native, "library", lambda: portable)
    monkeypatch.setattr(topk_native, "library", lambda: portable)
    assert heatmap_native.kernel() is portable and topk_native.kernel() is portable


@pytest.mark.parametrize("width,height,n,kind,dim", test_native.CASES)
def test_portable_heatmaps_equal_the_numba_kernels(width, height, n, kind, dim, with_portable, monkeypatch):
    test_native.test_c_heatmaps_equal_the_numba_kernels_and_the_reference(width, height, n, kind, dim, monkeypatch)


def test_portable_heatmaps_read_codebook_rows(with_portable, monkeypatch):
    test_native.test_c_heatmaps_read_codebook_rows_as_the_numba_kernel(monkeypatch)


@pytest.mark.parametrize("dim", [24, 130])
def test_portable_float16_tables_render_as_their_float32_values(dim, with_portable):
    test_native.test_float16_tables_render_as_their_float32_values(dim)  # the bit-layout widening


@pytest.mark.parametrize("width,height,n,kind,opacity", test_topk_native.CASES)
def test_portable_topk_equals_the_numba_kernel(width, height, n, kind, opacity, with_portable, monkeypatch):
    for config in (RasterConfig(), RasterConfig(tile_size=8, topk_min=4, topk_max=12, topk_coverage=0.75)):
        test_topk_native.test_c_topk_equals_the_numba_kernel(width, height, n, kind, opacity, config, None, monkeypatch)


def test_portable_ranking_sorts_like_numpy(with_portable):
    test_topk_native.test_the_c_ranking_sorts_like_numpy(None)  # Batcher's network, not the AVX2 sort
