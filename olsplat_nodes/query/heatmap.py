"""Open-vocabulary queries against a language map (paper eqs. semantic_rendering, semantic_heatmap).

Relevance of a Gaussian: cos(F_i, e_q). The heatmap of a view renders the Gaussians' features
with the rasterizer's alpha-blending weights, F(v) = sum w F_i / (sum w + eps), and takes
H_q(v) = cos(F(v), e_q) per pixel. Masks:
- ``argmax_masks`` (the evaluation rule): each pixel goes to the query whose heatmap is
  highest among the scene's queries; a query's mask is where it wins (and alpha > 0.5).
- ``relevancy_mask`` (one query on its own, LERF-style): the query must beat every negative
  text ("object", "things", ... or the scene's other queries) at that pixel.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Hashable

import numpy as np
from numba import njit, prange

from ..raster import RasterConfig, rasterize
from ..scene import Camera, Gaussians

CANONICAL_NEGATIVES = ("object", "things", "stuff", "texture")


def render_feature_map(gaussians: Gaussians, features: np.ndarray, camera: Camera, config: RasterConfig | None = None):
    """([H, W, D] float32 rendered features F(v), [H, W] alpha)."""
    result = rasterize(gaussians, camera, config, features=features, want_topk=False)
    return result.features, result.alpha


def render_heatmaps(
    gaussians: Gaussians,
    features: np.ndarray,
    texts: np.ndarray,
    camera: Camera,
    config=None,
    unit_out=None,
    rows: np.ndarray | None = None,
):
    """([Q, H, W] cosine heatmaps H_q(v) of the unit text embeddings texts [Q, D], [H, W] alpha):
    ``heatmaps(render_feature_map(...))`` computed per pixel inside the rasterizer, without the
    [H, W, D] feature image (157 MB at 640x480 and D = 128). With ``unit_out`` (float32
    [H * W, D]) the same pass also writes each pixel's unit feature F / |F| there. With
    ``rows`` ([N] int, -1: none) ``features`` is a table, e.g. a codebook's centres, and
    Gaussian g's feature is its row ``rows[g]``."""
    result = rasterize(
        gaussians,
        camera,
        config,
        features=features,
        want_topk=False,
        feature_queries=np.asarray(texts, np.float32),
        unit_features_out=unit_out,
        feature_rows=rows,
    )
    assert result.features is not None
    return np.moveaxis(result.features, -1, 0), result.alpha


class FeatureImages:
    """The rendered features of recent views, kept to answer the next query on the same view
    without rendering again (an operator tries several queries on one view; the alpha-blended
    features of a view do not depend on the query). An LRU under a byte budget: each entry is
    a view's unit features [H * W, D] float32 (F / |F|, rows of 0 where nothing was rendered)
    and its alpha [H, W]; 157 MB at 640x480 and D = 128. ``key`` must change whenever the
    features or the camera do (the query server uses (map version, view name)). A view larger
    than the whole budget is rendered and not kept.

    The first query on a view is answered by the compositing kernel, which writes the view's
    unit features into the cache in the same pass; the next ones by a matrix product (equal to
    the kernel's cosine to ~2e-5). Buffers of evicted views are reused, and ``reserve`` touches
    the budget's buffers ahead of the first query: each page of memory touched for the first
    time is a page fault, and on a small VM a view's worth of them costs about as much as
    rendering the view."""

    def __init__(self, budget_bytes: int):
        self.budget = int(budget_bytes)
        self.entries: OrderedDict[Hashable, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.spare: list[np.ndarray] = []  # touched [H * W, D] buffers of no view yet
        self.hits = self.misses = 0
        self.lock = threading.RLock()  # ``reserve`` may run in another thread

    @property
    def bytes(self) -> int:
        with self.lock:
            held = sum(unit.nbytes + alpha.nbytes for unit, alpha in self.entries.values())
            return held + sum(buffer.nbytes for buffer in self.spare)

    def reserve(self, pixels: int, dim: int) -> int:
        """Allocate and touch as many [pixels, dim] float32 buffers as the budget holds beside
        what is kept; the number of buffers made. Meant for a background thread (numpy fills
        without the GIL) while queries are answered."""
        made = 0
        size = pixels * (dim + 1) * 4
        while self.bytes + size <= self.budget:
            buffer = np.empty((pixels, dim), np.float32)
            buffer.fill(0.0)
            with self.lock:
                if self.bytes + size > self.budget:  # queries took the room meanwhile
                    return made
                self.spare.append(buffer)
            made += 1
        return made

    def _take_spare(self, pixels: int, dim: int) -> np.ndarray | None:
        for i, buffer in enumerate(list(self.spare)):
            if buffer.shape == (pixels, dim):
                return self.spare.pop(i)
        return None

    def heatmaps(
        self,
        key: Hashable,
        gaussians: Gaussians,
        features: np.ndarray,
        texts: np.ndarray,
        camera: Camera,
        config=None,
        rows: np.ndarray | None = None,
    ):
        """([Q, H, W] cosine heatmaps of the unit texts [Q, D], [H, W] alpha), as ``render_heatmaps``."""
        with self.lock:
            entry = self.entries.get(key)
            if entry is not None:
                self.hits += 1
                self.entries.move_to_end(key)
        if entry is None:
            pixels, dim = camera.width * camera.height, features.shape[1]
            size = pixels * (dim + 1) * 4
            with self.lock:
                self.misses += 1
                if size > self.budget:
                    unit = None
                else:
                    unit = self._take_spare(pixels, dim)
                    # room first: an evicted view's buffer (already in memory) takes the new view
                    while (self.entries or self.spare) and self.bytes + size > self.budget:
                        old = self.entries.popitem(last=False)[1][0] if self.entries else self.spare.pop()
                        if unit is None and old.shape == (pixels, dim):
                            unit = old
                    if unit is None:
                        unit = np.empty((pixels, dim), np.float32)
            maps, alpha = render_heatmaps(gaussians, features, texts, camera, config, unit, rows)
            if unit is not None:
                with self.lock:
                    self.entries[key] = (unit, alpha)
            return maps, alpha
        unit, alpha = entry
        # [Q, H * W] straight from the product: (unit @ texts.T).T needed a transposing copy
        # of the whole result (54 MB at 1280x960 and 11 texts)
        maps = np.asarray(texts, np.float32) @ unit.T
        return maps.reshape(len(texts), *alpha.shape), alpha


def heatmaps(feature_map: np.ndarray, text_embeddings: np.ndarray) -> np.ndarray:
    """[H, W, D] rendered features, [Q, D] unit text embeddings -> [Q, H, W] cosine heatmaps."""
    norm = np.linalg.norm(feature_map, axis=-1, keepdims=True)
    unit = feature_map / np.maximum(norm, 1e-12)
    return np.einsum("hwd,qd->qhw", unit, text_embeddings.astype(np.float32))


def argmax_masks(maps: np.ndarray, alpha: np.ndarray, min_alpha: float = 0.5) -> np.ndarray:
    """[Q, H, W] heatmaps -> [Q, H, W] bool: pixel goes to its highest query, where covered."""
    winner = maps.argmax(0)
    covered = alpha > min_alpha
    return np.stack([(winner == q) & covered for q in range(len(maps))])


def relevancy_mask(
    query_map: np.ndarray, negative_maps: np.ndarray, alpha: np.ndarray, min_alpha: float = 0.5
) -> np.ndarray:
    """[H, W] bool: where the query's heatmap beats every negative's (``query_map >
    negative_maps.max(0)``, NaN never beats) and ``alpha > min_alpha``. One pass per pixel over
    its negatives, whatever the maps' layout: a render's [Q, H, W] heatmaps are a view of its
    [H, W, Q] output, whose negatives numpy's ``max(0)`` read 44 bytes apart, a strided pass
    over the whole image per negative; here each pixel's values are read together, once."""
    if not len(negative_maps):
        return alpha > min_alpha
    out = np.empty(query_map.shape, np.bool_)
    _beats_every(query_map, negative_maps, alpha, np.float32(min_alpha), out)
    return out


@njit(parallel=True, cache=True)
def _beats_every(query_map, negative_maps, alpha, min_alpha, out):
    """out[y, x] = alpha[y, x] > min_alpha and query_map[y, x] > every negative_maps[k, y, x]."""
    for y in prange(query_map.shape[0]):
        for x in range(query_map.shape[1]):
            beats = alpha[y, x] > min_alpha
            value = query_map[y, x]
            k = 0
            while beats and k < negative_maps.shape[0]:
                beats = value > negative_maps[k, y, x]
                k += 1
            out[y, x] = beats


def threshold_mask(query_map: np.ndarray, threshold: float, alpha: np.ndarray, min_alpha: float = 0.5) -> np.ndarray:
    """[H, W] bool: where the query's cosine heatmap exceeds the caller's own ``threshold``."""
    return (query_map > threshold) & (alpha > min_alpha)
