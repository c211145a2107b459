"""The compact encoders shipped in the package: they load, differ, and know the simulator's world."""

from __future__ import annotations

import json

import numpy as np
import pytest

from olsplat_nodes.encoders.shipped import SHIPPED, default_encoder, shipped_encoder
from olsplat_nodes.encoders.tokenizer import WordTokenizer
from olsplat_sim.zeroshot import evaluate, label_queries


def test_shipped_encoders_load_and_differ():
    a, b = (shipped_encoder(name) for name in SHIPPED)
    assert (a.dim, b.dim) == (64, 64)
    assert a.input_size != b.input_size and a.crop_config != b.crop_config
    texts = label_queries()
    for encoder in (a, b, default_encoder()):
        embedded = encoder.encode_text(texts)
        np.testing.assert_allclose(np.linalg.norm(embedded, axis=1), 1.0, atol=1e-5)
        assert (embedded @ embedded.T)[~np.eye(len(texts), dtype=bool)].max() < 0.999, "queries stay distinct"
    with pytest.raises(ValueError, match="no shipped encoder"):
        shipped_encoder("ViT-L-14")


def test_zero_shot_on_a_held_out_scene():
    encoders = {"fusion": default_encoder(), SHIPPED[0]: shipped_encoder(SHIPPED[0])}
    results = evaluate(encoders, seeds=[7], views=4)
    assert results["fusion"]["n"] > 100
    assert results["fusion"]["accuracy"] > 0.5  # chance is 1/11
    with pytest.raises(ValueError, match="evaluation seeds must be below"):
        evaluate(encoders, seeds=[1000], views=1)


def test_word_tokenizer(tmp_path):
    path = tmp_path / "vocab.json"
    path.write_text(json.dumps(["red", "roof", "building", "grass"]))
    tokenizer = WordTokenizer(path, context_length=4)
    assert tokenizer.vocab_size == 6
    np.testing.assert_array_equal(
        tokenizer(["Red roof buildings", "grass", "purple", "roof roof roof roof roof"]),
        [[2, 3, 4, 0], [5, 0, 0, 0], [1, 0, 0, 0], [3, 3, 3, 3]],
    )
    path.write_text('{"not": "a list"}')
    with pytest.raises(ValueError, match="JSON list of strings"):
        WordTokenizer(path)
