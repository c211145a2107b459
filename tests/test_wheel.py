"""olsplat as a drone gets it: the wheel built from this checkout, installed (not editable, no
extras) into a fresh environment, run from a folder outside the checkout.

The editable install every other test runs on hides what a wheel leaves out (a subpackage the
package list forgot, a launch file that lives only in the checkout). Here pip resolves the base
install's dependencies from the package index exactly as on a flight computer, so the test
also shows that the base install does not pull torch, open3d or ray.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.helpers import free_port

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
# what only an extra installs: none of it may be in the base install
EXTRA_DISTRIBUTIONS = {"torch", "open3d", "ray", "depthai", "viser", "onnx", "onnxscript", "playwright"}
# the modules that need an extra to import (torch), all others must import from the base install
NEEDS_TORCH = {
    "olsplat_nodes.encoders.clip_model",
    "olsplat_nodes.encoders.export",
    "olsplat_nodes.structure.minkunet",
    "olsplat_nodes.structure.segcontrast",
    "olsplat_nodes.structure.sparse_conv",
    "olsplat_sim.train_encoders",
    "olsplat_sim.train_pair",
    "olsplat_sim.train_structure",
}

IMPORT_ALL = """
import importlib, json, pkgutil, sys
extras = set(sys.argv[1].split(","))
imported, need_extra, failed = [], {}, {}
for top in ("olsplat_nodes", "olsplat_msgs", "olsplat_sim"):
    package = importlib.import_module(top)
    for name in [top] + [m.name for m in pkgutil.walk_packages(package.__path__, top + ".")]:
        try:
            importlib.import_module(name)
            imported.append(name)
        except ModuleNotFoundError as exc:
            (need_extra if (exc.name or "").split(".")[0] in extras else failed)[name] = repr(exc)
        except Exception as exc:
            failed[name] = repr(exc)
print(json.dumps({"imported": imported, "need_extra": need_extra, "failed": failed,
                  "file": importlib.import_module("olsplat_nodes").__file__}))
"""


def _source_copy(target: Path) -> Path:
    """The checkout's files as git sees them (tracked and new, not ignored; symlinks kept), so
    that the build sees neither .venv nor a previous build/."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    for name in filter(None, listed):
        source, copy = REPO / name, target / name
        if not source.exists() and not source.is_symlink():  # deleted in the work tree, not yet in git
            continue
        copy.parent.mkdir(parents=True, exist_ok=True)
        if source.is_symlink():
            copy.symlink_to(source.readlink())
        else:
            shutil.copy2(source, copy)
    return target


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    source = _source_copy(tmp_path_factory.mktemp("source"))
    out = tmp_path_factory.mktemp("wheelhouse")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(source)],
        check=True, capture_output=True, timeout=600,
    )  # fmt: skip
    (built,) = out.glob("olsplat-*.whl")
    return built


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    """A fresh environment (no pip of its own: this one's pip installs into it) with the wheel
    and what pip resolves for it, no extras. Returns its bin/ folder."""
    env = tmp_path_factory.mktemp("flight_computer") / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env)], check=True, timeout=120)
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(env / "bin" / "python"), "install", "-q", str(wheel)],
        check=True, capture_output=True, timeout=900,
    )  # fmt: skip
    return env / "bin"


@pytest.fixture
def elsewhere(tmp_path) -> Path:
    """A working folder outside the checkout (nothing of the source tree importable from it)."""
    assert REPO not in tmp_path.parents
    return tmp_path


def _package_files() -> set[str]:
    """What the wheel must hold, by its path inside the wheel."""
    want = {f"olsplat_nodes/{p.relative_to(REPO / 'olsplat_nodes')}" for p in (REPO / "olsplat_nodes").rglob("*.py")}
    want |= {f"olsplat_msgs/{p.name}" for p in (REPO / "msgs").glob("*.py")} | {"olsplat_msgs/schema.yaml"}
    want |= {f"olsplat_sim/{p.name}" for p in (REPO / "sim").glob("*.py")}
    for data in ("launcher/files", "encoders/assets", "structure/assets"):
        files = [p for p in (REPO / "olsplat_nodes" / data).rglob("*") if p.is_file() and "__pycache__" not in p.parts]
        want |= {f"olsplat_nodes/{p.relative_to(REPO / 'olsplat_nodes')}" for p in files}
    return want


def test_the_wheel_holds_every_module_launch_file_and_model(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    want = _package_files()
    assert {"olsplat_nodes/launcher/files/replay.yaml", "olsplat_nodes/method/__init__.py"} <= want
    assert not want - names, f"missing from the wheel: {sorted(want - names)[:10]}"
    from olsplat_nodes.native import library

    if library() is not None:  # the checkout built the C kernels: the wheel must carry them too
        assert any(n.startswith("olsplat_nodes/native/_kernels") and n.endswith(".so") for n in names)


def test_the_base_install_has_no_extra(wheel, installed):
    listed = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(installed / "python"), "list", "--format", "json"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    have = {entry["name"].lower() for entry in json.loads(listed)}
    assert "olsplat" in have and "numba" in have and "onnxruntime" in have
    assert not have & EXTRA_DISTRIBUTIONS, f"the base install pulled extras: {sorted(have & EXTRA_DISTRIBUTIONS)}"


def test_every_module_imports_outside_the_checkout(installed, elsewhere):
    extras = "torch,open3d,ray,depthai,viser,onnx,onnxscript"
    done = subprocess.run(
        [str(installed / "python"), "-c", IMPORT_ALL, extras], cwd=elsewhere, capture_output=True, text=True,
        timeout=300, check=True,
    )  # fmt: skip
    report = json.loads(done.stdout)
    assert Path(report["file"]).is_relative_to(installed.parent), report["file"]  # the wheel's, not the checkout's
    assert not report["failed"], report["failed"]
    assert set(report["need_extra"]) <= NEEDS_TORCH, report["need_extra"]
    assert {"olsplat_nodes.nodes.accumulator", "olsplat_nodes.method", "olsplat_nodes.cluster"} <= set(
        report["imported"]
    )


def test_the_replay_graph_runs_from_the_wheel(installed, elsewhere):
    """A tiny simulated flight through the shipped ``replay`` launch file, by name, from the
    base install; then a launch that needs a missing extra is refused with one line."""
    olsplat = str(installed / "olsplat")
    subprocess.run(
        [olsplat, "sim", "make", "--preset", "tiny", "--seed", "0", "--out", "flight"],
        cwd=elsewhere, check=True, capture_output=True, timeout=600,
    )  # fmt: skip
    ply = "flight/map/point_cloud.ply"
    args = [olsplat, "launch", "replay", "--run-dir", "run", "--set", "ingest.source=flight/replay.mcap"]
    args += [f"--set={node}.map={ply}" for node in ("query_server", "accumulator", "refiner")]
    args += ["--set", f"query_server.query_endpoint=tcp://127.0.0.1:{free_port()}"]
    done = subprocess.run(args, cwd=elsewhere, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    latest = json.loads((elsewhere / "run" / "map" / "latest.json").read_text())
    assert latest["final"] and latest["views"] == 12, latest

    refused = subprocess.run(
        [*args[:3], "--run-dir", "run3d", *args[5:], "--set", "accumulator.features=2d3d"],
        cwd=elsewhere, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 1 and len(lines) == 1, refused.stderr
    assert "features=2d3d" in lines[0] and "pip install 'olsplat[structure]'" in lines[0], lines[0]
    assert not (elsewhere / "run3d" / "logs").exists()  # refused before any node started
