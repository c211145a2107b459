"""``olsplat doctor`` on this machine, and each machine row made to fail the honest way: an
empty numba cache, the C extension absent from the package, OLSPLAT_NATIVE=0, a changed byte in
a model."""

from __future__ import annotations

import shutil
from pathlib import Path

from olsplat_nodes.launcher.preflight._machine import cpu_features
from olsplat_nodes.launcher.preflight._models import MANIFEST, model_folder, read_manifest, shipped_model_folders

from .conftest import rows_of, run_olsplat

PACKAGE = Path(__file__).resolve().parents[2] / "olsplat_nodes"


def test_doctor_passes_on_this_set_up_machine(tmp_path):
    # make setup warmed numba's cache (olsplat warm-up); after editing a kernel's file, run it again
    done = run_olsplat("doctor", "--json", str(tmp_path / "d.json"))
    rows = rows_of(tmp_path / "d.json")
    assert done.returncode == 0, done.stdout + done.stderr
    assert not [r for r in rows.values() if r["status"] == "blocker"], done.stdout
    assert rows["numba cache"]["status"] == "ok" and rows["numba cache"]["figure"].startswith("warm")
    assert {"python", "cores", "cpu features", "C kernels", "onnxruntime", "model olsplat-cnn64", "model structure",
            "clock source", "clock sync"} <= set(rows)  # fmt: skip
    assert "ok" in done.stdout.splitlines()[-1] and "blocker" in done.stdout.splitlines()[-1]  # the counts line


def test_an_empty_numba_cache_is_a_blocker(tmp_path):
    cache = tmp_path / "numba_cache"
    cache.mkdir()
    done = run_olsplat("doctor", "--json", str(tmp_path / "d.json"), env={"NUMBA_CACHE_DIR": str(cache)})
    row = rows_of(tmp_path / "d.json")["numba cache"]
    assert done.returncode == 1
    assert row["status"] == "blocker" and row["figure"].startswith("cold") and str(cache) in row["figure"]
    assert "olsplat warm-up" in row["fix"]
    # nothing was compiled to find out (numba makes each kernel's folder when it is decorated)
    assert not [p for p in cache.rglob("*") if p.is_file()]


def test_without_the_built_extension_the_c_kernel_row_says_missing(tmp_path):
    # a copy of the package without the compiled extension, first on the path: an install where
    # the C compiler was missing (the editable install's finder comes after PYTHONPATH)
    shutil.copytree(PACKAGE, tmp_path / "site" / "olsplat_nodes", ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    done = run_olsplat("doctor", "--json", str(tmp_path / "d.json"), env={"PYTHONPATH": str(tmp_path / "site")})
    row = rows_of(tmp_path / "d.json")["C kernels"]
    assert row["status"] == "warn" and row["figure"].startswith("missing"), done.stdout
    assert "C compiler" in row["fix"]


def test_olsplat_native_0_says_disabled(tmp_path):
    done = run_olsplat("doctor", "--json", str(tmp_path / "d.json"), env={"OLSPLAT_NATIVE": "0"})
    rows = rows_of(tmp_path / "d.json")
    assert rows["C kernels"]["status"] == "warn" and rows["C kernels"]["figure"].startswith("disabled"), done.stdout
    assert "OLSPLAT_NATIVE" in rows["C kernels"]["fix"]


def test_the_shipped_manifests_list_every_model_file_with_its_checksum():
    for folder in shipped_model_folders():
        listed = set(read_manifest(folder / MANIFEST))
        assert listed == {p.name for p in folder.iterdir() if p.is_file() and p.name != MANIFEST}, folder
        assert model_folder(folder).status == "ok", model_folder(folder)


def test_a_changed_model_byte_is_a_blocker_naming_the_file(tmp_path):
    folder = next(f for f in shipped_model_folders() if (f / "image.onnx").is_file())
    copy = tmp_path / folder.name
    shutil.copytree(folder, copy)
    assert model_folder(copy).status == "ok"
    data = bytearray((copy / "image.onnx").read_bytes())
    data[len(data) // 2] ^= 0x01
    (copy / "image.onnx").write_bytes(bytes(data))
    row = model_folder(copy)
    assert row.status == "blocker" and row.figure.startswith("image.onnx: checksum") and "reinstall" in row.fix
    (copy / "image.onnx").unlink()
    assert model_folder(copy).status == "blocker" and "cannot be read" in model_folder(copy).figure


def test_cpu_features_per_architecture():
    assert cpu_features("x86_64", "flags\t: fpu sse avx2 fma f16c\n").status == "ok"
    row = cpu_features("x86_64", "flags\t: fpu sse avx\n")
    assert row.status == "warn" and "avx2, f16c, fma" in row.figure
    assert cpu_features("aarch64", "Features\t: fp asimd evtstrm\n").status == "ok"
    assert cpu_features("aarch64", "Features\t: fp evtstrm\n").status == "warn"
