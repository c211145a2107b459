"""Region crops, encoder fusion and per-view feature banks, with real (tiny, random) ONNX encoders."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from olsplat_nodes.encoders import CropConfig, FusedEncoder, encode_regions, region_crops
from olsplat_nodes.encoders.clip_model import ClipModel
from olsplat_nodes.encoders.export import export_model
from olsplat_nodes.encoders.onnx_encoder import OnnxEncoder
from olsplat_nodes.regions import RegionConfig, propose_regions

from ..regions.test_regions import blocks_image
from .test_clip_export import MERGES, small_config


@pytest.fixture(scope="module")
def encoders(tmp_path_factory):
    """Two exported random CLIPs of different crop sizes (exporting takes seconds: once per module)."""
    import gzip

    folder = tmp_path_factory.mktemp("encoders")
    vocab = folder / "merges.txt.gz"
    with gzip.open(vocab, "wt", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "\n".join(MERGES) + "\n")
    out = []
    for seed, size in ((1, 32), (2, 48)):
        torch.manual_seed(seed)
        model = ClipModel(small_config(image_size=size))
        out.append(OnnxEncoder(export_model(model, vocab, folder / f"enc{seed}", f"enc{seed}")))
    return out


def test_crops_center_the_region_and_fade_the_rest():
    image, truth = blocks_image()
    crops = region_crops(image, truth, 64, CropConfig(context=0.25, fade=1.0))
    assert crops.shape == (4, 64, 64, 3) and crops.dtype == np.uint8
    red = crops[1]  # region 1: the red rectangle
    centre = red[24:40, 24:40].reshape(-1, 3).mean(0)
    assert centre[0] > 140 and centre[1] < 90  # red inside
    np.testing.assert_allclose(red[2, 32], [124, 116, 104], atol=3)  # faded to grey outside (fade = 1)
    with pytest.raises(ValueError, match="differ in size"):
        region_crops(image, truth[:10], 64)


def test_fusion_is_the_weighted_similarity(encoders):
    a, b = encoders
    fused = FusedEncoder([a, b], [0.6, 0.4])
    assert fused.dim == a.dim + b.dim
    rng = np.random.default_rng(0)
    crops = [rng.integers(0, 256, (3, 32, 32, 3), dtype=np.uint8), rng.integers(0, 256, (3, 48, 48, 3), dtype=np.uint8)]
    texts = ["the road", "road"]
    image_f, text_f = fused.encode_crops(crops), fused.encode_text(texts)
    expected = (
        0.6 * a.encode_images(crops[0]) @ a.encode_text(texts).T
        + 0.4 * b.encode_images(crops[1]) @ b.encode_text(texts).T
    )
    np.testing.assert_allclose(image_f @ text_f.T, expected, atol=1e-5)
    summed = FusedEncoder([a, a], [0.6, 0.4], mode="sum")
    assert summed.dim == a.dim
    with pytest.raises(ValueError, match="one non-negative weight per encoder"):
        FusedEncoder([a, b], [1.0])
    with pytest.raises(ValueError, match="mode='sum' needs encoders of one dimension"):
        FusedEncoder([a, _Wider(b)], mode="sum")


class _Wider:
    """An encoder of another dimension (only its ``dim`` is looked at)."""

    def __init__(self, base):
        self.name, self.input_size, self.dim = "wider", base.input_size, base.dim + 1


def test_feature_bank_per_level(encoders):
    image, _ = blocks_image(3)
    levels = propose_regions(image, RegionConfig(level_counts=(4, 12)))
    bank = encode_regions(image, levels, FusedEncoder(encoders, [0.6, 0.4]), batch=5)
    assert [f.shape for f in bank.features] == [(count, 32) for count in levels.counts]
    for features in bank.features:
        np.testing.assert_allclose(np.linalg.norm(features, axis=1), 1.0, atol=1e-5)
    single = encode_regions(image, levels, encoders[0])
    assert single.dim == 16 and single.encoder == "enc1"
    with pytest.raises(ValueError, match="uint8 RGB"):
        encode_regions(image.astype(float), levels, encoders[0])


@pytest.mark.parametrize("config", [CropConfig(), CropConfig(context=0.5, fade=0.3, min_box_px=40)])
def test_crops_equal_the_numpy_reference(config):
    from olsplat_nodes.encoders._reference import region_crops_reference

    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    labels = (np.arange(60)[:, None] // 7) * 12 + np.arange(80)[None, :] // 7  # blocks, some at the edges
    labels[rng.random(labels.shape) < 0.05] = -1  # pixels of no region
    labels[labels == 5] = 6  # an id with no pixels: a grey crop
    for size in (16, 40):  # shrinking and enlarging crops
        np.testing.assert_array_equal(
            region_crops(image, labels, size, config), region_crops_reference(image, labels, size, config)
        )
