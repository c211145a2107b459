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


def warm_up(config: AggregationConfig | None = None, feature_dim: int = 8) -> float:
    """Run a live map's passes once on a made-up store in a temporary folder (64 Gaussians, three
    views of random mixtures): an exact pass, a fold with its refresh slice, and a snapshot's
    write, so that numba compiles the refinement kernels (or loads them from its cache) when the
    refiner starts and not in its first pass, while the accumulator compiles its own: on a fresh
    install that first pass took 42 s of a 12-view flight. ``config``: the aggregation to warm
    (the default method's when None; VALA's median compiles at its first pass). Nothing is kept.
    Returns the seconds it took."""
    import tempfile
    import time
    from pathlib import Path

    from ..aggregate.observe import ViewObservations
    from ..storage import LanguageMap, write_snapshot

    start = time.perf_counter()
    config = config or AggregationConfig()
    rng = np.random.default_rng(0)
    n = 64
    with tempfile.TemporaryDirectory(prefix="olsplat-warm-up-") as folder:
        store = ObservationStore(Path(folder) / "store", n, writer=True)
        live = LiveMap(store)
        for view in range(3):
            seen = np.sort(rng.choice(n, 48, replace=False)).astype(np.int32)
            offsets = np.arange(0, 2 * len(seen) + 1, 2, dtype=np.int64)  # two regions per Gaussian
            observations = ViewObservations(
                seen,
                rng.uniform(0.1, 1.0, len(seen)).astype(np.float32),
                offsets,
                rng.integers(0, 4, 2 * len(seen)).astype(np.int32),
                np.full(2 * len(seen), 0.5, np.float32),
            )
            store.append(f"warm_up_{view}", observations, rng.normal(size=(4, feature_dim)).astype(np.float32))
            live.update(config, exact=view != 1)  # exact (the first pass), a fold, exact (the final one)
        assert live.features is not None and live.observed is not None
        write_snapshot(Path(folder) / "map", 1, LanguageMap(live.features, live.observed, "warm-up"), {}, None)
    return time.perf_counter() - start
