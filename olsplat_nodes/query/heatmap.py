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
