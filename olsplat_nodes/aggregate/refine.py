"""Consistency-aware aggregation over views (paper eqs. initial_gaussian_feature and
robust_feature_update), on a flat list of observations.

An observation is (gaussian i, strength d_iv, feature f_iv). F0 is the d-weighted mean of a
Gaussian's features; then, T times, each observation is re-weighted by rho = d exp(beta_t c)
with c its cosine to the current F, and F becomes the rho-weighted mean. Gaussians with no
observation keep F = 0 and count 0.
"""

from __future__ import annotations

import numpy as np

from .config import AggregationConfig


def _weighted_mean(owner: np.ndarray, weights: np.ndarray, features: np.ndarray, n: int, eps: float) -> np.ndarray:
    total = np.zeros((n, features.shape[1]), np.float64)
    np.add.at(total, owner, weights[:, None] * features)
    norm = np.bincount(owner, weights=weights, minlength=n)
    return total / (norm[:, None] + eps)


def refine_observations(
    owner: np.ndarray,  # [O] int Gaussian index of each observation (0..n-1)
    strength: np.ndarray,  # [O] d_iv
    features: np.ndarray,  # [O, D] f_iv
    n: int,
    config: AggregationConfig = AggregationConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """(F [n, D] float32, observation count [n] int) after config.iterations iterations."""
    features = features.astype(np.float64)
    strength = strength.astype(np.float64)
    F = _weighted_mean(owner, strength, features, n, config.eps)
    feature_norm = np.linalg.norm(features, axis=1)
    for t in range(1, config.iterations + 1):
        current = F[owner]
        cos = (features * current).sum(1) / (feature_norm * np.linalg.norm(current, axis=1) + config.eps)
        rho = strength * np.exp(config.beta_at(t) * cos)
        F = _weighted_mean(owner, rho, features, n, config.eps)
    return F.astype(np.float32), np.bincount(owner, minlength=n)
