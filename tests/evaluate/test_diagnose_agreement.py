"""The diagnostics' statistics against slow, obviously-correct versions, and the geometry of
the per-pixel rays and ground cells against a camera's own projection."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from olsplat_nodes.evaluate.diagnose.agreement import (
    accuracy_by_bins,
    icc_oneway,
    pair_statistics,
    region_accuracy,
    surface_statistics,
)
from olsplat_nodes.evaluate.diagnose.flight import (
    ground_cells,
    majority_per_surface,
    off_nadir_deg,
    pixel_rays,
    region_truth,
    surface_ids,
)
from olsplat_nodes.scene import Camera
from olsplat_nodes.scene.camera import intrinsics, look_at


def _icc_reference(groups, values):
    """ICC(1) from its definition: the ANOVA mean squares computed with loops."""
    by_group: dict[int, list[float]] = {}
    for g, v in zip(groups.tolist(), values.tolist(), strict=True):
        by_group.setdefault(g, []).append(float(v))
    by_group = {g: vs for g, vs in by_group.items() if len(vs) >= 2}
    k = len(by_group)
    n = sum(len(vs) for vs in by_group.values())
    grand = sum(sum(vs) for vs in by_group.values()) / n
    ssb = sum(len(vs) * (sum(vs) / len(vs) - grand) ** 2 for vs in by_group.values())
    ssw = sum(sum((v - sum(vs) / len(vs)) ** 2 for v in vs) for vs in by_group.values())
    msb, msw = ssb / (k - 1), ssw / (n - k)
    n0 = (n - sum(len(vs) ** 2 for vs in by_group.values()) / n) / (k - 1)
    return (msb - msw) / (msb + (n0 - 1) * msw)


def test_icc_matches_its_definition_and_its_extremes():
    rng = np.random.default_rng(0)
    groups = rng.integers(0, 40, 400)
    values = (rng.random(400) < 0.2).astype(float)
    assert icc_oneway(groups, values) == pytest.approx(_icc_reference(groups, values), abs=1e-12)
    shared = rng.random(40) < 0.3  # each group wrong everywhere or nowhere
    assert icc_oneway(groups, shared[groups].astype(float)) == pytest.approx(1.0)
    assert abs(icc_oneway(rng.integers(0, 200, 20000), (rng.random(20000) < 0.3).astype(float))) < 0.05
    assert np.isnan(icc_oneway(np.arange(10), np.ones(10)))  # no group seen twice


def _pair_reference(truth, a, b):
    wrong_a = [int(t != x) for t, x in zip(truth, a, strict=True)]
    wrong_b = [int(t != x) for t, x in zip(truth, b, strict=True)]
    phi = np.corrcoef(wrong_a, wrong_b)[0, 1]
    both = [i for i in range(len(truth)) if wrong_a[i] and wrong_b[i]]
    return {
        "phi": phi,
        "both_wrong": len(both) / len(truth),
        "both_wrong_if_independent": np.mean(wrong_a) * np.mean(wrong_b),
        "same_wrong_label": np.mean([a[i] == b[i] for i in both]),
    }


def test_pair_statistics_match_their_definitions():
    rng = np.random.default_rng(1)
    truth = rng.integers(0, 5, 3000)
    a = np.where(rng.random(3000) < 0.2, rng.integers(0, 5, 3000), truth)
    b = np.where(rng.random(3000) < 0.5, a, np.where(rng.random(3000) < 0.25, rng.integers(0, 5, 3000), truth))
    got, want = pair_statistics(truth, a, b), _pair_reference(truth, a, b)
    for key in want:
        assert got[key] == pytest.approx(want[key], abs=1e-12), key
    assert pair_statistics(truth, truth, a)["phi"] == 0.0  # an encoder never wrong: undefined, reported 0
    assert pair_statistics(truth, a, a)["phi"] == pytest.approx(1.0)


def test_surface_statistics_count_every_and_some_views():
    surfaces = np.array([1, 1, 1, 2, 2, 3, 3, 3, 4])
    errors = np.array([1, 1, 1, 0, 1, 0, 0, 0, 1], bool)  # 1 wrong everywhere, 2 sometimes, 3 never, 4 once
    got = surface_statistics(surfaces, errors)
    assert got["surfaces"] == 3  # surface 4 was seen once
    assert got["wrong_every_view"] == pytest.approx(1 / 3) and got["wrong_some_views"] == pytest.approx(1 / 3)
    assert got["error_icc"] == pytest.approx(_icc_reference(surfaces[:8], errors[:8].astype(float)))


def test_accuracy_and_bins():
    truth, predicted = np.array([0, 1, 2, 3]), np.array([0, 1, 0, 0])
    assert region_accuracy(truth, predicted) == 0.5
    bins = accuracy_by_bins(truth, predicted, np.array([5.0, 15.0, 15.0, 45.0]), [0, 10, 20, 90])
    assert bins == {
        "0-10": {"accuracy": 1.0, "regions": 1},
        "10-20": {"accuracy": 0.5, "regions": 2},
        "20-90": {"accuracy": 0.0, "regions": 1},
    }


def _camera(eye, target) -> Camera:
    return Camera("v", 40, 30, intrinsics(30.0, 30.0, 20.0, 15.0), look_at(eye, target))


def test_pixel_rays_hit_the_ground_where_the_camera_projects_it():
    camera = _camera((3.0, -4.0, 50.0), (10.0, 5.0, 0.0))
    rays = pixel_rays(camera)
    for v, u in itertools.product((0, 14, 29), (0, 20, 39)):
        ray = rays[v, u]
        point = camera.center + ray * (-camera.center[2] / ray[2])  # on z = 0
        local = camera.camera_from_world @ np.append(point, 1.0)
        assert local[2] > 0
        projected = camera.K @ (local[:3] / local[2])
        assert projected[:2] == pytest.approx([u + 0.5, v + 0.5], abs=1e-9)
    nadir = _camera((0.0, 0.0, 50.0), (0.0, 0.0, 0.0))
    assert off_nadir_deg(pixel_rays(nadir))[15, 20] == pytest.approx(
        np.degrees(np.arctan(0.5 * np.sqrt(2) / 30)), abs=1e-6
    )
    cells = ground_cells(nadir, pixel_rays(nadir), cell_m=10.0)
    # a nadir view over the origin: opposite corners land in mirrored cells (floor(x) + floor(-x) = -1)
    assert (cells[0, 0] + cells[29, 39]).tolist() == [-1, -1] and (cells[0, 39] + cells[29, 0]).tolist() == [-1, -1]
    assert 3 <= np.abs(cells[0, 0]).max() <= 4  # the corner's ray reaches ~33 m out at 50 m height


def test_region_truth_and_surfaces():
    regions = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 2, 2]])
    labels = np.array([[3, 3, 4, -1], [3, 1, -1, -1], [5, 5, 6, 6]])
    assert region_truth(regions, labels, 7, 0.6).tolist() == [3, -1, -1]  # region 1: 1 of 4 pixels is 4; 2: 2 of 4
    assert region_truth(regions, labels, 7, 0.25).tolist() == [3, 4, 5]
    instances = np.array([[7, 7, -1, -1], [7, -1, -1, -1], [-1, -1, -1, -1]])
    cells = np.zeros((3, 4, 2), np.int64)
    cells[:, 2:, 0] = 1
    ids = surface_ids(labels, instances, cells)
    assert ids[0, 0] == ids[1, 0] != ids[1, 1]  # one instance; another label is another surface
    assert ids[2, 0] == ids[2, 1] != ids[2, 2]  # stuff: one label in one cell
    assert ids[0, 3] == -1
    per_pixel = {"a": np.array([[3, 3, 0, 0], [3, 3, 0, 0], [5, 5, 5, 5]])}
    surfaces, majority = majority_per_surface(ids, per_pixel, 7, min_px=2)
    assert dict(zip(surfaces.tolist(), majority["a"].tolist(), strict=True)) == {
        int(ids[0, 0]): 3,
        int(ids[2, 0]): 5,
        int(ids[2, 2]): 5,
    }
