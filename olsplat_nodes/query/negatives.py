"""The texts a query must beat when the operator names none: an aerial land-cover vocabulary.

A query's mask is where its text beats every negative (``heatmap.relevancy_mask``). Generic
negatives ("object", "things", "stuff", "texture") are far from every class of an aerial scene,
so almost anything beats them: on the tiny simulated flight the live "red roof buildings" mask
covered 26 % of a view, road and bare ground included, where the offline query with the flight's
own labels marked the roofs alone. The classes a UAV sees over a town are few and known; with
them as negatives a roof has to look more like "red roof buildings" than like "road" or "grey
roof buildings" to be marked. The vocabulary is the simulator's label set, worded as its
queries (the shipped encoders were trained on those words; a real CLIP reads them as well).

A vocabulary entry that says the same as the query is dropped: the exact text (any case), and
any entry whose text embedding is closer than ``MAX_TEXT_COSINE`` to the query's (with a real
CLIP, "red roofs" against "red roof buildings"), so that a query never has to beat itself.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .heatmap import CANONICAL_NEGATIVES

AERIAL_VOCABULARY: tuple[str, ...] = (
    "red roof buildings",
    "blue roof buildings",
    "white buildings",
    "grey roof buildings",
    "road",
    "lawn",
    "trees",
    "cars",
    "parking lot",
    "bare ground",
    "pavement",
)
MAX_TEXT_COSINE = 0.9  # an entry this close to the query's text embedding says the same thing


def vocabulary_negatives(
    text: str, encoder, vocabulary: Sequence[str] = AERIAL_VOCABULARY, max_cosine: float = MAX_TEXT_COSINE
) -> list[str]:
    """The entries of ``vocabulary`` a query ``text`` must beat: all but the text itself and
    those whose embedding (``encoder.encode_text``: unit rows) has a cosine >= ``max_cosine``
    with the text's. When none is left (a vocabulary of one), the generic negatives."""
    text = text.strip()
    kept = [v for v in vocabulary if v.strip().lower() != text.lower()]
    if kept:
        embeddings = np.asarray(encoder.encode_text([text, *kept]), np.float32)
        cosines = embeddings[1:] @ embeddings[0]
        kept = [v for v, c in zip(kept, cosines, strict=True) if c < max_cosine]
    return kept or list(CANONICAL_NEGATIVES)
