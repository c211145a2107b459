"""Metrics on hand-made masks; heatmaps and masks; the language map file."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.evaluate import QueryScore, summarize
from olsplat_nodes.query import argmax_masks, heatmaps, relevancy_mask
from olsplat_nodes.storage.snapshot import LanguageMap


def test_iou_accuracy_and_localisation():
    target = np.zeros((10, 10), bool)
    target[:, :5] = True  # 50 px: instance 1 rows 0-4, instance 2 rows 5-9
    instances = np.full((10, 10), -1)
    instances[:5, :5], instances[5:, :5] = 1, 2
    labelled = np.ones((10, 10), bool)
    labelled[:, 9] = False  # unlabelled column: predictions there do not count
    predicted = np.zeros((10, 10), bool)
    predicted[:3, :5] = True  # 15 px of instance 1 (60 % of it)
    predicted[:, 8:] = True  # 10 false positives, 10 of them unlabelled
    score = QueryScore()
    score.add_view(predicted, target, labelled, np.where(target, instances, -1))
    assert (score.tp, score.fp, score.fn) == (15, 10, 35)
    assert score.iou == pytest.approx(100 * 15 / 60) and score.accuracy == pytest.approx(30.0)
    # 25 px instances are under MIN_INSTANCE_PX = 50: no localisation targets
    assert score.instances == 0
    big = QueryScore()
    big_target = np.zeros((20, 20), bool)
    big_target[:10] = True  # one 200 px instance, half covered
    big_pred = np.zeros((20, 20), bool)
    big_pred[:5] = True
    big.add_view(big_pred, big_target, np.ones((20, 20), bool), np.where(big_target, 7, -1))
    nothing = QueryScore()
    nothing.add_view(big_pred, np.zeros((20, 20), bool), np.ones((20, 20), bool), None)  # no target in this town
    summary = summarize({"q": big, "absent one": nothing})
    assert (summary["loc40"], summary["loc50"], summary["loc60"]) == (100.0, 0.0, 0.0)  # covered 50 %: > 40 % only
    assert summary["mIoU"] == pytest.approx(50.0) and summary["absent"] == ["absent one"]


def test_heatmaps_and_masks():
    features = np.zeros((2, 3, 2), np.float32)
    features[:, 0] = [1, 0]
    features[:, 1] = [0, 2]
    features[:, 2] = [1, 1]
    texts = np.array([[1.0, 0.0], [0.0, 1.0]], np.float32)
    maps = heatmaps(features, texts)
    assert maps.shape == (2, 2, 3)
    np.testing.assert_allclose(maps[0, 0], [1.0, 0.0, np.sqrt(0.5)], atol=1e-6)
    alpha = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 0.1]])
    masks = argmax_masks(maps, alpha)
    assert masks[0, 0].tolist() == [True, False, True] and masks[1, 0].tolist() == [False, True, False]
    assert not masks[:, 1, 2].any()  # uncovered pixel
    np.testing.assert_array_equal(relevancy_mask(maps[1], maps[:1], alpha), masks[1] & (maps[1] > maps[0]))


def test_language_map_file(tmp_path):
    features = np.array([[3.0, 4.0], [0.0, 0.0]], np.float32)
    LanguageMap.from_features(features, np.array([True, False]), "shipped").save(tmp_path / "map.npz")
    loaded = LanguageMap.load(tmp_path / "map.npz")
    np.testing.assert_allclose(loaded.features.astype(np.float32), [[0.6, 0.8], [0.0, 0.0]], atol=1e-3)
    assert loaded.encoder == "shipped" and loaded.observed.tolist() == [True, False]
    assert not list(tmp_path.glob("*.tmp.npz"))
    with pytest.raises(SceneFormatError, match="does not exist"):
        LanguageMap.load(tmp_path / "none.npz")
    np.savez(tmp_path / "old.npz", features=features, observed=[True, True], encoder="x", version=0)
    with pytest.raises(SceneFormatError, match="language map version 0"):
        LanguageMap.load(tmp_path / "old.npz")
    np.savez(tmp_path / "v1.npz", features=features.astype(np.float16), observed=[True, True], encoder="x", version=1)
    assert LanguageMap.load(tmp_path / "v1.npz").form == "float16"  # maps of the first format still load


def test_language_map_codebook_form(tmp_path):
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(6, 16))
    features = np.repeat(directions, 50, axis=0) + 0.01 * rng.normal(size=(300, 16))
    features[7] = 0.0  # never observed
    original = LanguageMap.from_features(features, features.any(1), "shipped")
    original.save(tmp_path / "map.npz", codebook=6)
    loaded = LanguageMap.load(tmp_path / "map.npz")
    assert loaded.form == "codebook" and loaded.features.shape == (300, 16)
    cos = (loaded.features.astype(np.float32) * original.features.astype(np.float32)).sum(1)
    assert (np.delete(cos, 7) > 0.99).all() and not loaded.features[7].any()
    assert (tmp_path / "map.npz").stat().st_size < 0.5 * 300 * 16 * 2  # far below the float16 form
    np.savez(tmp_path / "bad.npz", form="zip", observed=[True], encoder="x", version=2)
    with pytest.raises(SceneFormatError, match="unknown language map form 'zip'"):
        LanguageMap.load(tmp_path / "bad.npz")


def test_rows_normalised_in_place_are_unit_rows_of_the_definition():
    from olsplat_nodes.storage.snapshot import normalise_rows, unit_rows

    rng = np.random.default_rng(4)
    rows = rng.normal(0, 3, (500, 37)).astype(np.float32)
    rows[::7] = 0.0  # never observed: stays 0
    rows[3] *= 1e-6  # short but not 0: still scaled to length 1
    # the plain definition: each row over its Euclidean length
    norm = np.linalg.norm(rows.astype(np.float64), axis=1, keepdims=True)
    expected = np.where(norm > 0, rows / np.maximum(norm, 1e-300), 0.0)
    copy = unit_rows(rows)
    normalise_rows(rows)
    np.testing.assert_array_equal(copy, rows)  # the offline and live maps are bit-identical
    np.testing.assert_allclose(rows, expected, rtol=2e-6, atol=1e-7)
    assert not rows[::7].any()
    np.testing.assert_allclose(np.linalg.norm(rows[1:7], axis=1), 1.0, rtol=1e-6)
