"""A live language map: the refiner's running features over a growing observation store.

A pass is either exact (every touched Gaussian recomputed from all of its views, as the paper's
aggregation over the whole flight) or a fold (only the views that arrived since the last pass,
folded into the running features): an exact pass costs the observations of the Gaussians the new
views touched, which on a survey flight is most of the map times the views so far, so exact
passes grow with the flight; a fold costs the new views only. The first pass after a start is
exact (nothing to fold into) and so is the final one, so the final map equals the offline map.

What a fold approximates (see ``refine.refine_mixed``): with the consistency update, a Gaussian
seen before weighs each new view with rho = d exp(beta_T cos(f, F)) against its current F, and
its earlier views keep the weights they had; a Gaussian first seen in the new views is exact.
VALA's streaming median folds exactly. So that these approximations do not pile up, each fold
also recomputes exactly a slice of the map holding ``refresh`` times as many observations as
the fold took in, the slices going round the map in index order: a pass's cost stays in
proportion to the new views, and a Gaussian is recomputed from all of its views again within
the passes that bring in as many observations as the map already holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..aggregate.config import AggregationConfig
from ..storage.store import ObservationStore


@dataclass
class LiveMap:
    """features [N, D] float16 unit rows (None before the first pass); observed [N] bool;
    weight [N] float64 each Gaussian's sum of final view weights and norm [N] float64 the
    length of its mean before normalising (the state a fold needs); views: the store's segments
    0..views-1 are in the map."""

    store: ObservationStore
    features: np.ndarray | None = None
    observed: np.ndarray | None = None
    weight: np.ndarray = field(init=False)
    norm: np.ndarray = field(init=False)
    views: int = 0
    refresh: float = 1.0
    cursor: int = 0  # the next refresh slice starts at this Gaussian
    counted: int = 0  # the store's observations when the last refresh slice was chosen

    def __post_init__(self) -> None:
        self.weight = np.zeros(self.store.n_gaussians)
        self.norm = np.zeros(self.store.n_gaussians)

    def update(self, config: AggregationConfig, exact: bool) -> np.ndarray | None:
        """One pass over the views that arrived since the last one (exact, or a fold; the first
        pass is always exact); returns the rows it changed [N] bool (None: all rows), and
        nothing changes (an all-False mask) when no view arrived and ``exact`` is False."""
        stop = self.store.touch_views(self.views)
        if self.features is None or exact:
            changed = None if self.features is None else self.store.touched.copy()
            self.features, observed = self.store.refine(
                self.features, config, self.features is not None, unit_float16=True, state=(self.weight, self.norm)
            )
            self.counted = int(self.store.observation_counts().sum())  # the next fold's budget counts from here
        else:
            changed = np.zeros(self.store.n_gaussians, bool)
            if stop == self.views:
                return changed
            state = (self.weight, self.norm)
            self.features, observed = self.store.refine(
                self.features, config, unit_float16=True, state=state, views=(self.views, stop)
            )
            changed[:] = observed
            span = self._refresh_span()
            if span is not None:
                self.features, refreshed = self.store.refine(
                    self.features, config, unit_float16=True, state=state, gaussians=span
                )
                changed[slice(*span)] |= refreshed[slice(*span)]
                observed |= refreshed
        if self.observed is not None and self.features is not None:
            observed |= self.observed  # Gaussians outside this pass keep their state
        self.observed = observed
        self.views = stop
        return changed

    def _refresh_span(self) -> tuple[int, int] | None:
        """The next slice (lo, hi) of Gaussians to recompute exactly after a fold: from the
        cursor, as many of the map's observations as ``refresh`` times those the fold took in
        (the growth of the store's running count since the last fold; at least one Gaussian);
        None when refresh is 0."""
        counts = self.store.observation_counts()
        total = int(counts.sum())
        budget, self.counted = self.refresh * (total - self.counted), total
        if budget <= 0:
            return None
        if self.cursor >= len(counts):
            self.cursor = 0
        lo = self.cursor
        hi = lo + max(int(np.searchsorted(np.cumsum(counts[lo:]), budget, side="right")), 1)
        self.cursor = min(hi, len(counts))
        return lo, self.cursor
