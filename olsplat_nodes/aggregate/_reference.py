"""Dense, obviously-correct versions of the aggregation maths: the oracles of the fast ones.

Everything is plain numpy over dense [pixels, K] and [Gaussians, views, D] arrays, straight
from the paper's equations; use only on small inputs.
"""

from __future__ import annotations

import numpy as np

from .config import AggregationConfig


def observe_view_dense(topk_ids, topk_weights, pixel_features, valid, n_gaussians, config: AggregationConfig):
    """(f [N, D], d [N]) for one view: eq. view_gaussian_feature and d_iv, all Gaussians, dense.

    pixel_features [H, W, D] = f_v(p); valid [H, W] = M_v(p). Rows with d <= tau_d are zeroed.
    """
    d_dim = pixel_features.shape[-1]
    numerator = np.zeros((n_gaussians, d_dim))
    strength = np.zeros(n_gaussians)
    height, width, k_max = topk_ids.shape
    for y in range(height):
        for x in range(width):
            w = topk_weights[y, x].astype(np.float64)
            total = w.sum()
            pi = w / (total + config.eps)
            effective = 1.0 / ((pi**2).sum() + config.eps)
            q = min(max(total, config.q_min), 1.0) * np.exp(-max(effective - config.tau_e, 0.0) / config.kappa)
            for k in range(k_max):
                i = topk_ids[y, x, k]
                if i < 0:
                    continue
                w_tilde = w[k] * float(valid[y, x]) * q
                numerator[i] += w_tilde * pixel_features[y, x]
                strength[i] += w_tilde
    features = numerator / (strength[:, None] + config.eps)
    keep = strength > config.tau_d
    return np.where(keep[:, None], features, 0.0), np.where(keep, strength, 0.0)


def refine_dense(features, strength, config: AggregationConfig):
    """features [N, V, D] f_iv, strength [N, V] d_iv (0 = no observation) -> F [N, D] after T iterations."""
    d = strength[..., None]
    F0 = F = (d * features).sum(1) / (strength.sum(1, keepdims=True) + config.eps)  # eq. initial_gaussian_feature
    rho = strength
    for t in range(1, config.iterations + 1):
        cos = (features * F[:, None, :]).sum(-1) / (
            np.linalg.norm(features, axis=-1) * np.linalg.norm(F, axis=-1, keepdims=True) + config.eps
        )
        rho = strength * np.exp(config.beta_at(t) * cos)  # rho = d exp(beta_t c); 0 where no observation
        F = (rho[..., None] * features).sum(1) / (rho.sum(1, keepdims=True) + config.eps)  # eq. robust_feature_update
    if config.min_retained_views is not None and config.iterations > 0:  # Kish effective views, after / before
        for i in range(len(F)):
            if strength[i].sum() > 0:
                before = strength[i].sum() ** 2 / (strength[i] ** 2).sum()
                after = rho[i].sum() ** 2 / (rho[i] ** 2).sum()
                if after / before < config.min_retained_views:
                    F[i] = F0[i]
    return F


def streaming_cosine_reference(owner, view, strength, features, n):
    """VALA's streaming update in plain numpy, view by view: (F [n, D], count [n]). A new
    observation enters the running mean with weight d (1 + cos(f, F)) / 2, the first with d."""
    total = np.zeros((n, features.shape[1]), np.float64)
    weight = np.zeros(n, np.float64)
    order = np.argsort(view, kind="stable")
    owner, view, strength, features = owner[order], view[order], strength[order], features[order].astype(np.float64)
    for v in np.unique(view):
        here = view == v
        g, f, d = owner[here], features[here], strength[here]
        current = total[g] / np.maximum(weight[g], 1e-12)[:, None]
        norm = np.linalg.norm(f, axis=1) * np.linalg.norm(current, axis=1)
        cos = np.where(norm > 0, (f * current).sum(1) / np.maximum(norm, 1e-12), 1.0)
        w = d * np.where(weight[g] > 0, (1.0 + cos) / 2.0, 1.0)
        np.add.at(total, g, w[:, None] * f)
        np.add.at(weight, g, w)
    return (total / np.maximum(weight, 1e-12)[:, None]).astype(np.float32), np.bincount(owner, minlength=n)
