"""Consistency-aware aggregation over views (paper eqs. initial_gaussian_feature and
robust_feature_update), on a flat list of observations.

An observation is (gaussian i, strength d_iv, feature f_iv). F0 is the d-weighted mean of a
Gaussian's features; then, T times, each observation is re-weighted by rho = d exp(beta_t c)
with c its cosine to the current F, and F becomes the rho-weighted mean. Gaussians with no
observation keep F = 0 and count 0.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from numba import njit

from .config import AggregationConfig


@njit(cache=True)
def _weighted_mean(owner: np.ndarray, weights: np.ndarray, features: np.ndarray, n: int, eps: float) -> np.ndarray:
    """[n, D] float64: per Gaussian, sum w f / (sum w + eps) over its observations."""
    total = np.zeros((n, features.shape[1]), np.float64)
    norm = np.zeros(n, np.float64)
    for o in range(owner.shape[0]):
        g, w = owner[o], weights[o]
        norm[g] += w
        for d in range(features.shape[1]):
            total[g, d] += w * features[o, d]
    for g in range(n):
        total[g] /= norm[g] + eps
    return total


def refine_observations(
    owner: np.ndarray,  # [O] int Gaussian index of each observation (0..n-1)
    strength: np.ndarray,  # [O] d_iv
    features: np.ndarray,  # [O, D] f_iv
    n: int,
    config: AggregationConfig = AggregationConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """(F [n, D] float32, observation count [n] int) after config.iterations iterations."""
    owner = np.ascontiguousarray(owner, np.int64)
    features = np.ascontiguousarray(features, np.float64)
    strength = np.ascontiguousarray(strength, np.float64)
    F0 = F = _weighted_mean(owner, strength, features, n, config.eps)
    feature_norm = np.linalg.norm(features, axis=1)
    rho = strength
    for t in range(1, config.iterations + 1):
        current = F[owner]
        cos = (features * current).sum(1) / (feature_norm * np.linalg.norm(current, axis=1) + config.eps)
        rho = strength * np.exp(config.beta_at(t) * cos)
        F = _weighted_mean(owner, rho, features, n, config.eps)
    if config.min_retained_views is not None and config.iterations > 0:
        F = np.where(_retained_views(owner, strength, rho, n)[:, None] < config.min_retained_views, F0, F)
    return F.astype(np.float32), np.bincount(owner, minlength=n)


def _retained_views(owner: np.ndarray, strength: np.ndarray, rho: np.ndarray, n: int) -> np.ndarray:
    """[n]: effective number of views under the final weights rho over that under d (Kish,
    (sum w)^2 / sum w^2); 1 where unobserved. ~1 when the consistency weights only trim
    outliers, small when they keep one of several disagreeing groups of views."""

    def effective(w):
        total, square = np.bincount(owner, w, n), np.bincount(owner, w * w, n)
        return total**2 / np.maximum(square, 1e-300)

    before = effective(strength)
    return np.where(before > 0, effective(rho) / np.maximum(before, 1e-300), 1.0)


def streaming_cosine(
    owner: np.ndarray,  # [O] Gaussian index
    view: np.ndarray,  # [O] view index (arrival order)
    strength: np.ndarray,  # [O] d_iv
    features: np.ndarray,  # [O, D] f_iv
    n: int,
) -> tuple[np.ndarray, np.ndarray]:
    """VALA-style streaming update, view by view in arrival order: a new observation enters the
    running weighted mean with weight d * (1 + cos(f, F)) / 2 (its agreement with the current
    feature; the first observation of a Gaussian enters with weight d). Returns (F, count)."""
    total = np.zeros((n, features.shape[1]), np.float64)
    weight = np.zeros(n, np.float64)
    order = np.argsort(view, kind="stable")
    owner, view, strength, features = owner[order], view[order], strength[order], features[order].astype(np.float64)
    bounds = np.flatnonzero(np.r_[True, view[1:] != view[:-1], True])
    for start, stop in pairwise(bounds):
        g, f, d = owner[start:stop], features[start:stop], strength[start:stop]
        current = total[g] / np.maximum(weight[g], 1e-12)[:, None]
        norm = np.linalg.norm(f, axis=1) * np.linalg.norm(current, axis=1)
        cos = np.where(norm > 0, (f * current).sum(1) / np.maximum(norm, 1e-12), 1.0)
        w = d * np.where(weight[g] > 0, (1.0 + cos) / 2.0, 1.0)
        np.add.at(total, g, w[:, None] * f)
        np.add.at(weight, g, w)
    F = total / np.maximum(weight, 1e-12)[:, None]
    return F.astype(np.float32), np.bincount(owner, minlength=n)
