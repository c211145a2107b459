"""The query server's text-embedding cache gives the encoder's embeddings, bounded."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.encoders.spec import encoder_from_spec
from olsplat_nodes.query.answer import CachedTexts


class Counting:
    def __init__(self, encoder):
        self.encoder, self.name, self.calls = encoder, encoder.name, []

    def encode_text(self, texts):
        self.calls.append(list(texts))
        return self.encoder.encode_text(texts)


def test_cached_embeddings_equal_the_encoders_and_stay_bounded():
    encoder = encoder_from_spec()
    counting = Counting(encoder)
    cached = CachedTexts(counting, size=3)
    texts = ["road", "trees", "road", "red roof buildings"]
    np.testing.assert_array_equal(cached.encode_text(texts), encoder.encode_text(texts))
    assert counting.calls == [["road", "trees", "red roof buildings"]]  # each text once
    np.testing.assert_array_equal(cached.encode_text(["trees", "road"]), encoder.encode_text(["trees", "road"]))
    assert len(counting.calls) == 1  # all from the cache
    cached.encode_text(["lawn"])  # a fourth text: the least recently used one ("red roof buildings") goes
    assert list(cached.cache) == ["trees", "road", "lawn"]
    assert cached.name == encoder.name


def test_a_codebook_map_answers_through_its_centres_as_its_decoded_rows(tmp_path):
    """The query server keeps a codebook map as codes and centres (``decode=False``): the chosen
    Gaussians and the heatmap equal those of the same map decoded to [N, D] rows."""
    from olsplat_nodes.aggregate.codebook import compress, fit_codebook
    from olsplat_nodes.query.answer import answer_query
    from olsplat_nodes.storage import LanguageMap

    from ..conftest import camera_for, random_gaussians

    encoder = encoder_from_spec()
    rng = np.random.default_rng(3)
    gaussians = random_gaussians(500, 0, seed=8)
    texts = encoder.encode_text(["road", "trees", "red roof buildings", "cars"])
    features = texts[rng.integers(0, 4, 500)] + 0.2 * rng.normal(size=(500, texts.shape[1]))
    features /= np.linalg.norm(features, axis=1, keepdims=True)
    observed = rng.random(500) < 0.8
    features[~observed] = 0
    centres = fit_codebook(features.astype(np.float32), 16)
    LanguageMap(
        features.astype(np.float16), observed, encoder.name, codes=compress(features, centres), centres=centres
    ).save(tmp_path / "map.npz")
    compact = LanguageMap.load(tmp_path / "map.npz", decode=False)
    dense = LanguageMap.load(tmp_path / "map.npz")
    assert compact.features.shape == (0, texts.shape[1]) and len(compact) == 500 and dense.features.shape[0] == 500
    camera = camera_for("PINHOLE_CENTRED", 40, 30)
    a = answer_query(compact, gaussians, encoder, "road", ["trees", "cars"], camera)
    b = answer_query(dense, gaussians, encoder, "road", ["trees", "cars"], camera)
    assert a.chosen.sum() > 20 and np.array_equal(a.chosen, b.chosen)
    np.testing.assert_allclose(a.heatmap, b.heatmap, atol=1e-5)
    np.testing.assert_array_equal(a.mask, b.mask)
    # with the map's voxel index, a codebook map's clustering takes its choice in the index's
    # order from the centres' verdicts: the same instances as from the chosen mask
    from olsplat_nodes.query.answer import QueryFeatures
    from olsplat_nodes.query.localize import VoxelIndex, instances_in_3d

    index = VoxelIndex.build(gaussians.means, 0.3)
    features_of_map = QueryFeatures.of(compact)
    for text in ("road", "trees", "cars"):
        with_index = answer_query(
            compact, gaussians, encoder, text, ["road", "trees", "cars", "red roof buildings"],
            cluster_radius=0.3, min_points=3, features=features_of_map, voxel_index=index,
        )  # fmt: skip
        expected = instances_in_3d(gaussians.means, with_index.chosen, 0.3, 3, index=index)
        assert with_index.instances == expected and len(expected) > 0


def test_a_codebook_answer_counts_its_chosen_gaussians_without_the_mask(tmp_path):
    """With its voxel index, a codebook map's answer counts the chosen Gaussians from the K
    centres (what the query server replies) and makes the [N] mask only when asked: the count
    equals the mask's, and the mask the dense map's."""
    from olsplat_nodes.aggregate.codebook import compress, fit_codebook
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.query.answer import QueryFeatures, answer_query
    from olsplat_nodes.query.localize import VoxelIndex, instances_in_3d
    from olsplat_nodes.storage import LanguageMap

    from ..conftest import random_gaussians

    encoder = encoder_from_spec()
    rng = np.random.default_rng(7)
    gaussians = random_gaussians(3000, 0, seed=7, spread=3.0)
    texts = encoder.encode_text(["road", "trees", "cars", "lawn"])
    features = texts[rng.integers(0, 4, 3000)] + 0.3 * rng.normal(size=(3000, texts.shape[1]))
    features /= np.linalg.norm(features, axis=1, keepdims=True)
    observed = rng.random(3000) > 0.2
    features[~observed] = 0
    centres = fit_codebook(features.astype(np.float32), 24)
    LanguageMap(
        features.astype(np.float16), observed, encoder.name, codes=compress(features, centres), centres=centres
    ).save(tmp_path / "map.npz")
    compact, dense = LanguageMap.load(tmp_path / "map.npz", decode=False), LanguageMap.load(tmp_path / "map.npz")
    index = VoxelIndex.build(gaussians.means, 0.5)
    features_of_map = QueryFeatures.of(compact)
    for text in ("road", "trees", "cars", "lawn"):
        negatives = [t for t in ("road", "trees", "cars", "lawn") if t != text]
        lazy = answer_query(
            compact, gaussians, encoder, text, negatives, cluster_radius=0.5, min_points=3,
            features=features_of_map, voxel_index=index,
        )  # fmt: skip
        assert lazy._chosen is None  # not made yet
        plain = answer_query(dense, gaussians, encoder, text, negatives, cluster_radius=0.5, min_points=3)
        assert lazy.chosen_count == int(lazy.chosen.sum()) == plain.chosen_count > 0
        np.testing.assert_array_equal(lazy.chosen, plain.chosen)
        assert not lazy.chosen[~observed].any()
        expected = instances_in_3d(gaussians.means, plain.chosen, 0.5, 3, index=index)  # the same grid
        assert lazy.instances == expected and len(expected) > 0
