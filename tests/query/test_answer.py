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
