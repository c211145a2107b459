"""Dense, obviously-correct versions of the aggregation maths: the oracles of the fast ones.

Everything is plain numpy over dense [pixels, K] and [Gaussians, views, D] arrays, straight
from the paper's equations; use only on small inputs.
"""

from __future__ import annotations

from dataclasses import replace

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


def streaming_median_reference(owner, view, strength, features, n):
    """VALA's streaming median in plain numpy, view by view (VALA Algorithm 1): (F [n, D] unit
    rows, count [n]). z starts at a Gaussian's first unit feature; each next view's unit f with
    weight w gives z <- normalize(z + w / (W + w) (f - (f . z) z)), W += w."""
    z = np.zeros((n, features.shape[1]), np.float64)
    total = np.zeros(n, np.float64)
    order = np.argsort(view, kind="stable")
    owner, view, strength, features = owner[order], view[order], strength[order], features[order].astype(np.float64)
    for v in np.unique(view):
        for i, w, f in zip(owner[view == v], strength[view == v], features[view == v], strict=True):
            norm = np.linalg.norm(f)
            if norm <= 0 or w <= 0:
                continue
            f = f / norm
            if total[i] == 0:
                z[i] = f
            else:
                z[i] = z[i] + w / (total[i] + w) * (f - (f @ z[i]) * z[i])
                z[i] /= np.linalg.norm(z[i])
            total[i] += w
    return z.astype(np.float32), np.bincount(owner, minlength=n)


def fold_dense(prior_mean, weight, features, strength, config: AggregationConfig):
    """A live map's fold of new views, in plain numpy: (F [N, D], weight [N]).

    prior_mean [N, D] is each Gaussian's un-normalised F over the views folded in so far and
    weight [N] their sum of final weights (0: no view yet); features [N, V, D] and strength
    [N, V] (0 = not seen) are the new views. A Gaussian without a prior and with a new view is
    computed exactly (``refine_dense``; its weight is its final sum of rho, or of d where the
    F0 fallback applies); one with a prior weighs each new view against it with
    rho = d exp(beta_T cos(f, prior)) and F = (W prior + sum rho f) / (W + sum rho + eps)."""
    F = prior_mean.astype(np.float64).copy()
    weight = weight.astype(np.float64).copy()
    beta_last = config.beta_at(config.iterations) if config.iterations > 0 else 0.0
    for i in range(len(F)):
        seen = strength[i] > 0
        if not seen.any():
            continue
        f, d = features[i, seen].astype(np.float64), strength[i, seen].astype(np.float64)
        if weight[i] > 0:
            cos = f @ F[i] / (np.linalg.norm(f, axis=1) * np.linalg.norm(F[i]) + config.eps)
            rho = d * np.exp(beta_last * cos)
            F[i] = (weight[i] * F[i] + rho @ f) / (weight[i] + rho.sum() + config.eps)
            weight[i] += rho.sum()
            continue
        F[i] = refine_dense(f[None], d[None], config)[0]
        if config.iterations == 0:
            weight[i] = d.sum()
            continue
        previous = replace(config, iterations=config.iterations - 1, min_retained_views=None)
        before = refine_dense(f[None], d[None], previous)[0]  # F^(T-1)
        cos = f @ before / (np.linalg.norm(f, axis=1) * np.linalg.norm(before) + config.eps)
        rho = d * np.exp(beta_last * cos)
        kept = (rho.sum() ** 2 / (rho**2).sum()) / (d.sum() ** 2 / (d**2).sum())
        fell_back = config.min_retained_views is not None and kept < config.min_retained_views
        weight[i] = d.sum() if fell_back else rho.sum()
    return F, weight


def flight_evidence_dense(features, strength, config: AggregationConfig):
    """One flight's map and evidence from its raw views, in plain numpy: (F [N, D], W [N],
    count [N], n_eff [N], spread [N]) for features [N, V, D] f_iv and strength [N, V] d_iv
    (0 = not seen). W = sum d, count = views with d > 0, n_eff = (sum d)^2 / sum d^2,
    spread = sum d (1 - cos(f, F)) / sum d (NaN where unseen)."""
    F = refine_dense(features, strength, config)
    W = strength.sum(1)
    count = (strength > 0).sum(1)
    n_eff = np.zeros(len(F))
    spread = np.full(len(F), np.nan)
    for i in range(len(F)):
        seen = strength[i] > 0
        if not seen.any():
            continue
        d, f = strength[i, seen], features[i, seen]
        n_eff[i] = d.sum() ** 2 / (d**2).sum()
        cos = f @ F[i] / (np.linalg.norm(f, axis=1) * np.linalg.norm(F[i]) + config.eps)
        spread[i] = (d * (1 - cos)).sum() / d.sum()
    return F, W, count, n_eff, spread


def change_score_dense(features, strength, flight, a, b, config: AggregationConfig, rule):
    """[N] change scores of flight ``a`` to flight ``b`` (``aggregate/change.py``'s rule) from
    raw views: features [N, V, D], strength [N, V] (0 = not seen), flight [V] each view's
    flight. Each flight's map comes from its own views alone (``flight_evidence_dense``)."""
    maps = {}
    for name in (a, b):
        views = np.asarray(flight) == name
        maps[name] = flight_evidence_dense(features[:, views], strength[:, views], config)
    (F_a, W_a, _, n_a, s_a), (F_b, W_b, _, n_b, s_b) = maps[a], maps[b]
    score = np.full(len(F_a), np.nan)
    for i in range(len(F_a)):
        well = [
            n >= rule.min_views and W >= rule.min_weight and np.isfinite(s)
            for n, W, s in ((n_a[i], W_a[i], s_a[i]), (n_b[i], W_b[i], s_b[i]))
        ]
        if not all(well):
            continue
        cos = F_a[i] @ F_b[i] / (np.linalg.norm(F_a[i]) * np.linalg.norm(F_b[i]))
        noise = s_a[i] + s_b[i] + rule.prior_spread / n_a[i] + rule.prior_spread / n_b[i]
        score[i] = (1 - cos) / noise
    return score
