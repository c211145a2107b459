"""Shared fixtures: small deterministic scenes and cameras, and where the real data lives."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from olsplat_nodes.scene import Camera, Gaussians, intrinsics, look_at
from olsplat_sim.make import make_dataset
from olsplat_sim.presets import PRESETS

from .promised import skip_unless_ci

SHARED_DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"

# Tests that start processes, graphs, servers, Ray or a browser, or that measure time: `make test`
# runs them alone, one at a time, after the others ran on two workers (pytest -n 2 -m "not serial").
# Two graphs of five processes on two cores would slow each other past what their waits allow.
SERIAL_FOLDERS = {"nodes", "launcher", "ground", "cluster", "transport", "doctor"}
SERIAL_FILES = {
    "test_wheel.py",
    "test_demo.py",
    "test_promised.py",
    "test_memory.py",
    "bench/test_bench_graph.py",  # launches graphs and times them
    "sources/test_depthai.py",  # timed camera loops
    "sources/test_replay_log.py",  # paced replay
}


def pytest_collection_modifyitems(config, items):
    tests = Path(__file__).resolve().parent
    for item in items:
        where = Path(str(item.fspath)).resolve().relative_to(tests)
        if where.parts[0] in SERIAL_FOLDERS or where.as_posix() in SERIAL_FILES:
            item.add_marker(pytest.mark.serial)


def random_gaussians(n: int, sh_degree: int = 3, seed: int = 0, spread: float = 1.0) -> Gaussians:
    """n Gaussians in a slab around the origin (|x|, |y| <= spread, |z| <= 0.3 spread)."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-spread, spread, (n, 3))
    means[:, 2] *= 0.3
    return Gaussians(
        means=means,
        quats=rng.normal(size=(n, 4)),
        log_scales=np.log(rng.uniform(0.02, 0.25, (n, 3)) * spread),
        opacity_logits=rng.normal(0.5, 2.0, n),
        sh=rng.normal(0.0, 0.4, (n, (sh_degree + 1) ** 2, 3)),
    )


def camera_for(kind: str, width: int, height: int) -> Camera:
    """Cameras of several intrinsics models looking at the origin from about 4 units away."""
    pose = look_at([0.4, -0.3, 4.0], [0.0, 0.0, 0.0], (0.0, 1.0, 0.0))
    if kind == "PINHOLE_CENTRED":
        return Camera(kind, width, height, intrinsics(0.9 * width, 0.9 * width, width / 2, height / 2), pose)
    if kind == "PINHOLE_SKEWED":  # fx != fy, principal point off centre
        return Camera(kind, width, height, intrinsics(0.8 * width, 1.1 * width, 0.4 * width, 0.6 * height), pose)
    if kind == "SIMPLE_RADIAL":
        K = intrinsics(0.7 * width, 0.7 * width, width / 2 + 1.3, height / 2 - 0.7)
        return Camera(kind, width, height, K, pose, dist=[0.05, 0, 0, 0], model="SIMPLE_RADIAL")
    if kind == "OPENCV_WIDE":  # wide field of view: Jacobian clamping matters at the border
        K = intrinsics(0.3 * width, 0.32 * width, width / 2, height / 2)
        return Camera(kind, width, height, K, pose, dist=[-0.1, 0.01, 0.001, -0.002], model="OPENCV")
    raise ValueError(kind)


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        skip_unless_ci("shared data", f"the shared real data folder is absent ({SHARED_DATA})")
    return SHARED_DATA


# `make test` runs pytest three times at once or in turn (two workers, then the serial pass), and
# each would make the session's flights again (~40 s of CPU). With OLSPLAT_TEST_SHARED (the
# Makefile gives each run a fresh folder) the first process that needs one makes it there, under
# a lock, and every process copies it into its own temporary folder: tests may write into theirs.
SHARED_FIXTURES = "OLSPLAT_TEST_SHARED"


def made_once(name: str, out: Path, make: Callable[[Path], None]) -> None:
    """``make(out)``, or with $OLSPLAT_TEST_SHARED a copy of what ``make`` made there once."""
    shared = os.environ.get(SHARED_FIXTURES)
    if not shared:
        make(out)
        return
    root = Path(shared)
    root.mkdir(parents=True, exist_ok=True)
    made = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or the process dies
        if not (root / f"{name}.made").exists():
            shutil.rmtree(made, ignore_errors=True)  # a process that died half-way
            make(made)
            (root / f"{name}.made").touch()
    shutil.copytree(made, out, symlinks=True)


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """The tiny simulator preset, generated once per test session (a few seconds)."""
    out = tmp_path_factory.mktemp("tiny") / "scene"
    made_once("tiny", out, lambda folder: make_dataset(PRESETS["tiny"], 0, folder, log=lambda *_: None))
    return out, json.loads((out / "scene.json").read_text())  # make_dataset's summary, as JSON keeps it


@pytest.fixture(scope="session")
def tiny_map(tiny, tmp_path_factory) -> Path:
    """The tiny flight aggregated offline (``olsplat aggregate``, the default method and the shipped
    encoders): the path of its language_map.npz, made once per test session."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method
    from olsplat_nodes.pipeline import Scene, aggregate_scene

    work = tmp_path_factory.mktemp("tiny_map")

    def make(folder: Path) -> None:
        shutil.copytree(tiny[0], folder / "scene")
        aggregate_scene(Scene.open(folder / "scene"), named_method("outlangsplat"), encoder_from_spec(), folder / "out")

    made_once("tiny_map", work / "made", make)
    return work / "made" / "out" / "language_map.npz"


@pytest.fixture(scope="session")
def change_flights(tmp_path_factory) -> Path:
    """Three flights of the tiny town of training seed 1005 over its one prior map, aggregated once
    with ``--per-flight``: A (f0), B after the default changes (f1), N with none (f2, "now");
    ``out/`` holds the aggregate and ``out/flights/`` the per-flight maps. Made once per session."""
    from olsplat_nodes.cli import main

    root = tmp_path_factory.mktemp("change_flights") / "made"

    def make(folder: Path) -> None:
        sim = ["sim", "make", "--preset", "tiny", "--seed", "1005"]
        assert main([*sim, "--out", str(folder / "A")]) == 0
        assert main([*sim, "--flight-seed", "1", "--changes", "default", "--out", str(folder / "B")]) == 0
        assert main([*sim, "--flight-seed", "1", "--changes", "none", "--out", str(folder / "N")]) == 0
        scenes = [arg for name in "ABN" for arg in ("--scene", str(folder / name))]
        assert main(["aggregate", *scenes, "--out", str(folder / "out"), "--per-flight"]) == 0

    made_once("change_flights", root, make)
    return root
