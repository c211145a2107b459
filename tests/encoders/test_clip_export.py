"""The CLIP ViT that loads open_clip keys, its ONNX export, the tokenizer, and clear errors."""

from __future__ import annotations

import gzip
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from olsplat_nodes.cli import main
from olsplat_nodes.encoders.clip_model import ClipConfig, ClipModel, load_clip
from olsplat_nodes.encoders.onnx_encoder import OnnxEncoder
from olsplat_nodes.encoders.tokenizer import ClipTokenizer
from olsplat_nodes.errors import OlsplatInputError

from ..promised import skip_unless_ci

MERGES = ["t h", "th e</w>", "a d</w>", "r o", "ro ad</w>"]  # a five-merge vocabulary: 512 + 5 + 2 tokens


@pytest.fixture
def vocab(tmp_path) -> Path:
    path = tmp_path / "merges.txt.gz"
    with gzip.open(path, "wt", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "\n".join(MERGES) + "\n")
    return path


def small_config(**changes) -> ClipConfig:
    base = dict(embed_dim=16, image_size=32, patch_size=8, vision_width=128, vision_layers=2,
                context_length=16, vocab_size=519, text_width=128, text_layers=2)  # fmt: skip
    return ClipConfig(**{**base, **changes})


@pytest.fixture
def checkpoint(tmp_path) -> Path:
    torch.manual_seed(0)
    model = ClipModel(small_config())
    path = tmp_path / "small_clip.pt"
    torch.save({"state_dict": {f"module.{k}": v for k, v in model.state_dict().items()}}, path)  # a DDP-style file
    return path


OPEN_CLIP_KEYS = [  # names in an open_clip ViT checkpoint (RemoteCLIP-ViT-B-32.pt has these)
    "positional_embedding", "text_projection", "logit_scale", "token_embedding.weight", "ln_final.weight",
    "ln_final.bias", "visual.class_embedding", "visual.positional_embedding", "visual.proj", "visual.conv1.weight",
    "visual.ln_pre.weight", "visual.ln_post.bias", "visual.transformer.resblocks.0.attn.in_proj_weight",
    "visual.transformer.resblocks.0.attn.in_proj_bias", "visual.transformer.resblocks.0.attn.out_proj.weight",
    "visual.transformer.resblocks.0.ln_1.weight", "visual.transformer.resblocks.1.mlp.c_fc.weight",
    "visual.transformer.resblocks.1.mlp.c_proj.bias", "transformer.resblocks.1.ln_2.bias",
    "transformer.resblocks.0.attn.out_proj.bias", "transformer.resblocks.1.mlp.c_fc.bias",
]  # fmt: skip


def test_parameter_names_are_open_clip_names():
    keys = set(ClipModel(small_config()).state_dict())
    assert set(OPEN_CLIP_KEYS) <= keys
    assert not any(k.startswith("text.") or "attn_mask" in k for k in keys)


def test_config_is_read_off_the_tensors(checkpoint):
    model = load_clip(str(checkpoint))
    assert model.config == small_config()


def test_tokenizer_on_a_known_vocabulary(vocab):
    tokenizer = ClipTokenizer(vocab, context_length=8)
    assert tokenizer.vocab_size == 519
    np.testing.assert_array_equal(
        tokenizer(["The  ROAD", "road"]), [[517, 513, 516, 518, 0, 0, 0, 0], [517, 516, 518, 0, 0, 0, 0, 0]]
    )
    long = tokenizer(["the " * 20])[0]
    assert long[0] == 517 and long[-1] == 518 and (long[1:-1] == 513).all()


def _open_clip_reference():
    """open_clip's own tokenizer module and vocabulary (make's set-up unpacks them into .venv/reference)."""
    folder = Path(sys.prefix) / "reference" / "open_clip"
    if not (folder / "tokenizer.py").is_file():
        skip_unless_ci("tokenizer", f"open_clip's tokenizer files are not in {folder} (make setup puts them there)")
    module_spec = importlib.util.spec_from_file_location("open_clip_tokenizer_reference", folder / "tokenizer.py")
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)  # tokenizer.py imports no other part of open_clip
    return module.SimpleTokenizer(), folder / "bpe_simple_vocab_16e6.txt.gz"


def test_tokenizer_matches_clips_bpe():
    reference, vocab = _open_clip_reference()
    ours = ClipTokenizer(vocab)
    texts = [
        "a photo of a cat", "red roof buildings", "Red-roofed buildings!!", "asphalt road, 2 lanes", "trees",
        "Café  naïve <b>bold</b> &amp; more", "it's the UAV's 3rd flight", "émoji 🚁 drone", "word " * 100, "",
    ]  # fmt: skip
    np.testing.assert_array_equal(ours(texts), reference(texts).numpy())
    np.testing.assert_array_equal(ours(["a photo of a cat"])[0, :7], [49406, 320, 1125, 539, 320, 2368, 49407])


def test_export_and_onnxruntime_agree_with_torch(checkpoint, vocab, tmp_path):
    out = tmp_path / "encoder"
    assert (
        main(
            [
                "export-clip",
                "--checkpoint",
                str(checkpoint),
                "--vocab",
                str(vocab),
                "--out",
                str(out),
                "--name",
                "tiny-clip",
            ]
        )
        == 0
    )
    encoder = OnnxEncoder(out)
    assert (encoder.name, encoder.dim, encoder.input_size) == ("tiny-clip", 16, 32)
    model = load_clip(str(checkpoint))
    crops = np.random.default_rng(0).integers(0, 256, (5, 32, 32, 3), dtype=np.uint8)
    pixels = ((crops / 255.0 - encoder.mean) / encoder.std).transpose(0, 3, 1, 2).astype(np.float32)
    with torch.no_grad():
        expected_images = model.encode_image(torch.from_numpy(pixels)).numpy()
        texts = ["the road", "road", "a red roof", "trees"]
        expected_texts = model.encode_text(torch.from_numpy(encoder.tokenizer(texts))).numpy()
    unit = lambda v: v / np.linalg.norm(v, axis=1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(encoder.encode_images(crops), unit(expected_images), atol=1e-4)
    np.testing.assert_allclose(encoder.encode_text(texts), unit(expected_texts), atol=1e-4)
    assert np.allclose(np.linalg.norm(encoder.encode_text(["x"]), axis=1), 1.0)


def test_bad_checkpoints_and_folders(checkpoint, vocab, tmp_path, capsys):
    torch.save({"visual.conv1.weight": torch.zeros(4, 3, 8, 8)}, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match=r"partial\.pt: not an open_clip CLIP ViT checkpoint"):
        load_clip(str(tmp_path / "partial.pt"))
    state = ClipModel(small_config()).state_dict()
    state["visual.proj"] = torch.zeros(128, 99)  # does not match text_projection's 16
    torch.save(state, tmp_path / "shapes.pt")
    with pytest.raises(ValueError, match=r"shapes\.pt: tensor shapes do not match"):
        load_clip(str(tmp_path / "shapes.pt"))
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert (
        main(
            [
                "export-clip",
                "--checkpoint",
                str(tmp_path / "junk.pt"),
                "--vocab",
                str(vocab),
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 1
    )
    assert "junk.pt: not a readable PyTorch checkpoint" in capsys.readouterr().err

    out = tmp_path / "encoder"
    assert main(["export-clip", "--checkpoint", str(checkpoint), "--vocab", str(vocab), "--out", str(out)]) == 0
    manifest = json.loads((out / "encoder.json").read_text())
    manifest["vocab_size"] = 49408  # as if a different vocabulary had been shipped with this text tower
    (out / "encoder.json").write_text(json.dumps(manifest))
    with pytest.raises(OlsplatInputError, match="not the vocabulary of this text tower"):
        OnnxEncoder(out)
    manifest["vocab_size"], manifest["image_size"] = 519, 64
    (out / "encoder.json").write_text(json.dumps(manifest))
    with pytest.raises(OlsplatInputError, match=r"image\.onnx: takes"):
        OnnxEncoder(out)
    (out / "image.onnx").write_bytes(b"not onnx")
    with pytest.raises(OlsplatInputError, match=r"image\.onnx: not a loadable ONNX model"):
        OnnxEncoder(out)
    (out / "text.onnx").unlink()
    with pytest.raises(OlsplatInputError, match=r"text\.onnx: missing"):
        OnnxEncoder(out)
    with pytest.raises(OlsplatInputError, match=r"encoder\.json: missing"):
        OnnxEncoder(tmp_path)


def test_a_plain_text_vocabulary_is_gzipped_reproducibly(tmp_path):
    """``export-clip --vocab merges.txt`` (not gzipped) stores it gzipped, the same bytes every time."""
    from olsplat_nodes.encoders.export import _gzip_copy

    plain = tmp_path / "merges.txt"
    plain.write_text("#version: 0.2\n" + "\n".join(MERGES) + "\n", encoding="utf-8")
    _gzip_copy(plain, tmp_path / "a.txt.gz")
    _gzip_copy(plain, tmp_path / "b.txt.gz")
    assert gzip.decompress((tmp_path / "a.txt.gz").read_bytes()) == plain.read_bytes()
    assert (tmp_path / "a.txt.gz").read_bytes() == (tmp_path / "b.txt.gz").read_bytes()
    assert ClipTokenizer(tmp_path / "a.txt.gz").vocab_size == 519
