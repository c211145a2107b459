"""``olsplat sim make --changes``: a later flight over the same map after stated changes, with the truth
of what changed (per prior-map Gaussian, per object, per view)."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.scene import read_colmap
from olsplat_sim.annotate import rasterize_annotation
from olsplat_sim.change_spec import KINDS, ChangeSpec, changes_rng, polygon_area
from olsplat_sim.change_truth import mark_map
from olsplat_sim.changes import apply_changes
from olsplat_sim.labels import LABEL
from olsplat_sim.make import make_dataset
from olsplat_sim.presets import PRESETS
from olsplat_sim.scene import generate_scene

TINY = dataclasses.replace(PRESETS["tiny"], n_views=4)


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """(plain, changed): flight 7 of the tiny town (seed 0) without and with ``--changes default``."""
    root = tmp_path_factory.mktemp("changes")
    make_dataset(TINY, 0, root / "plain", log=lambda *_: None, flight_seed=7)
    make_dataset(
        TINY, 0, root / "changed", log=lambda *_: None, flight_seed=7, changes=ChangeSpec.parse("default", 100)
    )
    return root / "plain", root / "changed"


def _records(folder) -> list[dict]:
    return json.loads((folder / "truth" / "changes" / "changes.json").read_text())["changes"]


def _masks(folder) -> dict[str, np.ndarray]:
    return {
        p.stem: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted((folder / "truth/changes/masks").glob("*"))
    }


def test_the_map_stays_the_one_of_before(flights):
    plain, changed = flights
    for same in ("map/point_cloud.ply", "truth/map_labels.npz", "map/georef.json", "sparse/0/images.txt"):
        assert (plain / same).read_bytes() == (changed / same).read_bytes(), same
    for other in ("truth/ground_truth.ply", "images/flight7_frame_0003.jpg", "annotations/flight7_frame_0003.json"):
        assert (plain / other).read_bytes() != (changed / other).read_bytes(), other
    assert "changes" not in json.loads((plain / "scene.json").read_text())  # scene.json of before, byte for byte


def test_default_is_a_mix_of_every_kind_sized_to_the_town(flights):
    _, changed = flights
    records = _records(changed)
    assert sorted({r["kind"] for r in records}) == sorted(KINDS)
    assert [r["id"] for r in records] == list(range(len(records)))
    summary = json.loads((changed / "scene.json").read_text())["changes"]
    assert summary["records"] == len(records) and min(summary["per_kind"].values()) >= 1
    for r in records:
        polygon = np.asarray(r["footprint"])
        assert polygon_area(polygon) > 0 and r["area_m2"] == pytest.approx(polygon_area(polygon), abs=1e-3)
        assert r["z_range"][0] < r["z_range"][1]
    flooded = next(r for r in records if r["kind"] == "flooded")
    assert flooded["area_m2"] == pytest.approx(150.0, rel=1e-3) and flooded["label_after"] is None
    tiny, large = ChangeSpec.default(100.0), ChangeSpec.default(230.0)
    assert tiny.cars_added == 2 and large.cars_added == 11 and large.burnt_m2 > 5 * tiny.burnt_m2


def test_an_added_car_is_annotated_as_a_car_where_there_was_none(flights):
    plain, changed = flights
    added = [r for r in _records(changed) if r["kind"] == "car_added"]
    seen = 0
    for stem, mask in _masks(changed).items():
        for r in added:
            where = mask == r["id"] + 1
            if where.sum() < 20:
                continue
            seen += 1
            labels, instances = rasterize_annotation(changed / "annotations" / f"{stem}.json")
            before, _ = rasterize_annotation(plain / "annotations" / f"{stem}.json")
            car = (labels == LABEL["car"]) & (instances == r["instance"])  # the mask also holds its shadow
            assert car.sum() > 10 and np.mean(where[car]) > 0.9
            assert np.mean(before[car] == LABEL["car"]) < 0.2  # the same camera saw no car there
    assert seen >= 1


def test_a_recoloured_roof_changes_its_buildings_label(flights):
    plain, changed = flights
    (roof,) = [r for r in _records(changed) if r["kind"] == "roof_recoloured"]
    assert roof["label_before"] != roof["label_after"]
    found = 0
    for folder, label in ((plain, roof["label_before"]), (changed, roof["label_after"])):
        for path in (folder / "annotations").glob("*.json"):
            shapes = [s for s in json.loads(path.read_text())["shapes"] if s["group_id"] == roof["instance"]]
            assert {s["label"] for s in shapes} <= {label}
            found += len(shapes)
    assert found > 0


def test_map_changed_marks_a_removed_car_and_a_felled_tree(flights):
    _, changed = flights
    change = np.load(changed / "truth/changes/map_changed.npz")["change_id"]
    labels = np.load(changed / "truth/map_labels.npz")
    assert change.dtype == np.int32 and len(change) == len(labels["instance"])
    for kind in ("car_removed", "tree_felled"):
        r = next(r for r in _records(changed) if r["kind"] == kind)
        own = labels["instance"] == r["instance"]
        assert own.sum() > 20 and (change[own] >= 0).all() and np.mean(change[own] == r["id"]) > 0.8, kind
    assert 0 < np.mean(change >= 0) < 0.2  # the changes, not the town


def test_none_changes_nothing():
    truth = generate_scene(20_000, 100.0, 0)
    changed = apply_changes(truth, ChangeSpec.parse("none", 100.0), changes_rng(7))
    assert changed.records == [] and (changed.before_ids == -1).all() and (changed.after_ids == -1).all()
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert getattr(changed.truth.gaussians, name).tobytes() == getattr(truth.gaussians, name).tobytes()
    assert (changed.truth.label == truth.label).all()
    marked = mark_map(changed, truth.layout, truth.gaussians.means, truth.instance, truth.category)
    assert (marked == -1).all()


def test_masks_show_changes_where_they_are_in_view(flights):
    plain, changed = flights
    records = _records(changed)
    cameras = {c.name.rsplit(".", 1)[0]: c for c in read_colmap(changed / "truth" / "true_poses")}
    masks = _masks(changed)
    assert set(masks) == set(cameras) and any(m.any() for m in masks.values())
    for stem, mask in masks.items():
        camera = cameras[stem]
        for k in np.unique(mask[mask > 0]) - 1:  # a change in the mask lies in the camera's view
            r = records[k]
            points = np.c_[
                np.asarray(r["footprint"] + (r["footprint_before"] or [])),
                np.zeros(len(r["footprint"]) + len(r["footprint_before"] or [])),
            ]
            local = (camera.camera_from_world[:3, :3] @ points.T + camera.camera_from_world[:3, 3:]).T
            pixels = (camera.K @ local.T).T
            pixels = pixels[:, :2] / pixels[:, 2:]
            margin = 40
            assert ((pixels > -margin) & (pixels < [camera.width + margin, camera.height + margin])).all(1).any(), r
        # where the picture changed a lot, the mask says so
        a = cv2.imread(str(plain / "images" / f"{stem}.jpg")).astype(int)
        b = cv2.imread(str(changed / "images" / f"{stem}.jpg")).astype(int)
        differs = np.abs(a - b).sum(-1) > 60
        near = cv2.dilate((mask > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert np.mean(near[differs]) > 0.9 if differs.sum() > 50 else True


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--changes", "default"], "olsplat sim: error: --changes needs --flight-seed: changes happen between two "
         "flights of a town"),
        (["--flight-seed", "1", "--changes", "cars_flying=2"], "olsplat sim: error: --changes: unknown item "
         "'cars_flying=2' (kinds: default, none, cars_moved, cars_added, cars_removed, objects_added, roofs_damaged, "
         "roofs_recoloured, trees_felled, flooded_m2, burnt_m2)"),
        (["--flight-seed", "1", "--changes", "cars_added=two"], "olsplat sim: error: --changes: cars_added needs an "
         "integer, got 'two'"),
        (["--flight-seed", "1", "--changes", "burnt_m2=-5"], "olsplat sim: error: --changes: burnt_m2 must be >= 0, "
         "got -5"),
        (["--flight-seed", "1", "--changes", "trees_felled=500"], "olsplat sim: error: --changes: 500 trees to fell "
         "but the town has 11"),
    ],
)  # fmt: skip
def test_a_bad_spec_is_one_line(tmp_path, capsys, extra, message):
    out = tmp_path / "x"
    assert main(["sim", "make", "--preset", "tiny", "--views", "2", "--out", str(out), *extra]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [message]
    assert not out.exists() or not any(out.iterdir())  # refused before anything is written
