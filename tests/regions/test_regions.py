"""Region proposals: nested levels that cover the image and follow real boundaries."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from olsplat_nodes.regions import RegionConfig, RegionLevels, propose_regions, relabel_contiguous


def blocks_image(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 240x320 picture of three textured rectangles on a background, and its truth labels."""
    rng = np.random.default_rng(seed)
    truth = np.zeros((240, 320), np.int32)
    truth[30:120, 40:150] = 1
    truth[140:220, 60:260] = 2
    truth[20:110, 190:300] = 3
    colors = np.array([[90, 110, 60], [170, 50, 40], [70, 70, 75], [225, 225, 220]], np.float64)
    image = colors[truth] + rng.normal(0, 6, (240, 320, 3))
    return np.clip(image, 0, 255).astype(np.uint8), truth


def _best_iou(levels: RegionLevels, mask: np.ndarray) -> float:
    """The best IoU of any region of any level with ``mask``."""
    best = 0.0
    for level in levels.label_maps:
        ids, overlap = np.unique(level[mask], return_counts=True)
        sizes = np.bincount(level.ravel())[ids]
        best = max(best, float((overlap / (sizes + mask.sum() - overlap)).max()))
    return best


def test_levels_are_nested_cover_the_image_and_hit_their_counts():
    image, _ = blocks_image()
    config = RegionConfig(level_counts=(8, 30, 100))
    levels = propose_regions(image, config)
    assert levels.label_maps.shape == (3, 240, 320)
    assert levels.counts == config.scaled_counts(240, 320)
    assert (levels.label_maps >= 0).all()
    for coarse, fine in pairwise(levels.label_maps):
        pairs = np.unique(np.stack([fine.ravel(), coarse.ravel()], 1), axis=0)
        assert len(pairs) == fine.max() + 1, "every fine region lies inside one coarse region"


def test_work_scale_gives_the_full_size_targets_and_follows_objects():
    """At half resolution: full-size label maps, the full-size region counts, objects still
    found (edges on a 2-pixel grid)."""
    image, truth = blocks_image(1)
    config = RegionConfig(level_counts=(8, 30, 100), work_scale=0.5)
    levels = propose_regions(image, config)
    assert levels.label_maps.shape == (3, 240, 320)
    assert levels.counts == config.scaled_counts(240, 320)
    for obj in (1, 2, 3):
        best = _best_iou(levels, truth == obj)
        assert best > 0.9, f"object {obj}: best region IoU {best:.2f}"
    with pytest.raises(ValueError, match="work_scale"):
        RegionConfig(work_scale=0.0)


def test_objects_come_out_as_regions():
    image, truth = blocks_image(1)
    levels = propose_regions(image, RegionConfig(level_counts=(8, 30, 100)))
    for obj in (1, 2, 3):
        best = _best_iou(levels, truth == obj)
        assert best > 0.9, f"object {obj}: best region IoU {best:.2f}"


def test_deterministic_and_validated():
    image, _ = blocks_image(2)
    a, b = propose_regions(image), propose_regions(image)
    np.testing.assert_array_equal(a.label_maps, b.label_maps)
    with pytest.raises(ValueError, match="uint8 RGB"):
        propose_regions(image.astype(np.float32))
    with pytest.raises(ValueError, match="increasing"):
        RegionConfig(level_counts=(100, 30))
    with pytest.raises(ValueError, match=r"\[L, H, W\]"):
        RegionLevels(np.zeros((4, 4), np.int32))


def test_relabel_contiguous():
    labels = np.array([[7, 7, -1], [3, 9, 3]])
    np.testing.assert_array_equal(relabel_contiguous(labels), [[1, 1, -1], [0, 2, 0]])
    sparse = labels * 10_000_000  # ids far apart: the sorting path
    np.testing.assert_array_equal(relabel_contiguous(np.where(labels < 0, -1, sparse)), [[1, 1, -1], [0, 2, 0]])
    rng = np.random.default_rng(0)
    random = rng.integers(-1, 50, (30, 40))
    _, expected = np.unique(random[random >= 0], return_inverse=True)
    np.testing.assert_array_equal(relabel_contiguous(random)[random >= 0], expected)
    assert (relabel_contiguous(random)[random < 0] == -1).all()


def test_regions_respect_simulator_labels(tmp_path):
    """On a rendered UAV frame, the finest level's regions are nearly pure in label."""
    import json

    import cv2

    from olsplat_sim.annotate import rasterize_annotation
    from olsplat_sim.make import make_dataset
    from olsplat_sim.presets import PRESETS

    make_dataset(PRESETS["tiny"], 5, tmp_path, log=lambda *_: None)
    purity = []
    for name in ("frame_0001", "frame_0008"):
        image = cv2.imread(str(tmp_path / "images" / f"{name}.jpg"))[..., ::-1].copy()
        labels, _ = rasterize_annotation(json.loads((tmp_path / "annotations" / f"{name}.json").read_text()))
        finest = propose_regions(image).label_maps[-1]
        valid = labels >= 0
        table = np.zeros((finest.max() + 1, labels.max() + 1))
        np.add.at(table, (finest[valid], labels[valid]), 1)
        purity.append(table.max(1).sum() / valid.sum())
    assert min(purity) > 0.8, purity
