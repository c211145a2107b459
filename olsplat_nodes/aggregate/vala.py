"""VALA's per-view step, the ``vala`` baseline (Wang et al., "Visibility-Aware Language
Aggregation for Open-Vocabulary Segmentation in 3D Gaussian Splatting", 2025, Sec. 4.1,
eqs. 8-13, and its released code).

A Gaussian's weight in a view is its marginal contribution w = alpha * T on the ray through
the pixel of its projected centre (0 when that ray saturates before reaching it), and its view
feature is that pixel's feature (eq. 8); no sum over pixels. The visibility gate then keeps,
per view, the Gaussians that are:

- stage A (eqs. 11-12): among the strongest holding ``gate_mass`` (tau_mass) of the view's
  total weight, and with w >= ``gate_floor`` (tau_abs); when none is, the strongest one;
- stage B (eq. 13 as the released code has it): w > min(``gate_cut``, the 0.85 quantile of
  w), with gate_cut = 0.15 in the code;
- at most the strongest half of the Gaussians the view reaches (released code);
- on a pixel that has a feature (our valid mask M_v; the code's "inside a SAM mask").

Views are combined by the streaming geometric median in cosine space (``refine.py``,
``combine="streaming_median"``). The defaults of tau_mass, tau_abs and the cut are VALA's values for
LERF scenes (0.75, 0.13, 0.15); docs/evaluation.md ("Comparisons") gives the values tuned on our training seeds.
Not reproduced: the code's final pruning of Gaussians with little total weight (it deletes
them from the scene, which a map of fixed Gaussians cannot do) and its half-pixel offset
between the weight's pixel and the feature's pixel (ours is the pixel containing the centre).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .config import AggregationConfig
from .observe import ViewObservations, level_weights

STAGE_B_QUANTILE = 0.85  # the released code's quantile of stage B
MAX_SHARE = 0.5  # at most this share of the Gaussians a view reaches are kept


@njit(cache=True)
def _centre_weights(topk_ids, topk_weights, means2d, radii, width, height):
    """(pixel [N] int64 flat index of the centre's pixel or -1, w [N] float32): Gaussian i's
    alpha*T on that pixel, found in the pixel's contribution list (0 when it is not there)."""
    n = means2d.shape[0]
    pixel = np.full(n, -1, np.int64)
    weight = np.zeros(n, np.float32)
    k = topk_ids.shape[1]
    for i in range(n):
        if radii[i] <= 0:
            continue
        u, v = means2d[i, 0], means2d[i, 1]
        if not (0.0 <= u < width and 0.0 <= v < height):
            continue
        p = int(v) * width + int(u)
        pixel[i] = p
        for r in range(k):
            if topk_ids[p, r] == i:
                weight[i] = topk_weights[p, r]
                break
    return pixel, weight


def visibility_gate(w: np.ndarray, tau_mass: float, tau_abs: float, cut: float = 0.15) -> np.ndarray:
    """[M] bool: which of a view's M reached Gaussians (weights w [M] > 0) the gate keeps
    (stages A and B and the cap of the module docstring)."""
    if not len(w):
        return np.zeros(0, bool)
    ranked = np.argsort(-w, kind="stable")
    cumulative = np.cumsum(w[ranked], dtype=np.float64)
    k_mass = min(int(np.searchsorted(cumulative, tau_mass * cumulative[-1])) + 1, len(w))
    stage_a = np.zeros(len(w), bool)
    stage_a[ranked[:k_mass]] = True
    stage_a &= w >= tau_abs
    if not stage_a.any():
        stage_a[ranked[0]] = True
    stage_b = w > min(cut, float(np.quantile(w, STAGE_B_QUANTILE)))
    capped = np.zeros(len(w), bool)
    capped[ranked[: int(MAX_SHARE * len(w))]] = True
    return stage_a & stage_b & capped


def observe_view_centres(
    topk_ids: np.ndarray,  # [H, W, K] int32, -1 padded: every contributor of each pixel (K large)
    topk_weights: np.ndarray,  # [H, W, K] float32 alpha*T
    means2d: np.ndarray,  # [N, 2] projected centres in pixels (pixel centres at +0.5)
    radii: np.ndarray,  # [N] int32, 0 = culled
    slot_maps: np.ndarray,  # [L, H, W] int32 rows of the stacked bank, -1 = no feature
    n_gaussians: int,
    config: AggregationConfig,
) -> ViewObservations:
    """The view's observations as VALA forms them: strength = the centre weight w, feature =
    the centre pixel's feature (a mixture over levels with the level weights)."""
    height, width, k = topk_ids.shape
    if slot_maps.shape[1:] != (height, width) or len(means2d) != n_gaussians:
        raise ValueError(f"label maps {slot_maps.shape[1:]} / centres {means2d.shape} do not fit the view")
    ids = np.ascontiguousarray(topk_ids.reshape(height * width, k))
    weights = np.ascontiguousarray(topk_weights.reshape(height * width, k), np.float32)
    pixel, w = _centre_weights(ids, weights, np.ascontiguousarray(means2d, np.float32), radii, width, height)
    reached = np.flatnonzero(w > 0)
    kept = reached[visibility_gate(w[reached], config.gate_mass, config.gate_floor, config.gate_cut)]
    slots = slot_maps.reshape(slot_maps.shape[0], -1)[:, pixel[kept]]  # [L, kept]
    valid = (slots >= 0).all(0)  # the gate's survivors on a pixel with a feature
    kept, slots = kept[valid], slots[:, valid]
    a = level_weights(config, slot_maps.shape[0])
    used = np.flatnonzero(a > 0)
    return ViewObservations(
        gaussians=kept.astype(np.int32),
        strength=w[kept].astype(np.float32),
        offsets=np.arange(len(kept) + 1, dtype=np.int64) * len(used),
        slots=slots[used].T.reshape(-1).astype(np.int32),  # per Gaussian, its used levels in order
        weights=np.tile(a[used], len(kept)).astype(np.float32),
    )
