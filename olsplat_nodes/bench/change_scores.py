"""The per-Gaussian change scores ``olsplat bench change`` compares, from one run's maps or store.

- **ours** (``aggregate.change.change_score``): the cosine distance of the two flights' features
  over their views' spread, from the default method's per-flight maps; NaN where either flight
  saw the Gaussian too little.
- **projection difference** (``feature_difference``): 1 − cos(F_a, F_b) of the per-flight maps
  made with the ``projection`` method (every contributor of every pixel, alpha*T-weighted mean,
  nothing else); NaN where either flight did not observe the Gaussian at all.
- **heatmap difference** (``best_view_difference``): no aggregation over views. Per flight, each
  Gaussian takes the 2D feature of the one view that sees it best (the largest d_iv, the
  alpha*T weight of its pixels in that view) as that view re-projects it: the mixture of the
  view's region features over the pixels it covers (``ViewObservations.features``). The score
  is 1 − cos of the two flights' such features, NaN where either flight has none. Read from the
  ``projection`` run's store, so both baselines start from the same observations.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

METHODS = ("ours", "projection difference", "heatmap difference")


class FeatureMap(Protocol):
    @property
    def features(self) -> np.ndarray: ...  # [N, D] rows (any scale)
    @property
    def observed(self) -> np.ndarray: ...  # [N] bool


def cosine_distance(a: np.ndarray, b: np.ndarray, both: np.ndarray) -> np.ndarray:
    """[N] float32: 1 − cos of rows a [N, D] and b [N, D] where ``both`` [N] bool, NaN elsewhere
    (and where a row is zero)."""
    out = np.full(len(both), np.nan, np.float32)
    rows = np.flatnonzero(both)
    fa, fb = np.asarray(a[rows], np.float64), np.asarray(b[rows], np.float64)
    norms = np.linalg.norm(fa, axis=1) * np.linalg.norm(fb, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out[rows] = np.where(norms > 0, 1.0 - np.einsum("ij,ij->i", fa, fb) / norms, np.nan)
    return out


def feature_difference(map_a: FeatureMap, map_b: FeatureMap) -> np.ndarray:
    """[N] float32 1 − cos(F_a, F_b) where both maps observed the Gaussian, NaN elsewhere."""
    if len(map_a.observed) != len(map_b.observed) or len(map_a.features) != len(map_a.observed):
        raise ValueError("two float maps of one prior map needed (codebook maps are not compared here)")
    return cosine_distance(map_a.features, map_b.features, map_a.observed & map_b.observed)


def best_view_features(store: str | Path, n: int, flight: str) -> tuple[np.ndarray, np.ndarray]:
    """(features [N, D] float32, strength [N] float32) of one flight (``"f1"``) of a run's store
    (one tile, ``store/views/``): per Gaussian, its feature in the flight's view with the largest
    d_iv and that d_iv; zero rows and 0 where no view of the flight observed it."""
    from ..storage.flights import flight_of
    from ..storage.store import ObservationStore

    reader = ObservationStore(store, n, keep=lambda name: flight_of(name) == flight)
    segments = reader.segments()
    best = np.zeros(n, np.float32)
    features: np.ndarray | None = None
    for index in range(len(segments)):
        if not reader.usable(index, segments):
            continue
        observations, bank = reader.load(index, segments)
        ids, strength = np.asarray(observations.gaussians), np.asarray(observations.strength, np.float32)
        better = np.flatnonzero(strength > best[ids])
        if not len(better):
            continue
        here = observations.features(np.asarray(bank, np.float32))  # [G, D]
        if features is None:
            features = np.zeros((n, here.shape[1]), np.float32)
        features[ids[better]] = here[better]
        best[ids[better]] = strength[better]
    if features is None:
        raise ValueError(f"{store}: no view of flight {flight} observed any Gaussian")
    return features, best


def best_view_difference(store: str | Path, n: int, flight_a: str, flight_b: str) -> np.ndarray:
    """[N] float32 1 − cos of the two flights' best-view features (``best_view_features``), NaN
    where either flight never observed the Gaussian."""
    fa, wa = best_view_features(store, n, flight_a)
    fb, wb = best_view_features(store, n, flight_b)
    return cosine_distance(fa, fb, (wa > 0) & (wb > 0))
