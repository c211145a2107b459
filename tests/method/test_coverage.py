"""Does a view see the prior map (``method.coverage``): the fast figures against the pixel-by-pixel
reference, from the render the per-view step makes; the simulated flight's views are taken and the
same views moved off the map (sideways, down to its ground) are refused, offline as a whole run."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest

from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.method import named_method, view_observations
from olsplat_nodes.method.coverage import (
    ALPHA_COVERED,
    CoverageGate,
    MapCoverage,
    _map_coverage_reference,
    map_coverage,
)
from olsplat_nodes.method.view_step import ViewOffMap
from olsplat_nodes.raster import rasterize
from olsplat_nodes.scene import Camera, read_colmap, read_ply, write_colmap

from ..conftest import camera_for, random_gaussians


@pytest.mark.parametrize(("height", "width", "k"), [(24, 32, 4), (260, 300, 3), (7, 5, 1), (6, 6, 0)])
def test_map_coverage_matches_the_reference(height, width, k):
    """Random alpha and Top-K (-1 entries, uncovered pixels), including a frame large enough that
    the ground is sampled on a grid (260 x 300 > 65,536 pixels)."""
    rng = np.random.default_rng(height * width + k)
    alpha = rng.uniform(0, 1, (height, width)).astype(np.float32)
    alpha[: height // 3] = 0.0  # sky
    ids = rng.integers(-1, 500, (height, width, k)).astype(np.int32)
    means_z = rng.normal(3.0, 2.0, 500)
    fast = map_coverage(alpha, ids, means_z, 42.0)
    slow = _map_coverage_reference(alpha, ids, means_z, 42.0)
    assert fast.coverage == pytest.approx(slow.coverage, abs=1e-12)
    assert fast.coverage == pytest.approx(float((alpha > ALPHA_COVERED).mean()))
    if k == 0:
        assert np.isnan(fast.height_m) and np.isnan(slow.height_m)
    else:
        assert fast.height_m == pytest.approx(slow.height_m, rel=1e-12) and 40 < fast.height_m < 44  # ground ~ -0.3


def test_the_rendered_figures_match_the_reference_on_a_real_render():
    gaussians = random_gaussians(400, 0, seed=3)
    camera = camera_for("PINHOLE_CENTRED", 64, 48)
    rendered = rasterize(gaussians, camera, named_method("outlangsplat").raster)
    assert rendered.topk_ids is not None
    args = (rendered.alpha, rendered.topk_ids, gaussians.means[:, 2], camera.center[2])
    fast, slow = map_coverage(*args), _map_coverage_reference(*args)
    assert fast == slow and 0.1 < fast.coverage < 1.0 and 3.0 < fast.height_m < 5.0  # camera at z = 4


def test_the_gate():
    gate = CoverageGate(0.2, 10.0)
    assert not gate.refuses(MapCoverage(0.5, 60.0))
    assert gate.refuses(MapCoverage(0.19, 60.0))  # too little of the map in view
    assert gate.refuses(MapCoverage(1.0, 2.0))  # inside the map, at its ground
    assert gate.refuses(MapCoverage(0.0, float("nan")))
    assert not CoverageGate(0.0, -1e9).refuses(MapCoverage(0.0, float("nan")))  # off
    with pytest.raises(ValueError, match=r"min_coverage=1\.5"):
        CoverageGate(1.5)


def _moved(camera: Camera, offset) -> Camera:
    pose = camera.world_from_camera.copy()
    pose[:3, 3] += offset
    return Camera(camera.name, camera.width, camera.height, camera.K, pose, camera.dist, camera.model)


def test_the_flight_is_taken_and_the_same_views_off_the_map_are_refused(tiny):
    scene, summary = tiny
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    method, gate = named_method("outlangsplat"), CoverageGate()
    cameras = read_colmap(scene / "sparse" / "0")
    label_maps = np.zeros((1, cameras[0].height, cameras[0].width), np.int32)
    bank = [np.ones((1, 4), np.float32) / 2]
    for camera in cameras:
        *_, stages = view_observations(gaussians, camera, label_maps, bank, method, None, gate)
        assert stages["coverage"] >= 2 * gate.min_coverage and stages["height_m"] > 5 * gate.min_height_m
    assert len(cameras) == summary["views"]
    ground = float(np.percentile(gaussians.means[:, 2], 5))
    for offset in ([5000.0, 0.0, 0.0], [0.0, 0.0, ground + 1.5 - cameras[0].center[2]]):
        with pytest.raises(ViewOffMap) as refused:
            view_observations(gaussians, _moved(cameras[0], offset), label_maps, bank, method, None, gate)
        assert refused.value.name == cameras[0].name and "map coverage" in str(refused.value)


def test_offline_a_run_whose_first_views_do_not_see_the_map_is_an_error(tiny, tmp_path, caplog):
    """``olsplat aggregate``'s pipeline: the tiny flight's cameras moved 5 km east (a wrong
    georeference): a WARN per refused view and one error naming the figures after the first five."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.pipeline import Scene, aggregate_scene

    scene, _ = tiny
    copy = tmp_path / "scene"
    shutil.copytree(scene, copy)
    cameras = read_colmap(copy / "sparse" / "0")
    write_colmap(copy / "sparse" / "0", [_moved(c, [5000.0, 0.0, 0.0]) for c in cameras])
    with caplog.at_level(logging.WARNING, logger="olsplat_nodes.pipeline.offline"):
        with pytest.raises(OlsplatInputError, match="views do not overlap the map: wrong map") as error:
            aggregate_scene(Scene.open(copy), named_method("outlangsplat"), encoder_from_spec(), tmp_path / "out")
    assert "The first 5 views were refused" in str(error.value) and "map coverage 0.0%" in str(error.value)
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(refused) == 5 and cameras[4].name in refused[4], refused
