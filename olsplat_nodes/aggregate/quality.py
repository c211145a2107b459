"""Pixel reliability (paper eqs. effective_gaussian_number and q_sum).

From a pixel's adaptive Top-K weights w_k: pi_k = w_k / (sum w + eps); the effective number
of Gaussians E = 1 / (sum pi_k^2 + eps) (inverse Simpson index); q_sum = clip(sum w, q_min, 1)
says how completely the Top-K explain the pixel; q_eff = exp(-max(E - tau_E, 0) / kappa)
penalises pixels whose contribution is spread over many Gaussians.
"""

from __future__ import annotations

import numpy as np

from .config import AggregationConfig


def pixel_quality(topk_weights: np.ndarray, config: AggregationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """topk_weights [..., K] -> (q_sum [...], q_eff [...], effective number E [...]), float32."""
    w = topk_weights.astype(np.float32)
    total = w.sum(-1)
    pi = w / (total[..., None] + config.eps)
    effective = 1.0 / ((pi * pi).sum(-1) + config.eps)
    q_sum = np.clip(total, config.q_min, 1.0)
    q_eff = np.exp(-np.maximum(effective - config.tau_e, 0.0) / config.kappa)
    return q_sum.astype(np.float32), q_eff.astype(np.float32), effective.astype(np.float32)
