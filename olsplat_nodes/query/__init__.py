"""Text queries against a language map: relevance, rendered heatmaps, masks."""

from .heatmap import CANONICAL_NEGATIVES, argmax_masks, heatmaps, relevancy_mask, render_feature_map

__all__ = ["CANONICAL_NEGATIVES", "argmax_masks", "heatmaps", "relevancy_mask", "render_feature_map"]
