"""One text query against a language map, as a pure function: what ``olsplat query`` prints and
what the query server sends back to the ground station.

Rule (documented in docs/method.md, "Queries"): a Gaussian is chosen when it is observed and its cosine
with the query beats its cosine with every negative text; chosen Gaussians are clustered into
3D instances. In a view, the rendered heatmap H_q must beat every negative's heatmap
(LERF-style relevancy mask); the mask's connected components are the 2D instances.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..errors import OlsplatInputError
from ..native import library
from ..scene import Camera, Gaussians
from ..storage.snapshot import LanguageMap
from .heatmap import CANONICAL_NEGATIVES, FeatureImages, relevancy_mask, render_heatmaps, threshold_mask
from .localize import Instance3D, Region2D, VoxelIndex, default_cluster_radius, instances_in_3d, regions_in_view
from .winners import gather_verdicts, winning_rows

_EMPTY = np.zeros(0, np.bool_)  # the kernels' "no observed mask"


@dataclass
class QueryAnswer:
    text: str
    negatives: list[str]
    chosen_count: int  # Gaussians that pick the query over every negative
    instances: list[Instance3D]  # world metres, largest first
    heatmap: np.ndarray | None = None  # [H, W] float32 cosine H_q in [-1, 1], when a view was given
    negative_heatmaps: np.ndarray | None = None  # [negatives, H, W] float32
    alpha: np.ndarray | None = None  # [H, W] float32 rendered opacity
    mask: np.ndarray | None = None  # [H, W] bool
    regions: list[Region2D] = field(default_factory=list)  # mask components, largest first
    unknown_words: list[str] = field(default_factory=list)  # words of the text the encoder does not know
    # makes ``chosen``: a codebook map's answer counts its chosen Gaussians from the K centres and
    # makes the [N] mask only if someone asks (the query server does not: 12-18 ms at 5.2M)
    chosen_of: Callable[[], np.ndarray] | None = field(default=None, repr=False)
    _chosen: np.ndarray | None = field(default=None, repr=False)

    @property
    def chosen(self) -> np.ndarray:
        """[N] bool: the Gaussians that pick the query over every negative (observed ones only)."""
        if self._chosen is None:
            assert self.chosen_of is not None, "an answer is made with chosen or chosen_of"
            self._chosen = self.chosen_of()
        return self._chosen


@dataclass
class QueryFeatures:
    """A map's features as queries use them: unit rows of a table and, for a codebook map, each
    Gaussian's row in it. Relevance then scores the K centres, not the N Gaussians (what keeps
    queries fast on a map of millions), and rendering reads the centres through the rows, so
    the [N, D] features are never made. ``of`` keeps a map's float16 rows as they are where the
    C kernels are built (half the memory and half the bytes each query reads; they read float16
    exactly), and widens them to float32 for the numba kernels otherwise."""

    table: np.ndarray  # [M, D] float16 or float32: row g is Gaussian g (M = N), or the codebook's centres (M = K)
    rows: np.ndarray | None = None  # [N] int32 row of ``table`` per Gaussian (-1: never observed)
    # codebook maps: rows in a VoxelIndex's order, made at the first query that clusters
    _ordered: dict[int, tuple[VoxelIndex, np.ndarray]] = field(default_factory=dict, repr=False)
    # codebook maps: [K] int64 observed Gaussians per centre (made with the features: ~20 ms for 5M)
    _per_row: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.rows is not None:
            self._per_row = np.bincount(self.rows[self.rows >= 0], minlength=len(self.table)).astype(np.int64)

    @staticmethod
    def of(language_map: LanguageMap) -> QueryFeatures:
        if language_map.codes is not None and language_map.centres is not None:
            rows = language_map.codes.astype(np.int32)
            rows[(rows == 65_535) | ~language_map.observed] = -1  # no feature: as a dense map's 0 row
            return QueryFeatures(_table(language_map.centres), rows)
        return QueryFeatures(_table(language_map.features))

    def winners(self, embeddings: np.ndarray, observed: np.ndarray | None = None) -> np.ndarray:
        """[N] bool: the Gaussians whose feature is closer to embeddings[0] than to every other
        row of embeddings [Q, D] (unit rows), among the ``observed`` ones ([N] bool) when given.
        ``winners.winning_rows``: one pass over the rows, or over the K centres and then one
        gather over the N rows of a codebook map (row -1, never observed, never wins)."""
        seen = _EMPTY if observed is None else np.ascontiguousarray(observed, np.bool_)
        embeddings = np.ascontiguousarray(embeddings, np.float32)
        if self.rows is None:
            return winning_rows(self.table, embeddings, seen)
        return gather_verdicts(winning_rows(self.table, embeddings, _EMPTY), self.rows, seen)

    def winners_in_order(self, embeddings: np.ndarray, index: VoxelIndex) -> np.ndarray | None:
        """``winners`` in ``index.order`` ([N'] bool), for a codebook map: a sequential gather
        from the K centres' verdicts instead of a random one from N (what a query's clustering
        takes). None for a dense map."""
        rows = self.rows_in_order(index)
        if rows is None:
            return None
        verdicts = winning_rows(self.table, np.ascontiguousarray(embeddings, np.float32), _EMPTY)
        return gather_verdicts(verdicts, rows, _EMPTY)

    def count_winners(self, embeddings: np.ndarray) -> int | None:
        """For a codebook map, ``winners(embeddings).sum()`` from the K centres' verdicts and the
        number of observed Gaussians per centre, without the [N] gather; None for a dense map."""
        if self._per_row is None:
            return None
        verdicts = winning_rows(self.table, np.ascontiguousarray(embeddings, np.float32), _EMPTY)
        return int(self._per_row[verdicts].sum())

    def rows_in_order(self, index: VoxelIndex) -> np.ndarray | None:
        """[N'] int32 ``rows`` in ``index.order``, made once per index (~50 ms for 5M: a
        query server makes them when a map version arrives, not at its first query); None
        for a dense map."""
        if self.rows is None:
            return None
        cached = self._ordered.get(id(index))
        if cached is None or cached[0] is not index:
            cached = self._ordered[id(index)] = (index, self.rows[index.order])
        return cached[1]


def _table(rows: np.ndarray) -> np.ndarray:
    """A map's rows as the query kernels read them: float16 kept where the C kernels are built
    (no copy), float32 otherwise (no copy when they already are)."""
    keep = np.asarray(rows).dtype == np.float16 and library() is not None
    return np.ascontiguousarray(rows, np.float16 if keep else np.float32)


class CachedTexts:
    """A text encoder that remembers its embeddings: a ground station sends the same negatives
    (and often the same queries) again and again. Bounded: the oldest ``size`` texts go first."""

    def __init__(self, encoder, size: int = 4096):
        self.encoder, self.size, self.name = encoder, size, encoder.name
        self.cache: OrderedDict[str, np.ndarray] = OrderedDict()
        self.lock = threading.Lock()  # the query server's warm query may encode beside a real one

    def unknown_words(self, text: str) -> list[str]:
        return list(getattr(self.encoder, "unknown_words", lambda _t: [])(text))

    def encode_text(self, texts: list[str]) -> np.ndarray:
        """[len(texts), D] unit rows, as the encoder's."""
        with self.lock:
            missing = list(dict.fromkeys(t for t in texts if t not in self.cache))
            if missing:
                self.cache.update(zip(missing, self.encoder.encode_text(missing), strict=True))
            rows = []
            for text in texts:
                self.cache.move_to_end(text)
                rows.append(self.cache[text])
            while len(self.cache) > self.size:
                self.cache.popitem(last=False)
            return np.stack(rows)


def encoder_for_map(language_map: LanguageMap):
    """The text encoder that embeds queries into the map's feature space."""
    from ..encoders.spec import encoder_from_spec

    spec = language_map.encoder
    return encoder_from_spec("shipped" if spec.startswith("olsplat-cnn64:") else spec)


def answer_query(
    language_map: LanguageMap,
    gaussians: Gaussians,
    encoder,
    text: str,
    negatives: list[str] | tuple[str, ...] = CANONICAL_NEGATIVES,
    camera: Camera | None = None,
    threshold: float | None = None,
    images: FeatureImages | None = None,
    image_key: Hashable = None,
    cluster_radius: float | None = None,
    min_points: int = 20,
    features: QueryFeatures | None = None,
    voxel_index: VoxelIndex | None = None,
    locate: bool = True,
    drawn: tuple[Gaussians, np.ndarray] | None = None,
) -> QueryAnswer:
    """Relevance of every Gaussian to ``text``, 3D instances, and with ``camera`` the heatmap,
    mask and 2D regions of that view. The mask is where the query beats every negative, or,
    with ``threshold``, where its cosine heatmap exceeds that value. With ``images`` the view's
    rendered features are taken from (and kept in) that cache under ``image_key``. 3D instances:
    DBSCAN of the chosen Gaussians' centres with radius ``cluster_radius`` (metres; None: from
    the map's density, ``localize.default_cluster_radius``) and ``min_points``. ``features``:
    the map's ``QueryFeatures``, made once by a caller that asks many queries; ``voxel_index``:
    the map's ``localize.VoxelIndex`` for the cluster radius, likewise. ``locate`` False skips
    the Gaussians' choice and the 3D instances (a preview's heatmap: chosen_count -1, no
    instances). ``drawn`` = (Gaussians, their ids [M] int64 in the map): the view is rendered
    from these alone (a preview's decimated map), with their features. Raises
    OlsplatInputError on an empty text or a map that does not match the Gaussians."""
    text = text.strip()
    if not text:
        raise OlsplatInputError("the query text is empty")
    if len(gaussians) != len(language_map):
        raise OlsplatInputError(f"the language map has {len(language_map)} Gaussians, the scene's map {len(gaussians)}")
    negatives = [n for n in (t.strip() for t in negatives) if n and n != text]
    if not negatives:  # with nothing to beat, every observed Gaussian would be chosen
        raise OlsplatInputError(
            "no negatives left once empty ones and the query itself are removed: give other texts to "
            'compare with (e.g. the other things you look for, or "object, things, stuff, texture")'
        )
    embeddings = encoder.encode_text([text, *negatives])  # [1 + negatives, D] unit rows
    features = features if features is not None else QueryFeatures.of(language_map)
    chosen_of = partial(features.winners, embeddings, language_map.observed)
    if locate:
        radius = cluster_radius if cluster_radius is not None else default_cluster_radius(gaussians.means, min_points)
        answer = _located(text, negatives, gaussians, features, embeddings, chosen_of, radius, min_points, voxel_index)
    else:  # a preview: the view's pictures only
        answer = QueryAnswer(text, negatives, -1, [], chosen_of=chosen_of)
    answer.unknown_words = list(getattr(encoder, "unknown_words", lambda _t: [])(text))
    if camera is not None:
        table, rows, source = features.table, features.rows, gaussians
        if drawn is not None:  # a subset of the map: its rows of the table (its ids, for a per-Gaussian table)
            source, ids = drawn
            rows = ids if rows is None else rows[ids]
        if images is not None:
            maps, alpha = images.heatmaps(image_key, source, table, embeddings, camera, rows=rows)
        else:
            maps, alpha = render_heatmaps(source, table, embeddings, camera, rows=rows)
        answer.heatmap, answer.negative_heatmaps, answer.alpha = maps[0], maps[1:], alpha
        if threshold is None:
            answer.mask = relevancy_mask(maps[0], maps[1:], alpha)
        else:
            answer.mask = threshold_mask(maps[0], threshold, alpha)
        answer.regions = regions_in_view(answer.mask)
    return answer


def _located(text, negatives, gaussians, features, embeddings, chosen_of, radius, min_points, voxel_index):
    """``answer_query``'s choice of Gaussians and their 3D instances (DBSCAN, ``radius`` metres)."""
    if voxel_index is not None and voxel_index.eps == float(radius):
        in_order = features.winners_in_order(embeddings, voxel_index)  # observed: rows -1 otherwise
        if in_order is not None:  # a codebook map with its index: no [N] mask unless asked for
            count = features.count_winners(embeddings)
            assert count is not None
            answer = QueryAnswer(text, negatives, count, [], chosen_of=chosen_of)
            answer.instances = instances_in_3d(gaussians.means, None, radius, min_points, index=voxel_index,
                                               in_order=in_order)  # fmt: skip
            return answer
    selected = chosen_of()
    answer = QueryAnswer(text, negatives, int(np.count_nonzero(selected)), [], _chosen=selected)
    answer.instances = instances_in_3d(gaussians.means, selected, radius, min_points, index=voxel_index)
    return answer
