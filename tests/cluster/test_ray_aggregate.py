"""The aggregation on a real local Ray cluster (bound to 127.0.0.1): two flights into one tiled
map equal to the single machine's, and a tile actor killed mid-run changes nothing."""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from olsplat_nodes.encoders.spec import DEFAULT_SPEC, encoder_from_spec
from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.method import named_method
from olsplat_nodes.pipeline import Scene
from olsplat_nodes.pipeline.offline import aggregate_flights
from olsplat_nodes.storage import LanguageMap, ObservationStore

# before Ray is imported: its servers listen on the loopback address only (see ``connect``)
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
try:
    import ray
except ImportError:  # without olsplat[cluster]: skipped, or failed in CI (tests/promised.py)
    ray = None
from olsplat_nodes.cluster.ray_aggregate import aggregate_on_ray

from ..promised import skip_unless_ci

pytestmark = [pytest.mark.cluster, pytest.mark.slow]


@pytest.fixture(scope="module", autouse=True)
def _ray_installed():
    if ray is None:
        skip_unless_ci("ray", "olsplat[cluster] is not installed")


@pytest.fixture(scope="module", autouse=True)
def local_cluster(_ray_installed):
    """One local cluster for the module (its worker processes, once warm, serve every run)."""
    from olsplat_nodes.cluster.ray_aggregate import connect

    assert connect("auto") == ["127.0.0.1"]  # a cluster of this computer, on its loopback address only
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def flights(tiny, tmp_path_factory):
    """Two flights over the tiny town's one prior map: the first five views of the tiny flight
    (its folder with a COLMAP model of those views), and five views of another flight over the
    same town (``--flight-seed 1``: another path, another noise, the same map). Encodings
    cached; the expected map is the single machine's of both flights."""
    from dataclasses import replace

    from olsplat_nodes.pipeline import view_features
    from olsplat_nodes.scene import write_colmap
    from olsplat_sim.make import make_dataset
    from olsplat_sim.presets import PRESETS

    work = tmp_path_factory.mktemp("flights")
    shutil.copytree(tiny[0], work / "a", ignore=shutil.ignore_patterns("cache"))
    cameras = Scene.open(work / "a").cameras[:5]
    shutil.rmtree(work / "a" / "sparse" / "0")
    write_colmap(work / "a" / "sparse" / "0", cameras)
    make_dataset(replace(PRESETS["tiny"], n_views=5), 0, work / "b", log=lambda *_: None, flight_seed=1)
    scenes = [Scene.open(work / name) for name in ("a", "b")]
    assert (work / "a" / "map" / "point_cloud.ply").read_bytes() == (
        work / "b" / "map" / "point_cloud.ply"
    ).read_bytes()
    assert [len(s.cameras) for s in scenes] == [5, 5]
    for scene in scenes:
        for camera in scene.cameras:  # the cache, so that the cluster's workers do not encode
            view_features(scene, camera, encoder_from_spec())
    expected = aggregate_flights(scenes, named_method("outlangsplat"), encoder_from_spec(), work / "single")
    assert expected["tiles"] == 1
    return scenes, LanguageMap.load(work / "single" / "language_map.npz")


def _same_map(got: LanguageMap, expected: LanguageMap) -> None:
    """Equal to float16 rounding: a tile records its views in the order they arrive, so a
    Gaussian's sums may be added in another order than the single machine's."""
    np.testing.assert_array_equal(got.observed, expected.observed)
    np.testing.assert_allclose(
        np.asarray(got.features, np.float32), np.asarray(expected.features, np.float32), atol=2e-3
    )


def _views_per_tile(store) -> list[list[str]]:
    return [ObservationStore(p, 1).names() for p in sorted(store.iterdir()) if (p / "views").is_dir()]


@pytest.mark.parametrize("tile_m", [0.0, 100.0])
def test_two_flights_on_ray_make_the_single_machine_map(flights, tmp_path, tile_m):
    scenes, expected = flights
    stats = aggregate_on_ray(scenes, named_method("outlangsplat"), (DEFAULT_SPEC, None), tmp_path, tile_m, "auto")
    assert stats["tiles"] == (1 if tile_m == 0 else 4) and len(stats["actor_peak_rss_mb"]) == stats["tiles"]
    assert stats["nodes"] == ["127.0.0.1"]
    _same_map(LanguageMap.load(tmp_path / "language_map.npz"), expected)
    names = {f"f{i}/{c.name}" for i, s in enumerate(scenes) for c in s.cameras}
    per_tile = _views_per_tile(tmp_path / "store") if tile_m else [ObservationStore(tmp_path / "store", 1).names()]
    for views in per_tile:  # each view once in each tile it touched
        assert len(views) == len(set(views)) and set(views) <= names
    assert set().union(*map(set, per_tile)) == names


def test_a_tile_actor_killed_mid_run_is_restarted_from_its_shard(flights, tmp_path):
    """SIGKILL the process of the first tile actor that has recorded a view, mid-run: Ray
    restarts the actor, which opens its shard again; the views in flight are sent again and
    recorded once; the map is the uninterrupted one."""
    scenes, expected = flights
    killed: dict[str, object] = {}

    def kill_one(actors) -> None:
        where = dict((folder, pid) for pid, folder in ray.get([actor.where.remote() for actor in actors]))

        def watch() -> None:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                for folder, pid in where.items():
                    views = len(list((Path(folder) / "views").glob("0*")))
                    if views >= 1:
                        killed.update(folder=folder, views_then=views)
                        os.kill(pid, signal.SIGKILL)
                        return
                time.sleep(0.05)

        threading.Thread(target=watch, daemon=True).start()

    aggregate_on_ray(
        scenes, named_method("outlangsplat"), (DEFAULT_SPEC, None), tmp_path, 100.0, "auto", on_start=kill_one
    )
    assert killed, "no tile recorded a view before the run ended: nothing was killed"
    _same_map(LanguageMap.load(tmp_path / "language_map.npz"), expected)
    views = ObservationStore(str(killed["folder"]), 1).names()
    assert len(views) == len(set(views)) > int(killed["views_then"])  # recorded after the restart too, once each


def test_the_command_aggregates_two_flights_into_one_tiled_map_on_a_local_cluster(flights, tmp_path):
    """``olsplat aggregate --scene A --scene B --tile-m 100 --cluster auto`` as a user runs it:
    its own process, which joins the cluster on this computer or starts one (127.0.0.1 only)."""
    import subprocess
    import sys

    scenes, expected = flights
    args = ["--scene", str(scenes[0].folder), "--scene", str(scenes[1].folder), "--tile-m", "100"]
    command = [sys.executable, "-m", "olsplat_nodes.cli", "aggregate", *args, "--cluster", "auto"]
    result = subprocess.run([*command, "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "10 views of 2 flight(s), 4 tile(s)" in result.stdout
    _same_map(LanguageMap.load(tmp_path / "out" / "language_map.npz"), expected)
    assert len(list((tmp_path / "out" / "store").glob("*/language_map.npz"))) == 4  # each tile's own map


def test_bad_input_in_a_view_task_is_the_one_error_that_names_the_file(flights, tmp_path):
    scenes, _ = flights
    shutil.copytree(scenes[0].folder, tmp_path / "a", ignore=shutil.ignore_patterns("cache"))
    missing = tmp_path / "a" / "images" / scenes[0].cameras[2].name
    missing.unlink()
    with pytest.raises(OlsplatInputError) as caught:
        aggregate_on_ray(
            [Scene.open(tmp_path / "a")], named_method("outlangsplat"), (DEFAULT_SPEC, None), tmp_path / "out", 100.0
        )
    assert str(missing) in str(caught.value) and "\n" not in str(caught.value)
