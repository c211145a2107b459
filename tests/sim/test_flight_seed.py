"""``olsplat sim make --flight-seed``: the same town and map flown again on another path, and
without it the flight of before, byte for byte."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from olsplat_nodes.cli import main
from olsplat_nodes.scene import read_colmap, write_colmap
from olsplat_sim.flight import FlightSpec, plan_flight
from olsplat_sim.make import prior_map
from olsplat_sim.presets import PRESETS

# the true centres (metres) of the first and last frame of the tiny preset's seed 0, as made
# before the flight seed existed: users of the default flight rely on these bytes
FIRST_CENTRE = [-28.065205396752937, -27.249254573471532, 60.00293852020252]
LAST_CENTRE = [109.19591373313163, 42.301616972462234, 60.0]


def _make(out, *extra: str) -> dict:
    """``olsplat sim make`` of the tiny town (seed 0) with four views; returns its scene.json."""
    assert main(["sim", "make", "--preset", "tiny", "--seed", "0", "--views", "4", "--out", str(out), *extra]) == 0
    return json.loads((out / "scene.json").read_text())


def test_a_flight_seed_flies_the_same_map_on_another_path(tmp_path):
    plain, summary = tmp_path / "plain", _make(tmp_path / "plain")
    other, record = tmp_path / "f7", _make(tmp_path / "f7", "--flight-seed", "7")
    for same in ("map/point_cloud.ply", "truth/map_labels.npz", "truth/ground_truth.ply"):
        assert (plain / same).read_bytes() == (other / same).read_bytes(), same
    assert record["flight_seed"] == 7 and 0.0 <= record["flight_turn_deg"] < 360.0
    assert record["map_gaussians"] == summary["map_gaussians"] and record["views"] == 4

    cameras, theirs = read_colmap(other / "truth" / "true_poses"), read_colmap(plain / "truth" / "true_poses")
    assert [c.name for c in cameras] == [f"flight7_frame_{i:04d}.jpg" for i in range(4)]  # no name of the plain flight
    assert sorted(p.name for p in (other / "images").glob("*.jpg")) == [c.name for c in cameras]
    distances = [np.linalg.norm(a.center - b.center) for a, b in zip(cameras, theirs, strict=True)]
    assert min(distances) > 5.0, distances  # another path, not the same one with other noise
    sfm = read_colmap(other / "sparse" / "0")
    assert 0 < np.mean([np.linalg.norm(a.center - b.center) for a, b in zip(sfm, cameras, strict=True)]) < 0.5
    axes = [c.world_from_camera[:3, 2] for c in cameras]  # the optical axis, in the world
    targets = [c.center[:2] - c.center[2] * axis[:2] / axis[2] for c, axis in zip(cameras, axes, strict=True)]
    assert np.abs(targets).max() < 50.0  # the view centres stay on the 100 m town

    # the flight is a function of the flight seed: made again without rendering, the same centres
    # (to the rounding of COLMAP's quaternions)
    again = prior_map(dataclasses.replace(PRESETS["tiny"], n_views=4), 0, flight_seed=7)[1]
    np.testing.assert_allclose(again, [c.center for c in cameras], atol=1e-9)


def test_without_a_flight_seed_the_flight_of_before(tiny, tmp_path):
    out, summary = tiny
    record = json.loads((out / "scene.json").read_text())
    assert record["flight_seed"] is None and record["flight_turn_deg"] == 0.0 and summary["flight_seed"] is None
    cameras = read_colmap(out / "truth" / "true_poses")
    assert [c.name for c in cameras] == [f"frame_{i:04d}.jpg" for i in range(12)]
    np.testing.assert_allclose(cameras[0].center, FIRST_CENTRE, rtol=1e-12)
    np.testing.assert_allclose(cameras[-1].center, LAST_CENTRE, rtol=1e-12)
    # the seed's own flight stream, unturned, as documented in make.py
    preset = PRESETS["tiny"]
    rng = np.random.default_rng(np.random.SeedSequence(0).spawn(4)[0])
    spec = FlightSpec(preset.n_views, preset.width, preset.height, altitude_m=preset.altitude_m)
    write_colmap(tmp_path / "planned", [f.camera for f in plan_flight(preset.size_m, spec, rng)], binary=False)
    written = (out / "truth" / "true_poses" / "images.txt").read_bytes()
    assert (tmp_path / "planned" / "images.txt").read_bytes() == written


def test_a_turn_turns_the_poses_and_draws_the_same_numbers():
    """A quarter turn of the pattern: every camera centre turned by 90 degrees about the town's centre."""
    spec = FlightSpec(8, 160, 120, altitude_m=60.0)
    plain = plan_flight(100.0, spec, np.random.default_rng(3))
    turned = plan_flight(100.0, FlightSpec(8, 160, 120, altitude_m=60.0, turn_deg=90.0), np.random.default_rng(3))
    for a, b in zip(plain, turned, strict=True):
        x, y, z = a.camera.center
        np.testing.assert_allclose(b.camera.center, [-y, x, z], atol=1e-9)


def test_a_negative_flight_seed_is_one_clear_error(tmp_path, capsys):
    out = tmp_path / "x"
    assert main(["sim", "make", "--preset", "tiny", "--flight-seed", "-1", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["olsplat sim: error: --flight-seed must be >= 0, got -1"]
    assert not out.exists()  # refused before anything is written
