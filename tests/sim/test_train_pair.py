"""The independent encoder pair (sim/train_pair.py): seeds, views, noisy captions, the budget rule, a tiny run."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

pytest.importorskip("torch")

from olsplat_nodes.encoders.onnx_encoder import OnnxEncoder
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
    "acc_a, acc_b, expected",
    [
        ([0.50, 0.70, 0.76, 0.80], [0.60, 0.74, 0.77, 0.85], (2, 2)),  # both first reach T at rung 2, 1 point apart
        ([0.50, 0.76, 0.80], [0.40, 0.60, 0.74, 0.85], (1, 2)),  # 9 points apart: B steps down to 0.74
        ([0.60, 0.85, 0.90], [0.40, 0.60, 0.76, 0.80], (1, 2)),  # A jumps past B's band: 0.85 is nearer than 0.60
        ([0.70, 0.74, 0.86], [0.40, 0.77, 0.80], (1, 1)),  # A's first rung over T is 9 points stronger: 0.74
        ([0.40, 0.50, 0.60], [0.40, 0.76, 0.80], (2, 1)),  # A never reaches T: its last rung; B's 0.76 is nearest
        ([0.80, 0.90], [0.70, 0.78], (0, 1)),  # rung 0 reaches T for A; B first at rung 1
    ],
)
def test_choose_rungs(acc_a, acc_b, expected):
    assert tp.choose_rungs(acc_a, acc_b, target=0.75, max_gap=0.03) == expected


def test_choose_rungs_rejects_an_empty_ladder():
    with pytest.raises(ValueError, match="accuracy per rung"):
        tp.choose_rungs([], [0.8])


def test_tiny_run_exports_loadable_encoders(tmp_path):
    import torch

    torch.set_num_threads(1)
    report = tp.train_pair(
        tmp_path,
        1,
        2,
        validation_views=1,
        rungs=(0.5, 1.0),
        log=lambda _: None,
        validation_seeds=tp.VALIDATION_SEEDS[:1],
    )
    assert (tmp_path / "train_pair.json").is_file()
    for p in tp.PAIR:
        folder = tmp_path / p.design.name
        entry = report["designs"][p.design.name]
        assert [r["epochs"] for r in entry["ladder"]] == [0.5, 1.0] and entry["crops"] > 0
        for line in (folder / "SHA256SUMS").read_text().splitlines():
            digest, name = line.split("  ")
            assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest
        encoder = OnnxEncoder(folder, 1)
        assert encoder.name == p.design.name and encoder.input_size == p.design.image_size
        crops = np.random.default_rng(0).integers(0, 256, (3, p.design.image_size, p.design.image_size, 3), np.uint8)
        for rows in (encoder.encode_images(crops), encoder.encode_text(label_queries())):
            assert np.allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-5)


def test_refine_stronger_stops_where_it_crosses_the_weaker(monkeypatch):
    ladders = [
        [{"step": 10, "accuracy": 0.60}, {"step": 20, "accuracy": 0.80}],
        [{"step": 5, "accuracy": 0.50}, {"step": 9, "accuracy": 0.70}],
    ]
    calls = {}

    def fine_ladder(design, samples, validation, rungs, log, steps, schedule_epochs):
        calls.update(design=design, steps=list(steps), schedule_epochs=schedule_epochs)
        return [{"step": s, "accuracy": 0.60 + 0.02 * (s - 10)} for s in steps]

    monkeypatch.setattr(tp, "train_ladder", fine_ladder)
    refined = tp.refine_stronger(ladders, (1, 1), ["a", "b"], None, rungs=(1.0, 8.0), log=lambda _: None)
    assert calls == {"design": tp.DESIGN_A, "steps": list(range(11, 21)), "schedule_epochs": 8}  # the same run
    assert refined["encoder"] == 0 and refined["rung"]["step"] == 15  # 0.70 reaches B's 0.70
    assert tp.refine_stronger([ladders[0], ladders[0]], (1, 1), ["a", "b"], None) is None  # no gap
