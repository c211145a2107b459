"""Change scores between two flights' language maps of one prior map, Gaussian by Gaussian.

Each flight's map (``storage/flights.py``) carries, per Gaussian, its feature F (from that
flight's views alone) and the evidence behind it: W = sum of d_iv over the flight's views, n =
Kish's effective number of those views under d, (sum d)^2 / sum d^2, and s = the spread of its
views about F, the d-weighted mean of 1 - cos(f_iv, F). The rule:

    c     = 1 - cos(F_a, F_b)                                   cosine distance, 0..2
    noise = s_a + s_b + s0 / n_a + s0 / n_b
    score = c / noise        where both flights saw it well enough (n >= min_views, W >= min_weight)
    score = NaN              elsewhere: unknown, neither changed nor unchanged

s is how far one view of a flight typically falls from that flight's F; if nothing changed, the
other flight's F is in effect one more (well-averaged) view, so c compared with s_a + s_b asks
whether the flights disagree more than each flight's views disagree among themselves. s0 / n
is a prior spread that fades with the evidence: a flight whose few views happen to agree
(s ~ 0 from two views) is not thereby certain, and fewer views mean a larger noise. The spread
is weighted by d, not by the consistency weights rho: those all but drop the views that
disagree with F, so a Gaussian whose views split into two camps would look certain. The
effective count, not the plain count, gates and scales: one good view and two glimpses are
about one view (a Gaussian seen once, obliquely, scores NaN).

Why not the mean's standard error (s / n): two flights see a Gaussian from other sides and cut
other regions around it, a difference that more views of the same flight do not average out;
with s / n the no-change flights of the tiny town reached scores of 60 (docs/decisions.md).

``_reference.change_score_dense`` computes the same from raw per-view observations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .codebook import decompress

_ROWS = 32_768  # Gaussians per chunk: a chunk's float64 rows stay ~50 MB at D = 128


@dataclass(frozen=True)
class ChangeRule:
    """When a Gaussian counts as seen well enough in a flight, and the prior spread s0."""

    min_views: float = 2.0  # effective views (Kish, under d) each flight needs; below: NaN
    min_weight: float = 0.5  # sum of d_iv each flight needs (pixel weight, after the quality factors); below: NaN
    prior_spread: float = 0.4  # s0: the spread assumed of one view, added as s0 / n per flight
    threshold: float = 3.0  # a score above this is a change (no Gaussian of two no-change flights reaches it)

    def __post_init__(self) -> None:
        if not self.min_views >= 1.0 or self.min_weight < 0.0 or not self.prior_spread > 0.0:
            raise ValueError(f"need min_views >= 1, min_weight >= 0 and prior_spread > 0, got {self}")
        if not self.threshold > 0.0:
            raise ValueError(f"the threshold must be > 0, got {self.threshold}")


class FlightFeatures(Protocol):
    """A flight's map's features (``storage.LanguageMap``), as rows or as codes."""

    @property
    def features(self) -> np.ndarray: ...  # [N, D] unit rows, or [0, D] when kept as codes
    @property
    def observed(self) -> np.ndarray: ...  # [N] bool
    @property
    def codes(self) -> np.ndarray | None: ...  # [N] uint16 codebook form (65535: unobserved)
    @property
    def centres(self) -> np.ndarray | None: ...  # [K, D]


class FlightMap(FlightFeatures, Protocol):
    """What a change score reads of a flight's map (``storage.LanguageMap`` with its evidence)."""

    @property
    def strength_sum(self) -> np.ndarray | None: ...  # [N] W
    @property
    def effective_views(self) -> np.ndarray | None: ...  # [N] n
    @property
    def view_spread(self) -> np.ndarray | None: ...  # [N] s


def feature_rows(flight: FlightFeatures, lo: int, hi: int, dtype=np.float64) -> np.ndarray:
    """Rows lo..hi-1 of a map's features ([hi - lo, D], ``dtype``), decoded from its codes if it
    keeps them."""
    if len(flight.features) == len(flight.observed):
        return np.asarray(flight.features[lo:hi], dtype)
    if flight.codes is None or flight.centres is None:
        raise ValueError(f"a map of {len(flight.observed)} Gaussians with {len(flight.features)} feature rows")
    return decompress(flight.codes[lo:hi], flight.centres).astype(dtype)


def _evidence(flight: FlightMap, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    arrays = (flight.strength_sum, flight.effective_views, flight.view_spread)
    if any(array is None for array in arrays):
        raise ValueError(
            f"map {name} carries no evidence (strength_sum, effective_views, view_spread): not a flight's map"
        )
    return tuple(np.asarray(array, np.float64) for array in arrays)  # type: ignore[return-value]


def seen_well(
    strength_sum: np.ndarray, effective_views: np.ndarray, spread: np.ndarray, rule: ChangeRule
) -> np.ndarray:
    """[N] bool: the Gaussians a flight saw well enough to be compared (its W, n and s [N])."""
    return (effective_views >= rule.min_views) & (strength_sum >= rule.min_weight) & np.isfinite(spread)


def change_score(map_a: FlightMap, map_b: FlightMap, rule: ChangeRule = ChangeRule()) -> np.ndarray:
    """[N] float32: each Gaussian's change score from flight a's map to flight b's (the rule in
    the module's docstring): ~0 .. 1 where they agree within their views' spread, above
    ``rule.threshold`` for a change, NaN where either flight did not see it well enough."""
    n = len(map_a.observed)
    if len(map_b.observed) != n:
        raise ValueError(f"maps of {n} and {len(map_b.observed)} Gaussians: not two flights of one prior map")
    W_a, n_a, s_a = _evidence(map_a, "a")
    W_b, n_b, s_b = _evidence(map_b, "b")
    ok = seen_well(W_a, n_a, s_a, rule) & seen_well(W_b, n_b, s_b, rule) & map_a.observed & map_b.observed
    score = np.full(n, np.nan, np.float32)
    for lo in range(0, n, _ROWS):
        hi = min(n, lo + _ROWS)
        here = np.flatnonzero(ok[lo:hi])
        if not len(here):
            continue
        fa, fb = feature_rows(map_a, lo, hi)[here], feature_rows(map_b, lo, hi)[here]
        norms = np.linalg.norm(fa, axis=1) * np.linalg.norm(fb, axis=1)
        distance = 1.0 - np.einsum("ij,ij->i", fa, fb) / np.maximum(norms, 1e-12)
        rows = lo + here
        noise = s_a[rows] + s_b[rows] + rule.prior_spread / n_a[rows] + rule.prior_spread / n_b[rows]
        score[rows] = distance / noise
    return score
