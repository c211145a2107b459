"""The observation store: append-only, one segment per view on disk, memory-mapped to read.

Layout of a store folder:

    views/000000/   gaussians.npy strength.npy offsets.npy slots.npy weights.npy bank.npy name.txt
    views/000001/   ...

A segment is written into a temporary folder and renamed into place, so a crash never leaves
half a view, and ``append`` returns only once the view is on disk: an accepted view is never
lost. Sizes: per kept Gaussian and view, 4 (id) + 4 (d) + 8 (offset) bytes plus 8 bytes per
mixture entry (~1-3 per level); the bank is regions x D float16.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
from numba import njit

from .config import AggregationConfig
from .observe import ViewObservations
from .refine import refine_observations, streaming_cosine

_ARRAYS = ("gaussians", "strength", "offsets", "slots", "weights", "bank")


@njit(cache=True)
def _mix_rows(bank, slots, weights, offsets, rows):
    """[len(rows), D] float32: for each chosen row j, sum_e weights[e] * bank[slots[e]] over its entries."""
    out = np.zeros((rows.shape[0], bank.shape[1]), np.float32)
    for i in range(rows.shape[0]):
        for e in range(offsets[rows[i]], offsets[rows[i] + 1]):
            w = weights[e]
            row = bank[slots[e]]
            for d in range(bank.shape[1]):
                out[i, d] += w * row[d]
    return out


class ObservationStore:
    def __init__(self, folder: str | Path, n_gaussians: int):
        self.folder = Path(folder)
        self.n_gaussians = n_gaussians
        (self.folder / "views").mkdir(parents=True, exist_ok=True)
        for leftover in (self.folder / "views").glob("*.tmp"):  # a crash during an earlier append
            shutil.rmtree(leftover)
        self.touched = np.zeros(n_gaussians, bool)  # observed since the last refinement

    def __len__(self) -> int:
        return len(self.segments())

    def segments(self) -> list[Path]:
        return sorted(p for p in (self.folder / "views").iterdir() if p.is_dir() and not p.name.endswith(".tmp"))

    def append(self, name: str, observations: ViewObservations, bank: np.ndarray) -> int:
        """Write one view's observations and its stacked region bank [R, D]; returns the view index."""
        if len(observations) and observations.gaussians.max() >= self.n_gaussians:
            raise ValueError(
                f"view {name!r}: Gaussian {observations.gaussians.max()} is outside the map of {self.n_gaussians}"
            )
        if len(observations.slots) and observations.slots.max() >= len(bank):
            raise ValueError(
                f"view {name!r}: observation slot {observations.slots.max()} is outside its bank of {len(bank)} rows"
            )
        index = len(self.segments())
        final = self.folder / "views" / f"{index:06d}"
        tmp = final.with_name(final.name + ".tmp")
        tmp.mkdir()
        arrays: dict[str, np.ndarray] = {
            "gaussians": observations.gaussians.astype(np.int32),
            "strength": observations.strength.astype(np.float32),
            "offsets": observations.offsets.astype(np.int64),
            "slots": observations.slots.astype(np.int32),
            "weights": observations.weights.astype(np.float32),
            "bank": bank.astype(np.float16),
        }
        for key, value in arrays.items():
            with open(tmp / f"{key}.npy", "wb") as f:
                np.save(f, value)
                f.flush()
                os.fsync(f.fileno())
        (tmp / "name.txt").write_text(name)
        tmp.rename(final)
        self.touched[observations.gaussians] = True
        return index

    def load(self, index: int) -> tuple[ViewObservations, np.ndarray]:
        folder = self.segments()[index]
        a = {key: np.load(folder / f"{key}.npy", mmap_mode="r") for key in _ARRAYS}
        obs = ViewObservations(a["gaussians"], a["strength"], a["offsets"], a["slots"], a["weights"])
        return obs, a["bank"]

    def gather(self, selected: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(owner, view, strength, dense features) of every observation of the selected Gaussians [N] bool."""
        owners, views, strengths, features = [], [], [], []
        for index in range(len(self.segments())):
            obs, bank = self.load(index)
            rows = np.flatnonzero(selected[obs.gaussians])
            if not len(rows):
                continue
            dense = _mix_rows(
                np.asarray(bank, np.float32),
                np.asarray(obs.slots),
                np.asarray(obs.weights),
                np.asarray(obs.offsets),
                rows,
            )
            owners.append(np.asarray(obs.gaussians)[rows])
            views.append(np.full(len(rows), index))
            strengths.append(np.asarray(obs.strength)[rows])
            features.append(dense)
        if not owners:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, 0), np.float32)
        return np.concatenate(owners), np.concatenate(views), np.concatenate(strengths), np.concatenate(features)

    def names(self) -> list[str]:
        """The view names in store order (a node uses them to accept each view once)."""
        return [(segment / "name.txt").read_text() for segment in self.segments()]

    def touch_views(self, first: int) -> int:
        """Mark the Gaussians of views ``first``.. as touched (a refiner in another process
        than the writer learns of new views from the disk); returns the number of views."""
        segments = self.segments()
        for index in range(first, len(segments)):
            self.touched[np.asarray(self.load(index)[0].gaussians)] = True
        return len(segments)

    def observation_counts(self) -> np.ndarray:
        """[N] int64: in how many views each Gaussian has a kept observation."""
        counts = np.zeros(self.n_gaussians, np.int64)
        for index in range(len(self.segments())):
            counts[np.asarray(self.load(index)[0].gaussians)] += 1  # a Gaussian appears once per view
        return counts

    def refine(
        self,
        F: np.ndarray | None,
        config: AggregationConfig,
        only_touched: bool = True,
        max_observations: int = 400_000,
    ):
        """(features [N, D], observed [N] bool). Recomputes the Gaussians touched since the last
        call (all of them when ``only_touched`` is False or F is None); the others keep their
        rows of F. ``observed`` marks the Gaussians with at least one kept observation among
        the recomputed ones. Gaussians are processed in index ranges holding at most
        ``max_observations`` observations (~1 GB of working memory at D = 128), so memory does
        not grow with the map or the flight."""
        selected = self.touched.copy() if (only_touched and F is not None) else np.ones(self.n_gaussians, bool)
        observed = np.zeros(self.n_gaussians, bool)
        out = None if F is None else F.copy()
        cumulative = np.cumsum(self.observation_counts() * selected)
        first = 0
        while first < self.n_gaussians:
            done_before = cumulative[first - 1] if first else 0
            stop = max(int(np.searchsorted(cumulative, done_before + max_observations, side="right")), first + 1)
            part = np.zeros(self.n_gaussians, bool)
            part[first:stop] = selected[first:stop]
            first = stop
            if not part.any():
                continue
            owner, view, strength, features = self.gather(part)
            if not len(owner):
                continue
            if out is None:
                out = np.zeros((self.n_gaussians, features.shape[1]), np.float32)
            rows, local = np.unique(owner, return_inverse=True)  # work on this range's Gaussians only
            local = local.reshape(-1)
            if config.combine == "streaming_cosine":
                refined, count = streaming_cosine(local, view, strength, features, len(rows))
            else:
                refined, count = refine_observations(local, strength, features, len(rows), config)
            out[part] = 0.0  # recomputed; those with observations are set next
            out[rows] = refined
            observed[rows] = count > 0
        self.touched[:] = False
        return out, observed
