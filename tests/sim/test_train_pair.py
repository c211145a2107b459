"""The independent encoder pair (sim/train_pair.py): seeds, views, noisy captions, the budget rule, a tiny run."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

pytest.importorskip("torch")

from olsplat_sim import train_pair as tp
from olsplat_sim.labels import LABELS, QUERIES
from olsplat_sim.region_samples import TRAINING_SEED_BASE
from olsplat_sim.train_encoders import vocabulary
from olsplat_sim.zeroshot import label_queries

OLD_PAIR_SEEDS = set(range(1000, 1010))


def test_seeds_are_disjoint():
    a, b = set(tp.DESIGN_A.seeds), set(tp.DESIGN_B.seeds)
    assert len(a) == len(tp.DESIGN_A.seeds) == 10 and len(b) == 10
    assert not a & b
    for seeds in (a, b):
        assert not seeds & OLD_PAIR_SEEDS
        assert not seeds & set(tp.VALIDATION_SEEDS)
        assert min(seeds) >= TRAINING_SEED_BASE  # never a held-out evaluation seed
    assert min(tp.VALIDATION_SEEDS) >= TRAINING_SEED_BASE
    assert not set(tp.VALIDATION_SEEDS) & OLD_PAIR_SEEDS
    assert tp.DESIGN_A.init_seed != tp.DESIGN_B.init_seed and {0, 1}.isdisjoint(
        {tp.DESIGN_A.init_seed, tp.DESIGN_B.init_seed}
    )


def test_designs_differ_in_data_and_model():
    a, b = tp.DESIGN_A, tp.DESIGN_B
    assert a.design.kind != b.design.kind and a.views != b.views and a.captions is not b.captions
    assert a.design.crop.context < b.design.crop.context and a.altitude_scale < 1.0 < b.altitude_scale
    assert set(b.captions) == set(LABELS) and set(a.captions) == set(LABELS)
    caption_texts = {t for texts in b.captions.values() for t in texts}
    assert not caption_texts & {t for texts in a.captions.values() for t in texts}


@pytest.mark.parametrize("design", tp.PAIR, ids=lambda p: p.design.name)
def test_query_words_are_known(design):
    tokenizer = tp._tokenizer(vocabulary(design.captions))
    texts = label_queries() + [text for text, _, _ in QUERIES]
    assert [w for text in texts for w in tokenizer.unknown_words(text)] == []


@pytest.mark.parametrize("design", tp.PAIR, ids=lambda p: p.design.name)
def test_view_planner_keeps_one_kind_at_scaled_altitude(design):
    frames = tp.view_planner(design, 6)(110.0, 80.0, np.random.default_rng(0))
    assert len(frames) == 6
    kinds = {f.kind for f in frames}
    assert kinds == {"nadir"} if design.views == "nadir" else kinds <= {"oblique", "orbit"}
    heights = np.array([f.camera.world_from_camera[2, 3] for f in frames])  # metres above the ground
    assert np.allclose(heights, design.altitude_scale * 80.0, atol=3.0)


def test_noisy_labels_share_and_seed():
    labels = np.random.default_rng(1).integers(0, len(LABELS), 20_000)
    noisy = tp.noisy_labels(labels, 0.15, seed=40)
    assert abs((noisy != labels).mean() - 0.15) < 0.01
    assert np.array_equal(noisy, tp.noisy_labels(labels, 0.15, seed=40))
    assert not np.array_equal(noisy, tp.noisy_labels(labels, 0.15, seed=41))
    assert noisy.min() >= 0 and noisy.max() < len(LABELS)
    assert np.array_equal(tp.noisy_labels(labels, 0.0, seed=40), labels)
    assert tp.DESIGN_B.caption_noise == 0.15 and tp.DESIGN_A.caption_noise == 0.0


@pytest.mark.parametrize(
    "a, b, expected",
    [
        ([40, 50, 56, 60], [45, 54, 57, 62], (2, 2)),  # both first reach T = 55 at rung 2, 1 point apart
        ([40, 56, 60], [30, 45, 58, 70], (1, 2)),  # the first reaching, not the best: 56 and 58
        ([50, 62, 66], [30, 45, 55.5, 70], (0, 2)),  # A's 62 vs B's 55.5: A steps down, 50 is nearer
        ([45, 54.9, 70], [30, 56, 60], (1, 1)),  # A jumps to 70 at T: 14 points stronger, steps to 54.9
        ([40, 48, 45], [30, 52, 58], (1, 1)),  # A never reaches T: its best, 48; B steps down to 52
        ([56, 70], [57, 80], (0, 0)),  # the first rung reaches T for both
        ([40, 52, 52], [44, 47, 49], (1, 2)),  # neither reaches T: best each, earlier on a tie; 3 apart: kept
        ([40, 56, 60], [20, 30, 40], (0, 2)),  # B's best 40; A steps down to its 40 (rung 0)
        ([50, 60, 60], [57, 58], (1, 0)),  # within 3 points: no step-down
    ],
)
def test_choose_rungs(a, b, expected):
    assert tp.choose_rungs(a, b, target=55.0, max_gap=3.0) == expected


def test_choose_rungs_defaults_are_the_rule():
    assert tp.TARGET_MIOU == 55.0 and tp.MAX_GAP_MIOU == 3.0
    assert tp.RUNG_EPOCHS == (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0)
    assert tp.choose_rungs([40, 56], [30, 54]) == (1, 1)  # 2 points apart at T = 55


def test_choose_rungs_rejects_an_empty_or_unscanned_ladder():
    with pytest.raises(ValueError, match="score per rung"):
        tp.choose_rungs([], [60.0])
    with pytest.raises(ValueError, match="rung 1 is not scored"):
        tp.choose_rungs([40.0, None, 60.0], [60.0])  # a higher rung scored does not end the scan
    with pytest.raises(ValueError, match="rung 2 is not scored"):
        tp.choose_rungs([56.0], [40.0, 50.0, None])  # never reached T so far: every rung is needed


def test_next_to_score_is_the_lowest_first_scan():
    assert tp.next_to_score([None, None, None], 55) == 0
    assert tp.next_to_score([40, None, None], 55) == 1
    assert tp.next_to_score([40, 56, None], 55) is None  # reached T
    assert tp.next_to_score([40, 50, 54], 55) is None  # every rung scored
    assert tp.next_to_score([None, 80, 90], 55) == 0


def _lazy(full, target):
    scores = [None] * len(full)
    while (i := tp.next_to_score(scores, target)) is not None:
        scores[i] = full[i]
    return scores


@pytest.mark.parametrize("seed", range(200))
def test_lazy_scoring_chooses_as_full_scoring(seed):
    rng = np.random.default_rng(seed)
    n_a, n_b = rng.integers(1, 12, 2)
    steps = rng.normal(3.0, 5.0, (2, 11))  # not monotone: a rung may score below the one before
    full_a = list(np.round(30 + np.cumsum(steps[0][:n_a]), 1))
    full_b = list(np.round(35 + np.cumsum(steps[1][:n_b]), 1))
    lazy_a, lazy_b = _lazy(full_a, 55.0), _lazy(full_b, 55.0)
    assert tp.choose_rungs(lazy_a, lazy_b) == tp.choose_rungs(full_a, full_b)
    first = next((i for i, s in enumerate(full_a) if s >= 55.0), None)
    assert sum(s is not None for s in lazy_a) == (len(full_a) if first is None else first + 1)  # no more than needed


class _Finished:
    def poll(self):
        return 0


def test_tiny_run_scores_lazily_and_ships_the_chosen_rungs(tmp_path, monkeypatch):
    """``run_pair`` on a tiny real training run (1 scene, 2 views) with a stand-in scorer and ONNX
    export (an hour of ``olsplat eval`` and the exporter's minutes are not a unit test)."""
    import json

    import torch

    torch.set_num_threads(1)
    monkeypatch.setattr(tp, "validation_scenes", lambda folder, seeds, log: [folder / "val2000"])
    exported = []

    def fake_export(design, image_tower, text_tower, vocab, out, trained_on=None):
        assert isinstance(image_tower, torch.nn.Module) and isinstance(text_tower, torch.nn.Module)
        folder = out / design.name
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "encoder.json").write_text(json.dumps({"name": design.name, "trained_on": trained_on}))
        exported.append(folder)
        return folder

    monkeypatch.setattr(tp, "export_design", fake_export)
    scored = []

    def fake_score(folder, scenes, log, crops=None):  # A reaches T at its first rung, B only at its second
        name, epochs = folder.name, float(folder.parent.name)
        scored.append((name, epochs))
        return {"2000": {("olsplat-nadir32", 0.5): 60.0, ("olsplat-oblique48", 0.5): 40.0}.get((name, epochs), 57.0)}

    def train_now(p, work, n_seeds, views, validation_views, rungs, validation_seeds):
        tp.train_rungs(p, work, n_seeds, views, validation_views, rungs, lambda _: None, validation_seeds)
        return _Finished()

    out = tmp_path / "assets"
    report = tp.run_pair(tmp_path / "work", out, n_seeds=1, views=2, validation_views=1, rungs=(0.5, 1.0),
                         log=lambda _: None, validation_seeds=(2000,), score=fake_score,
                         start_training=train_now)  # fmt: skip
    assert scored == [("olsplat-nadir32", 0.5), ("olsplat-oblique48", 0.5), ("olsplat-oblique48", 1.0)]
    a, b = (report["designs"][p.design.name] for p in tp.PAIR)
    assert a["chosen"]["epochs"] == 0.5 and a["chosen"]["miou_mean"] == 60.0
    assert b["chosen"]["epochs"] == 1.0 and b["chosen"]["miou"] == {"2000": 57.0}
    assert [r["epochs"] for r in b["ladder"]] == [0.5, 1.0] and "miou" not in a["ladder"][1]
    assert json.loads((tmp_path / "work" / "train_pair.json").read_text())["target_miou"] == 55.0
    cached = json.loads((tmp_path / "work" / "scores.json").read_text())
    assert cached["olsplat-oblique48"]["1"]["miou"] == {"2000": 57.0}
    assert exported[-2:] == [out / "olsplat-nadir32", out / "olsplat-oblique48"]
    for p in tp.PAIR:
        folder = out / p.design.name
        manifest = json.loads((folder / "encoder.json").read_text())
        assert (
            "validation outlangsplat mIoU" in manifest["trained_on"]
            and "of a 1-epoch one-cycle run" in (manifest["trained_on"])
        )
        for line in (folder / "SHA256SUMS").read_text().splitlines():
            digest, name = line.split("  ")
            assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest
    # a rerun continues from the cache: nothing is trained, scored or exported again, the same choice
    again = tp.run_pair(tmp_path / "work", None, n_seeds=1, views=2, validation_views=1, rungs=(0.5, 1.0),
                        log=lambda _: None, validation_seeds=(2000,), score=None, start_training=None)  # fmt: skip
    assert again["designs"]["olsplat-oblique48"]["chosen"] == b["chosen"] and len(exported) == 5
