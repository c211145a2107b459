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
also recomputes exactly, from all of their views, the stale Gaussians (folds took in
observations since their last exact computation) likeliest to be wrong (``stalest``), as many
as hold ``refresh`` times the observations the fold took in. A pass's cost stays in proportion
to the new views; the budget goes where the approximation errs (a Gaussian no fold touched
since its exact pass is exact, and recomputing it would change nothing: round-robin slices of
the map, the first design, spent most of their budget there).

A fold is not always the cheaper pass: its refresh reads scattered Gaussians (each view's id
list scanned for them) and costs more per observation than an exact pass's sequential read, and
a fold that comes after a long wait takes in a large share of the flight. So a fold runs only
while the observations it would read (its new ones plus its refresh's) stay under
``fold_limit`` times those of an exact pass (every touched Gaussian's); otherwise the pass is
exact, no dearer and without drift (``last_exact`` says which ran). A pass reads the store's
segments up to the views it counted at its start: a segment written while it runs waits for the
next pass (taken in now by an exact recomputation, it would be folded in again by the next fold).
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
    refresh: float = 2.0  # refiner.refresh's default (docs/decisions.md, "A larger refresh on the medium preset")
    # refiner.fold_limit's default (docs/decisions.md, "A fold or an exact pass"): a fold only while
    # it reads at most this share of an exact pass's observations (0: every pass exact; 1e9: always a fold)
    fold_limit: float = 0.85
    last_exact: bool = False  # the last pass was exact (asked for, the first one, or the cheaper)
    last_reads: dict = field(default_factory=dict)  # its observations: added, fold and exact (would read)
    seen: np.ndarray = field(init=False)  # [N] int32 each Gaussian's observations in views 0..views-1
    exact_at: np.ndarray = field(init=False)  # [N] int32 its ``seen`` when it was last computed exactly

    def __post_init__(self) -> None:
        n = self.store.n_gaussians
        self.weight, self.norm = np.zeros(n), np.zeros(n)
        self.seen, self.exact_at = np.zeros(n, np.int32), np.zeros(n, np.int32)

    def update(self, config: AggregationConfig, exact: bool) -> np.ndarray | None:
        """One pass over the views that arrived since the last one (exact, or a fold; the first
        pass is always exact, and so is a fold that would read more than ``fold_limit`` times an
        exact pass's observations); returns the rows it changed [N] bool (None: all rows), and
        nothing changes (an all-False mask) when no view arrived and ``exact`` is False."""
        stop = self.store.touch_views(self.views)
        before = self.seen.copy()
        self.seen += self.store.counts_in(self.views, stop)
        added = int(self.seen.sum(dtype=np.int64) - before.sum(dtype=np.int64))  # a fold's observations
        self.last_reads = self.reads(before, added)
        # strictly more: a fold of no new view reads nothing and stays a fold (it changes nothing)
        exact = exact or self.features is None or self.last_reads["fold"] > self.fold_limit * self.last_reads["exact"]
        self.last_exact = exact
        if exact:
            changed = None if self.features is None else self.store.touched.copy()
            self.features, observed = self.store.refine(
                self.features,
                config,
                self.features is not None,
                unit_float16=True,
                state=(self.weight, self.norm),
                upto=stop,
            )
            self.exact_at[:] = self.seen
        else:
            changed = np.zeros(self.store.n_gaussians, bool)
            if stop == self.views:
                return changed
            state = (self.weight, self.norm)
            self.features, observed = self.store.refine(
                self.features, config, unit_float16=True, state=state, views=(self.views, stop)
            )
            changed[:] = observed
            first_seen = before == 0  # a fold computes these exactly
            self.exact_at[first_seen] = self.seen[first_seen]
            stalest = self.stalest(self.refresh * added)
            if stalest is not None:
                self.features, refreshed = self.store.refine(
                    self.features, config, unit_float16=True, state=state, gaussians=stalest, upto=stop
                )
                self.exact_at[stalest] = self.seen[stalest]
                changed |= refreshed
                observed |= refreshed
        if self.observed is not None and self.features is not None:
            observed |= self.observed  # Gaussians outside this pass keep their state
        self.observed = observed
        self.views = stop
        return changed

    def reads(self, before: np.ndarray, added: int) -> dict[str, int]:
        """What each kind of pass would read now, in observations (``before`` [N]: ``seen``
        before the new views; ``added``: their observations): ``fold`` = the new ones plus the
        refresh's (``refresh`` x added, at most the observations of the Gaussians still stale
        after the fold: not those first seen in it), ``exact`` = every touched Gaussian's."""
        stale = (self.seen > self.exact_at) & (before > 0)
        refresh = min(self.refresh * added, float(self.seen[stale].sum(dtype=np.int64)))
        exact = int(self.seen[self.store.touched].sum(dtype=np.int64))
        return {"added": added, "fold": int(added + refresh), "exact": exact}

    def stalest(self, budget: float) -> np.ndarray | None:
        """[N] bool: the Gaussians to recompute exactly after a fold, the likeliest wrong first
        per observation a recomputation costs, as many as hold at most ``budget``
        observations in all (at least one); None when the budget is 0 or no Gaussian is stale.

        A Gaussian is stale when folds took in observations since its last exact computation.
        Its priority is spread x share / seen: spread = 1 - norm (its views disagree: where the
        consistency weights matter), share = its folded observations / all of them (how much
        of its weighting is stale), and / seen, a recomputation's cost (view features are
        mixtures of unit region features, so norm <= 1; VALA's median, whose folds are exact,
        keeps norm 1: its stale Gaussians tie at 0 and go in index order). Chosen on a training
        flight (docs/decisions.md): with a budget of 30 % of the stale observations after five
        folds it takes in 71 % of the fold's error (1 - cos against the exact map), the share
        alone 23 %, the feature's movement in the folds 26 %."""
        stale = np.flatnonzero(self.seen > self.exact_at)
        if budget <= 0 or not len(stale):
            return None
        seen = self.seen[stale].astype(np.float64)
        spread = 1.0 - np.clip(self.norm[stale], 0.0, 1.0)
        priority = refresh_priority(spread, seen - self.exact_at[stale], seen)
        ranked = stale[np.argsort(-priority, kind="stable")]  # stable: ties keep the index order
        take = max(int(np.searchsorted(np.cumsum(self.seen[ranked], dtype=np.int64), budget, side="right")), 1)
        chosen = np.zeros(len(self.seen), bool)
        chosen[ranked[:take]] = True
        return chosen


def refresh_priority(spread: np.ndarray, folded: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The refresh's priority of stale Gaussians ([M] each, float64): spread (1 - |F|) x share
    (``folded`` / ``seen``: its observations taken in by folds since its last exact computation,
    of all of them) / ``seen`` (what recomputing it costs); ``LiveMap.stalest`` explains it."""
    return spread * folded / (seen * seen)


def warm_up(config: AggregationConfig | None = None, feature_dim: int = 8) -> float:
    """Run a live map's passes once on a made-up store in a temporary folder (64 Gaussians, three
    views of random mixtures): an exact pass, a fold with its refresh, and a snapshot's
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
