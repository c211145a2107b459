"""``olsplat bench robustness``, the stress test: ``--mode swap`` is the sweep it was, and
``--mode lookalike`` confuses the tiny scene's surfaces with the encoder's own look-alikes, the
same way in every view at correlation 1. (The corruption itself is tested against its
reference in tests/evaluate/test_confusion.py.)"""

from __future__ import annotations

import hashlib
import json
import re
import shutil

import numpy as np
import pytest

from olsplat_nodes.bench.robustness import confuse, corrupted_features, scene_lookalikes
from olsplat_nodes.cli import main


def _old_confuse(bank, p, rng):
    """The sweep before --mode existed (robustness.py at 60d352c), verbatim."""
    out = []
    for features in bank:
        swapped = rng.random(len(features)) < p
        confused = features.copy()
        confused[swapped] = features[rng.integers(0, len(features), int(swapped.sum()))]
        out.append(confused)
    return out


@pytest.fixture(scope="module")
def scene(tiny, tmp_path_factory):
    """A copy of the tiny scene (its feature cache is written beside it) and the encoder."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.pipeline import Scene

    folder = tmp_path_factory.mktemp("robustness") / "scene"
    shutil.copytree(tiny[0], folder)
    return Scene.open(folder), encoder_from_spec()


def test_confusion_replaces_rows_by_rows_of_the_same_view():
    rng = np.random.default_rng(0)
    bank = [rng.normal(size=(40, 8)).astype(np.float32), rng.normal(size=(200, 8)).astype(np.float32)]
    assert all(np.array_equal(a, b) for a, b in zip(confuse(bank, 0.0, rng), bank, strict=True))
    confused = confuse(bank, 0.5, np.random.default_rng(1))
    for before, after in zip(bank, confused, strict=True):
        changed = (before != after).any(1)
        assert 0.3 < changed.mean() < 0.7  # about p of the rows (a few draw themselves)
        rows = {r.tobytes() for r in before}
        assert all(r.tobytes() in rows for r in after)  # every row is some region's feature of this view
    assert np.array_equal(confuse(bank, 0.5, np.random.default_rng(1))[1], confused[1])  # seeded: same for every method


def test_swap_mode_is_the_sweep_it_was(scene):
    rng = np.random.default_rng(5)
    bank = [rng.normal(size=(30, 8)).astype(np.float32), rng.normal(size=(90, 8)).astype(np.float32)]
    out = confuse(bank, 0.3, np.random.default_rng([0, 3]))
    # recorded from the sweep before --mode existed: the same numbers, bit for bit
    digest = hashlib.sha256(b"".join(o.tobytes() for o in out)).hexdigest()
    assert digest == "7b612f4136210d00c70f97aede429040651be8b86fc15dafe29fb117bd179075"

    from olsplat_nodes.pipeline import view_features

    scene, encoder = scene
    features_of = corrupted_features(scene, encoder, "swap", 0.3, seed=4)
    for index, camera in enumerate(scene.cameras):
        label_maps, bank = view_features(scene, camera, encoder)
        maps, got = features_of(camera)
        np.testing.assert_array_equal(maps, label_maps)
        for a, b in zip(got, _old_confuse(bank, 0.3, np.random.default_rng([4, index])), strict=True):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="'lookalike' or 'swap'"):
        corrupted_features(scene, encoder, "shuffle", 0.3, seed=4)


def test_lookalike_mode_repeats_a_surface_s_confusion_in_every_view_at_correlation_one(scene):
    from olsplat_nodes.pipeline import view_features

    scene, encoder = scene
    truths, looks = measured = scene_lookalikes(scene, encoder)
    assert set(truths) == {c.name for c in scene.cameras}  # the tiny scene annotates every view
    np.testing.assert_allclose(looks.rows.sum(1), 1.0)
    assert (np.diag(looks.rows) == 0).all() and looks.counts.sum() > 100

    clean = corrupted_features(scene, encoder, "lookalike", 0.0, seed=0, rho=1.0, lookalikes=measured)
    confused = corrupted_features(scene, encoder, "lookalike", 0.5, seed=0, rho=1.0, lookalikes=measured)
    received: dict[int, set[int]] = {}  # surface -> labels its finest regions received over the views
    for camera in scene.cameras:
        _, bank = view_features(scene, camera, encoder)
        assert all(np.array_equal(a, b) for a, b in zip(clean(camera)[1], bank, strict=True))
        after, levels = confused(camera)[1][-1], truths[camera.name][-1]
        for r in np.flatnonzero(levels.surface >= 0):
            donor = np.flatnonzero((bank[-1] == after[r]).all(1))
            if (after[r] == bank[-1][r]).all():
                label = -1
            elif len(donor):
                label = int(levels.truth[donor[0]])
            else:  # the flight's mean feature of the look-alike, or its text
                label = int(np.flatnonzero(((looks.prototypes[-1] == after[r]) | (looks.texts == after[r])).all(1))[0])
            received.setdefault(int(levels.surface[r]), set()).add(label)
    assert len(received) > 20
    assert all(len(labels) == 1 for labels in received.values()), received
    assert {-1} in received.values() and any(labels != {-1} for labels in received.values())


def test_robustness_benchmark_runs(tiny, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    table, scores = tmp_path / "r.md", tmp_path / "r.json"
    argv = ["bench", "robustness", "--scene", str(scene), "--methods", "topk", "--confusion", "0.5"]
    assert main([*argv, "--md", str(table), "--json", str(scores)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"encoder region accuracy \d+\.\d % on \d+ regions; look-alikes: ", out), out
    printed = re.search(r"p 0\.50\s+topk\s+mIoU\s+(\d+\.\d)\s+mAcc\s+\d+\.\d\s+Loc@50\s+(\d+\.\d)", out)
    assert printed
    text = table.read_text()
    assert "look-alike confusion p, correlation 0.7 across views (a stress test)" in text
    assert f"| topk | **{printed[1]} / {printed[2]}** |" in text  # one scene: the mean is the run
    assert json.loads(scores.read_text())["topk"]["0.5"]["scene"]["mIoU"] == pytest.approx(float(printed[1]), abs=0.05)
    assert main([*argv, "--mode", "swap", "--features", "2d,2d3d"]) == 0
    out = capsys.readouterr().out
    assert "p = share of each view's regions given another region's feature" in out
    assert re.search(r"p 0\.50\s+topk 2d\s+mIoU\s+\d+\.\d", out) and re.search(
        r"p 0\.50\s+topk 2d3d\s+mIoU\s+\d+\.\d", out
    ), out
    assert main(["bench", "robustness", "--scene", str(scene), "--methods", "topk", "--features", "3d"]) == 1
    assert "--features" in capsys.readouterr().err
    assert main([*argv, "--correlation", "1.5"]) == 1
    assert "--correlation" in capsys.readouterr().err
