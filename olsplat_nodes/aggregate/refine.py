"""Consistency-aware aggregation over views (paper eqs. initial_gaussian_feature and
robust_feature_update), Gaussian by Gaussian.

An observation is (gaussian i, strength d_iv, feature f_iv). F0 is the d-weighted mean of a
Gaussian's features; then, T times, each observation is re-weighted by rho = d exp(beta_t c)
with c its cosine to the current F, and F becomes the rho-weighted mean. Gaussians with no
observation keep F = 0 and count 0.

A Gaussian's result depends on its own observations only, so the kernels work one Gaussian at
a time on its few observations (one per view that saw it), in cache, and never build [O, D]
temporaries: a refinement pass costs O(observations of the refined Gaussians x D x T). The
features stay in the store's mixture form, f = sum_e w_e bank[slot_e], and are mixed inside the
kernel. ``_reference.py`` holds the dense equations (``refine_dense``) and VALA's streaming
median in numpy (``streaming_median_reference``), which these kernels are tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .config import AggregationConfig


@dataclass(frozen=True)
class MixedObservations:
    """Observations whose features are mixtures of bank rows (the store's form).

    owner [O] int64 Gaussian index (0..n-1), in arrival order (view by view); strength [O]
    float32 d_iv; observation o's feature is sum over e in entry_offsets[o]:entry_offsets[o+1]
    of weights[e] * bank[slots[e]], with entry_offsets [O+1] int64, slots [E] int64,
    weights [E] float32 and bank [S, D] float32.
    """

    owner: np.ndarray
    strength: np.ndarray
    entry_offsets: np.ndarray
    slots: np.ndarray
    weights: np.ndarray
    bank: np.ndarray

    @staticmethod
    def dense(owner: np.ndarray, strength: np.ndarray, features: np.ndarray) -> MixedObservations:
        """Observations with one plain feature each: features [O, D]."""
        count = len(owner)
        return MixedObservations(
            np.ascontiguousarray(owner, np.int64),
            np.ascontiguousarray(strength, np.float32),
            np.arange(count + 1, dtype=np.int64),
            np.arange(count, dtype=np.int64),
            np.ones(count, np.float32),
            np.ascontiguousarray(features, np.float32).reshape(count, -1),
        )

    def __len__(self) -> int:
        return len(self.owner)


@njit(cache=True)
def _group_by_owner(owner, n):
    """(first [n+1], order [O]): observations of Gaussian g are order[first[g]:first[g+1]], in
    their original order (a stable counting sort)."""
    first = np.zeros(n + 1, np.int64)
    for o in range(owner.shape[0]):
        first[owner[o] + 1] += 1
    for g in range(n):
        first[g + 1] += first[g]
    fill = first[:-1].copy()
    order = np.empty(owner.shape[0], np.int64)
    for o in range(owner.shape[0]):
        order[fill[owner[o]]] = o
        fill[owner[o]] += 1
    return first, order


@njit(inline="always", fastmath=True)
def _dot(a, b):
    total = 0.0
    for d in range(a.shape[0]):
        total += a[d] * b[d]
    return total


@njit(inline="always")
def _mix(features, norms, strength_out, strength, order, a, entry_offsets, slots, weights, bank):
    """Fill features [k, D] float64 with the mixed features of observations order[a:a+k]."""
    for j in range(features.shape[0]):
        o = order[a + j]
        strength_out[j] = strength[o]
        features[j, :] = 0.0
        for e in range(entry_offsets[o], entry_offsets[o + 1]):
            w = weights[e]
            row = bank[slots[e]]
            for d in range(features.shape[1]):
                features[j, d] += w * row[d]
        norms[j] = np.sqrt(_dot(features[j], features[j]))


@njit(inline="always")
def _weighted_mean(features, w, eps, out):
    out[:] = 0.0
    total = 0.0
    for j in range(features.shape[0]):
        total += w[j]
        for d in range(features.shape[1]):
            out[d] += w[j] * features[j, d]
    out /= total + eps


@njit(inline="always")
def _effective_views(w):
    """Kish's effective number of views, (sum w)^2 / sum w^2."""
    total = squares = 0.0
    for j in range(w.shape[0]):
        total += w[j]
        squares += w[j] * w[j]
    return total**2 / max(squares, 1e-300)


# Gaussians per parallel chunk: each chunk allocates its scratch arrays once (the size of the
# most-observed Gaussian), not once per Gaussian (millions of small allocations per pass)
_CHUNK = 512


@njit(inline="always")
def _most_observed(first):
    most = 0
    for g in range(first.shape[0] - 1):
        most = max(most, first[g + 1] - first[g])
    return most


@njit(inline="always")
def _prior_mean(prior_row, norm, out):
    """out = the prior's un-normalised mean: its row's direction at length ``norm``."""
    length = np.sqrt(_dot(prior_row, prior_row))
    for d in range(out.shape[0]):
        out[d] = prior_row[d] * (norm / length) if length > 0.0 else 0.0


@njit(parallel=True, cache=True, fastmath=True)
def _consistency(
    first, order, strength, entry_offsets, slots, weights, bank, betas, eps, min_retained, prior, weight, norm, spread
):
    """[n, D] float32 F per Gaussian; betas [T] beta_t; min_retained <= 0 turns the F0 fallback off.

    weight [n] and norm [n] float64 are the running state, read and written: a Gaussian with
    weight 0 is computed exactly from its observations here (T iterations); one with weight W > 0
    already holds earlier views, whose mean is prior [n, D]'s row direction at length norm, and
    folds these in: each new view weighs rho = d exp(beta_T cos(f, F)) against that mean and
    F = (W F + sum rho f) / (W + sum rho + eps). On return weight holds the sum of the final
    weights (rho, or d after the F0 fallback) and norm |F|. spread [n] float64, unless it has
    no rows, gets each computed Gaussian's spread of views about F (``_spread``; NaN for a fold,
    which no longer holds the earlier views)."""
    n, dim = first.shape[0] - 1, bank.shape[1]
    out = np.zeros((n, dim), np.float32)
    beta_last = betas[-1] if betas.shape[0] > 0 else 0.0
    most = _most_observed(first)
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        all_features, all_norms = np.empty((most, dim)), np.empty(most)
        all_d, all_rho = np.empty(most), np.empty(most)
        F, F0 = np.empty(dim), np.empty(dim)
        for g in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            a, k = first[g], first[g + 1] - first[g]
            if k == 0:
                continue
            features, norms, d, rho = all_features[:k], all_norms[:k], all_d[:k], all_rho[:k]
            _mix(features, norms, d, strength, order, a, entry_offsets, slots, weights, bank)
            if weight[g] > 0.0:  # fold the new views into the running mean
                _prior_mean(prior[g], norm[g], F)
                norm_F = np.sqrt(_dot(F, F))
                for j in range(k):  # every new view against the same prior mean: order does not matter
                    rho[j] = d[j] * np.exp(beta_last * _dot(features[j], F) / (norms[j] * norm_F + eps))
                total = weight[g]
                F *= total
                for j in range(k):
                    total += rho[j]
                    for c in range(dim):
                        F[c] += rho[j] * features[j, c]
                F /= total + eps
                weight[g] = total
                norm[g] = np.sqrt(_dot(F, F))
                out[g] = F
                if spread.shape[0] > 0:
                    spread[g] = np.nan
                continue
            _weighted_mean(features, d, eps, F0)
            F[:] = F0
            rho[:] = d
            for beta in betas:
                norm_F = np.sqrt(_dot(F, F))
                for j in range(k):
                    cosine = _dot(features[j], F) / (norms[j] * norm_F + eps)
                    rho[j] = d[j] * np.exp(beta * cosine)
                _weighted_mean(features, rho, eps, F)
            if min_retained > 0 and betas.shape[0] > 0:
                before = _effective_views(d)
                retained = _effective_views(rho) / max(before, 1e-300) if before > 0 else 1.0
                if retained < min_retained:
                    F[:] = F0
                    rho[:] = d
            total = 0.0
            for j in range(k):
                total += rho[j]
            weight[g] = total
            norm[g] = np.sqrt(_dot(F, F))
            out[g] = F
            if spread.shape[0] > 0:
                spread[g] = _spread(features, norms, d, F, eps)
    return out


@njit(inline="always")
def _spread(features, norms, w, F, eps):
    """The w-weighted mean of 1 - cos(f_j, F) over a Gaussian's views (0: they all point
    along F; 1: orthogonal on average): how much its views scatter about the feature made of
    them. w = d_iv, the views' own evidence, not the consistency weights rho: rho = d exp(8 cos)
    all but drops the views that disagree with F, and a Gaussian whose views split into two
    camps (an edge seen against two backgrounds) would look certain of the camp it chose."""
    norm_F = np.sqrt(_dot(F, F))
    total = spread = 0.0
    for j in range(features.shape[0]):
        total += w[j]
        spread += w[j] * (1.0 - _dot(features[j], F) / (norms[j] * norm_F + eps))
    return spread / total if total > 0.0 else np.nan


@njit(parallel=True, cache=True)
def _streaming_median(first, order, strength, entry_offsets, slots, weights, bank, prior, weight, norm, spread):
    """[n, D] float32 unit rows: VALA's streaming weighted geometric median in cosine space
    (VALA Sec. 4.2, Algorithm 1), per Gaussian over its observations in arrival order: z starts
    at the first unit feature with W = its weight; each next one (unit f, weight w) moves z
    along its tangent direction, z <- normalize(z + w / (W + w) * (f - (f . z) z)), W += w.
    Observations with a zero feature or weight are skipped. A Gaussian with weight W > 0 goes on
    from z = prior [n, D]'s row direction (the median is incremental by nature); weight [n] is
    read and written, norm [n] is set to 1 where z is set; spread [n] (unless it has no rows)
    gets the d-weighted ``_spread`` about z of the views a Gaussian computed from scratch
    (NaN when it went on from a prior)."""
    n, dim = first.shape[0] - 1, bank.shape[1]
    out = np.zeros((n, dim), np.float32)
    most = _most_observed(first)
    for chunk in prange((n + _CHUNK - 1) // _CHUNK):
        all_features, all_norms, all_d = np.empty((most, dim)), np.empty(most), np.empty(most)
        z = np.empty(dim)
        for g in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            a, k = first[g], first[g + 1] - first[g]
            if k == 0:
                continue
            features, norms, d = all_features[:k], all_norms[:k], all_d[:k]
            _mix(features, norms, d, strength, order, a, entry_offsets, slots, weights, bank)
            z[:] = 0.0
            total = weight[g]
            if total > 0.0:
                _prior_mean(prior[g], 1.0, z)
            for j in range(k):
                if norms[j] <= 0.0 or d[j] <= 0.0:
                    continue
                if total == 0.0:
                    for c in range(dim):
                        z[c] = features[j, c] / norms[j]
                else:
                    eta = d[j] / (total + d[j])
                    along = _dot(features[j], z) / norms[j]  # f . z with f the unit feature
                    for c in range(dim):
                        z[c] += eta * (features[j, c] / norms[j] - along * z[c])
                    z /= np.sqrt(_dot(z, z))
                total += d[j]
            if spread.shape[0] > 0:
                spread[g] = np.nan if weight[g] > 0.0 else _spread(features, norms, d, z, 1e-30)
            weight[g] = total
            norm[g] = 1.0 if total > 0.0 else 0.0
            out[g] = z
    return out


def refine_mixed(
    observations: MixedObservations,
    n: int,
    config: AggregationConfig = AggregationConfig(),
    state: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    evidence: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(F [n, D] float32, observation count [n] int64) combining each Gaussian's observations
    as ``config.combine`` says: the consistency update with config.iterations iterations, or
    VALA's streaming median in arrival order.

    ``state`` = (prior [n, D] float32 or [0, D], weight [n] float64, norm [n] float64) is a live
    map's running state, updated in place: Gaussians with weight 0 (all of them when the prior
    has no rows) are computed exactly, the others fold these observations into their prior (see
    ``_consistency``; the median folds exactly). Without it every Gaussian is computed exactly.

    ``evidence`` = (strength sum [n], effective views [n], spread [n]) float64 is written for
    every Gaussian with an observation here: the sum of its d_iv (how much of the views' pixel
    weight it drew, after the quality factors), Kish's effective number of its views under d,
    (sum d)^2 / sum d^2 (one strong view and two glimpses count little more than one), and the
    spread of its views about its F (``_spread``: the d-weighted mean of 1 - cos; NaN where a
    prior was folded into)."""
    first, order = _group_by_owner(observations.owner, n)
    dim = observations.bank.shape[1]
    prior, weight, norm = state if state is not None else (np.zeros((0, dim), np.float32), np.zeros(n), np.zeros(n))
    if len(weight) != n or len(norm) != n or prior.shape not in ((n, dim), (0, dim)):
        raise ValueError(f"state for {n} Gaussians of width {dim}: prior {prior.shape}, weight {weight.shape}")
    if evidence is not None and any(len(array) != n for array in evidence):
        raise ValueError(f"evidence for {n} Gaussians: {[len(array) for array in evidence]} rows")
    if not len(prior):  # no prior: every observed Gaussian is computed exactly
        weight[np.diff(first) > 0] = 0.0
    arrays = (
        first,
        order,
        np.ascontiguousarray(observations.strength, np.float32),
        np.ascontiguousarray(observations.entry_offsets, np.int64),
        np.ascontiguousarray(observations.slots, np.int64),
        np.ascontiguousarray(observations.weights, np.float32),
        np.ascontiguousarray(observations.bank, np.float32),
    )
    prior = np.ascontiguousarray(prior, np.float32)
    seen = np.diff(first) > 0
    spread = np.full(n if evidence is not None else 0, np.nan)
    if config.combine == "streaming_median":
        F = _streaming_median(*arrays, prior, weight, norm, spread)
    else:
        betas = np.array([config.beta_at(t) for t in range(1, config.iterations + 1)], np.float64)
        min_retained = -1.0 if config.min_retained_views is None else float(config.min_retained_views)
        F = _consistency(*arrays, betas, float(config.eps), min_retained, prior, weight, norm, spread)
    if evidence is not None:
        d = observations.strength.astype(np.float64)
        sums = np.bincount(observations.owner, d, minlength=n)[seen]
        squares = np.bincount(observations.owner, d * d, minlength=n)[seen]
        evidence[0][seen], evidence[2][seen] = sums, spread[seen]
        evidence[1][seen] = sums**2 / np.maximum(squares, 1e-300)
    return F, np.diff(first)


def refine_observations(
    owner: np.ndarray,  # [O] int Gaussian index of each observation (0..n-1)
    strength: np.ndarray,  # [O] d_iv
    features: np.ndarray,  # [O, D] f_iv
    n: int,
    config: AggregationConfig = AggregationConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """(F [n, D] float32, observation count [n] int) after config.iterations iterations (the
    consistency update; observations with plain features)."""
    return refine_mixed(MixedObservations.dense(owner, strength, features), n, config)
