"""`olsplat sim make`: files a user's tools read, annotations that match the pictures, determinism."""

from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest
from plyfile import PlyData

from olsplat_nodes.raster import rasterize
from olsplat_nodes.scene import read_colmap, read_ply
from olsplat_sim import LABELS, generate_scene
from olsplat_sim.annotate import label_maps, rasterize_annotation
from olsplat_sim.labels import CATEGORY, LABEL
from olsplat_sim.make import BACKGROUND, make_dataset
from olsplat_sim.presets import PRESETS


def _digest(folder):
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_same_seed_same_bytes(tiny, tmp_path):
    out, _ = tiny
    again = tmp_path / "again"
    make_dataset(PRESETS["tiny"], 0, again, log=lambda *_: None)
    assert _digest(out) == _digest(again)


def test_layout_of_the_output(tiny):
    out, summary = tiny
    for path in ("map/point_cloud.ply", "sparse/0/cameras.txt", "sparse/0/images.txt", "queries.json", "replay.mcap",
                 "truth/map_labels.npz", "truth/ground_truth.ply", "preview/contact_sheet.jpg", "preview/overview.jpg",
                 "images/timestamps.csv", "scene.json"):  # fmt: skip
        assert (out / path).is_file(), path
    assert len(list((out / "images").glob("*.jpg"))) == summary["views"] == 12
    assert len(list((out / "annotations").glob("*.json"))) == 12


def test_map_and_cameras_read_back(tiny):
    out, summary = tiny
    vertex = PlyData.read(str(out / "map" / "point_cloud.ply"))["vertex"]  # standard readers
    assert len(vertex) == summary["map_gaussians"]
    import open3d

    cloud = open3d.io.read_point_cloud(str(out / "map" / "point_cloud.ply"))
    assert len(cloud.points) == summary["map_gaussians"]
    gaussians = read_ply(out / "map" / "point_cloud.ply")
    truth = np.load(out / "truth" / "map_labels.npz")
    assert len(truth["label"]) == len(gaussians)
    assert (truth["label"][truth["category"] == CATEGORY["floater"]] == -1).all()
    assert 1.25 < summary["map_gaussians"] / summary["ground_truth_gaussians"] < 1.45  # + 40 % translucent layers
    cameras = read_colmap(out / "sparse" / "0")
    true_cameras = read_colmap(out / "truth" / "true_poses")
    assert [c.name for c in cameras] == sorted(p.name for p in (out / "images").glob("*.jpg"))
    offsets = [np.linalg.norm(a.center - b.center) for a, b in zip(cameras, true_cameras, strict=True)]
    assert 0 < np.mean(offsets) < 0.5  # structure-from-motion error: small, not zero
    for camera in cameras:
        image = cv2.imread(str(out / "images" / camera.name))
        assert image.shape == (camera.height, camera.width, 3)
        assert 60.0 - 3 < camera.center[2] < 60.0 + 3  # the preset's altitude


def test_annotations_agree_with_rendered_labels(tiny):
    out, _ = tiny
    truth = generate_scene(PRESETS["tiny"].n_gaussians, PRESETS["tiny"].size_m, 0)
    agreement = []
    for camera in read_colmap(out / "truth" / "true_poses"):
        doc = json.loads((out / "annotations" / camera.name.replace(".jpg", ".json")).read_text())
        annotated, annotated_instances = rasterize_annotation(doc)
        result = rasterize(truth.gaussians, camera, background=BACKGROUND)
        rendered, instances = label_maps(
            result.topk_ids, result.topk_weights, result.alpha, truth.label, truth.instance
        )
        labelled = rendered >= 0
        agreement.append((annotated[labelled] == rendered[labelled]).mean())
        same = labelled & (annotated == rendered)
        assert (annotated_instances[same] == instances[same]).mean() > 0.97
        for shape in doc["shapes"]:
            points = np.asarray(shape["points"])
            assert shape["label"] in LABELS
            assert (
                (points >= 0).all() and (points[:, 0] <= camera.width).all() and (points[:, 1] <= camera.height).all()
            )
    assert np.mean(agreement) > 0.93 and min(agreement) > 0.85


def test_queries_name_annotated_instances(tiny):
    out, _ = tiny
    queries = json.loads((out / "queries.json").read_text())
    groups = set()
    for doc in (out / "annotations").glob("*.json"):
        groups |= {(s["label"], s["group_id"]) for s in json.loads(doc.read_text())["shapes"]}
    texts = {q["text"]: q for q in queries["queries"]}
    assert {"red roof buildings", "buildings", "road", "trees"} <= set(texts)
    assert texts["trees"]["instances"], "trees are instances"
    assert texts["road"]["instances"] == []
    for query in queries["queries"]:
        assert set(query["labels"]) <= set(LABELS)
        for instance in query["instances"]:
            assert any((label, instance) in groups for label in query["labels"])


def test_trees_hide_parts_of_annotated_buildings(tiny):
    """Occlusion occurs: a building is partly hidden by a crown in some view."""
    out, _ = tiny
    truth = generate_scene(PRESETS["tiny"].n_gaussians, PRESETS["tiny"].size_m, 0)
    no_trees = truth.gaussians.subset(truth.category != CATEGORY["tree"])
    labels_no_trees = truth.label[truth.category != CATEGORY["tree"]]
    instances_no_trees = truth.instance[truth.category != CATEGORY["tree"]]
    building = np.isin(truth.label, [LABEL[f"{c} roof buildings"] for c in ("red", "blue", "white", "grey")])
    hidden = []
    for camera in read_colmap(out / "truth" / "true_poses"):
        with_trees = rasterize(truth.gaussians, camera)
        without = rasterize(no_trees, camera)
        _, inst_with = label_maps(
            with_trees.topk_ids, with_trees.topk_weights, with_trees.alpha, truth.label, truth.instance
        )
        _, inst_without = label_maps(
            without.topk_ids, without.topk_weights, without.alpha, labels_no_trees, instances_no_trees
        )
        for instance in np.unique(truth.instance[building]):
            full = (inst_without == instance).sum()
            if full > 50:
                hidden.append(1.0 - (inst_with == instance).sum() / full)
    hidden = np.array(hidden)
    assert ((hidden > 0.05) & (hidden < 0.95)).any(), "no building is partly behind a tree"


@pytest.mark.parametrize("preset", ["tiny"])
def test_every_category_present(preset):
    truth = generate_scene(PRESETS[preset].n_gaussians * 5, 160.0, 3)
    present = set(np.unique(truth.category).tolist())
    assert present == set(range(len(CATEGORY))) - {CATEGORY["floater"]}


def test_cli_options_and_motion_blur(tmp_path, capsys):
    """Fewer views, a faster rate and a long shutter: blur softens the frame, stamps follow the rate."""
    from olsplat_nodes.cli import main
    from olsplat_nodes.sources.replay_log import read_replay

    common = ["sim", "make", "--preset", "tiny", "--views", "3", "--rate", "4"]
    assert main([*common, "--out", str(tmp_path / "sharp")]) == 0
    assert main([*common, "--out", str(tmp_path / "blur"), "--motion-blur", "0.5"]) == 0
    frames = list(read_replay(tmp_path / "sharp" / "replay.mcap"))
    assert len(frames) == 3 and frames[1].stamp_ns - frames[0].stamp_ns == 250_000_000

    def sharpness(path):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        return cv2.Laplacian(image, cv2.CV_32F).var()

    name = "images/frame_0001.jpg"
    assert sharpness(tmp_path / "blur" / name) < 0.8 * sharpness(tmp_path / "sharp" / name)
    assert main(["sim", "make", "--preset", "tiny", "--views", "0", "--out", str(tmp_path / "x")]) == 1
    assert "--views and --gaussians must be positive" in capsys.readouterr().err


def test_the_overview_carries_a_true_scale_bar_and_a_north_arrow():
    from olsplat_nodes.scene import Camera, intrinsics, look_at
    from olsplat_sim.preview import _scale_and_north

    pixels, focal, altitude = 400, 300.0, 150.0  # 2 px per metre on the ground
    top = Camera(
        "t", pixels, pixels, intrinsics(focal, focal, 200, 200), look_at([0, 0, altitude], [0, 1e-6, 0], (0, 1, 0))
    )
    image = np.zeros((pixels, pixels, 3), np.uint8)
    _scale_and_north(image, top.camera_from_world, focal, pixels)
    bar_row = image[pixels - 27]  # inside the bar (bottom - 3)
    drawn = np.flatnonzero(bar_row.max(1) > 200)  # the white half of the bar
    assert 0.12 * pixels <= 2 * (drawn.max() - drawn.min() + 1) <= 0.30 * pixels  # 50 m at 2 px/m = 100 px, half white
    column = image[: pixels - 40, pixels - 30 : pixels - 20].max(axis=(1, 2))
    top_of_arrow = np.flatnonzero(column > 200).min()
    assert top_of_arrow < pixels - 90  # the arrow points up the picture: +y, north
