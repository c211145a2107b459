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

from collections import OrderedDict
from collections.abc import Hashable

import numpy as np

from ..raster import RasterConfig, rasterize
from ..scene import Camera, Gaussians

CANONICAL_NEGATIVES = ("object", "things", "stuff", "texture")


def render_feature_map(gaussians: Gaussians, features: np.ndarray, camera: Camera, config: RasterConfig | None = None):
    """([H, W, D] float32 rendered features F(v), [H, W] alpha)."""
    result = rasterize(gaussians, camera, config, features=features, want_topk=False)
    return result.features, result.alpha


def render_heatmaps(gaussians: Gaussians, features: np.ndarray, texts: np.ndarray, camera: Camera, config=None):
    """([Q, H, W] cosine heatmaps H_q(v) of the unit text embeddings texts [Q, D], [H, W] alpha):
    ``heatmaps(render_feature_map(...))`` computed per pixel inside the rasterizer, without the
    [H, W, D] feature image (157 MB at 640x480 and D = 128)."""
    result = rasterize(
        gaussians, camera, config, features=features, want_topk=False, feature_queries=np.asarray(texts, np.float32)
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
    than the whole budget is rendered and not kept. The answers are those of
    ``render_heatmaps`` (the same sums, the cosine taken by a matrix product: equal to ~1e-6)."""

    def __init__(self, budget_bytes: int):
        self.budget = int(budget_bytes)
        self.entries: OrderedDict[Hashable, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.hits = self.misses = 0

    @property
    def bytes(self) -> int:
        return sum(unit.nbytes + alpha.nbytes for unit, alpha in self.entries.values())

    def heatmaps(
        self, key: Hashable, gaussians: Gaussians, features: np.ndarray, texts: np.ndarray, camera: Camera, config=None
    ):
        """([Q, H, W] cosine heatmaps of the unit texts [Q, D], [H, W] alpha), as ``render_heatmaps``."""
        entry = self.entries.get(key)
        if entry is None:
            self.misses += 1
            size = camera.width * camera.height * (features.shape[1] + 1) * 4
            keep = size <= self.budget
            # Room first, then render: the evicted views' memory is reused for the new one. Growing
            # the process instead costs ~0.3 s per 157 MB of first-touched pages on a small VM.
            while keep and self.entries and self.bytes + size > self.budget:
                self.entries.popitem(last=False)
            feature_map, alpha = render_feature_map(gaussians, features, camera, config)
            unit = feature_map.reshape(-1, feature_map.shape[-1])
            norm = np.sqrt(np.einsum("nd,nd->n", unit, unit))
            unit /= np.maximum(norm, np.float32(1e-30))[:, None]  # in place: 0 rows stay 0
            entry = (unit, alpha)
            if keep:
                self.entries[key] = entry
        else:
            self.hits += 1
            self.entries.move_to_end(key)
        unit, alpha = entry
        maps = unit @ np.asarray(texts, np.float32).T  # [H * W, Q]
        return np.ascontiguousarray(maps.T).reshape(len(texts), *alpha.shape), alpha


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
    """[H, W] bool: where the query's heatmap beats every negative's."""
    return (query_map > negative_maps.max(0)) & (alpha > min_alpha) if len(negative_maps) else alpha > min_alpha


def threshold_mask(query_map: np.ndarray, threshold: float, alpha: np.ndarray, min_alpha: float = 0.5) -> np.ndarray:
    """[H, W] bool: where the query's cosine heatmap exceeds the caller's own ``threshold``."""
    return (query_map > threshold) & (alpha > min_alpha)
