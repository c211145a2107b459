"""The observation store: append-only, one segment per view on disk, memory-mapped to read.

Layout of a store folder:

    views/000000/   gaussians.npy strength.npy offsets.npy slots.npy weights.npy bank.npy name.txt
    views/000001/   ...

A segment is written into a temporary folder and renamed into place, so a crash never leaves
half a view, and ``append`` returns only once the view is on disk (every file, the folder and
the rename fsynced): an accepted view is never lost, not even to a power cut. Sizes: per kept
Gaussian and view, 4 (id) + 4 (d) + 8 (offset) bytes plus 8 bytes per mixture entry (~1-3 per
level); the bank is regions x D float16.
"""

from __future__ import annotations

import errno
import logging
import mmap
import os
import shutil
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from numba import njit

from ..aggregate.config import AggregationConfig
from ..aggregate.observe import ViewObservations
from ..aggregate.refine import MixedObservations, refine_mixed
from ..durable import free_mb, fsync_dir, write_atomic
from .snapshot import normalise_rows

log = logging.getLogger(__name__)
_ARRAYS = ("gaussians", "strength", "offsets", "slots", "weights", "bank")


@njit(cache=True)
def _take_entries(offsets, slots, weights, rows, slot_base):
    """The mixture entries of the chosen rows: (entry_offsets [len(rows)+1], slots + slot_base,
    weights), so that they index a bank stacked over views."""
    counts = np.empty(rows.shape[0] + 1, np.int64)
    counts[0] = 0
    for i in range(rows.shape[0]):
        counts[i + 1] = counts[i] + offsets[rows[i] + 1] - offsets[rows[i]]
    out_slots = np.empty(counts[-1], np.int64)
    out_weights = np.empty(counts[-1], np.float32)
    for i in range(rows.shape[0]):
        e0 = offsets[rows[i]]
        for j in range(counts[i + 1] - counts[i]):
            out_slots[counts[i] + j] = slots[e0 + j] + slot_base
            out_weights[counts[i] + j] = weights[e0 + j]
    return counts, out_slots, out_weights


def _npy_header(path: Path) -> tuple[np.dtype, tuple[int, ...], int]:
    """(dtype, shape, data offset) of a C-order ``.npy`` file, as ``np.load`` reads them."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:  # np.save writes 1.0 for the arrays a store holds
            raise ValueError(f"{path}: .npy format {version} is not one a store writes")
        if fortran or dtype.hasobject:
            raise ValueError(f"{path}: not a plain C-order array")
        return dtype, tuple(shape), f.tell()


def _map_npy(path: Path, header: tuple[np.dtype, tuple[int, ...], int]) -> np.ndarray:
    """The array of ``path`` memory-mapped read-only, from its known header: what
    ``np.load(path, mmap_mode="r")`` gives, without parsing the header again (a refinement
    pass maps every segment once per range: ~0.3 ms an array through ``np.load``, 12 s of a
    pass at 300 views of the large flight). A file shorter than its header says is a ValueError."""
    dtype, shape, offset = header
    count = int(np.prod(shape))
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size < offset + count * dtype.itemsize:
            raise ValueError(f"{path}: {size} bytes, its header needs {offset + count * dtype.itemsize}")
        if count == 0:
            return np.empty(shape, dtype)
        buffer = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # the mapping outlives the file object
    return np.frombuffer(buffer, dtype, count, offset).reshape(shape)


# A segment's files (name stem -> the type it is stored in): one table for what the store
# writes and what a run's disk estimate counts.
SEGMENT_TYPES = {
    "gaussians": np.int32,
    "strength": np.float32,
    "offsets": np.int64,
    "slots": np.int32,
    "weights": np.float32,
    "bank": np.float16,
}


def _segment_sources(observations: ViewObservations, bank: np.ndarray) -> dict[str, np.ndarray]:
    return {
        "gaussians": observations.gaussians,
        "strength": observations.strength,
        "offsets": observations.offsets,
        "slots": observations.slots,
        "weights": observations.weights,
        "bank": bank,
    }


def segment_bytes(observations: ViewObservations, bank: np.ndarray) -> int:
    """The bytes of a view's store segment (its arrays; each file adds a 128-byte header)."""
    sources = _segment_sources(observations, bank)
    return sum(sources[key].size * np.dtype(kind).itemsize for key, kind in SEGMENT_TYPES.items())


class ObservationStore:
    """A store folder opened by its one writer (``writer=True``: the accumulator, an offline
    run) or by any number of readers (the refiner, tools, tests). Only the writer removes the
    ``*.tmp`` segment a crash left behind: a reader that did so could delete a segment the
    live writer is still filling, which then enters the store with files missing.

    A reader with ``keep`` (a test of a view's name) sees only the views it keeps, in store
    order (e.g. one flight's, ``f1/...``): their map is the map of those views alone."""

    def __init__(
        self, folder: str | Path, n_gaussians: int, writer: bool = False, keep: Callable[[str], bool] | None = None
    ):
        if writer and keep is not None:
            raise ValueError(f"{folder}: a store's writer sees every view (keep is for readers)")
        self.folder = Path(folder)
        self.n_gaussians = n_gaussians
        self.writer = writer
        self.keep = keep
        self.kept: dict[str, bool] = {}  # segment folder name -> keep(its view name), once per segment
        if writer:
            (self.folder / "views").mkdir(parents=True, exist_ok=True)
            for leftover in (self.folder / "views").glob("*.tmp"):  # a crash during an earlier append
                shutil.rmtree(leftover)
        self.touched = np.zeros(n_gaussians, bool)  # observed since the last refinement
        self.checked: set[str] = set()  # segments found whole (they never change once written)
        self.quarantined: dict[str, str] = {}  # segment folder name -> why it is skipped
        # headers of the segments' arrays (segments never change once written): a few hundred
        # bytes per view, so that mapping a segment again does not parse its headers again
        self.headers: dict[tuple[str, str], tuple[np.dtype, tuple[int, ...], int]] = {}
        # per-Gaussian count of kept observations over the first ``counted`` segments (usable ones)
        self.counts = np.zeros(n_gaussians, np.int64)
        self.counted = 0

    def __len__(self) -> int:
        return len(self.segments())

    def segments(self) -> list[Path]:
        views = self.folder / "views"
        if not views.is_dir():  # a reader before the writer's first view
            return []
        found = sorted(p for p in views.iterdir() if p.is_dir() and not p.name.endswith(".tmp"))
        return found if self.keep is None else [p for p in found if self._kept(p)]

    def _kept(self, segment: Path) -> bool:
        """Whether ``keep`` keeps this segment's view (one whose name cannot be read is not kept)."""
        if segment.name not in self.kept:
            try:
                name = (segment / "name.txt").read_text()
            except OSError:
                return False  # perhaps not yet: asked again next time
            self.kept[segment.name] = bool(self.keep and self.keep(name))
        return self.kept[segment.name]

    def append(self, name: str, observations: ViewObservations, bank: np.ndarray) -> int:
        """Write one view's observations and its stacked region bank [R, D]; returns the view index."""
        if not self.writer:
            raise RuntimeError(f"{self.folder}: the store was opened for reading; open it with writer=True")
        if len(observations) and observations.gaussians.max() >= self.n_gaussians:
            raise ValueError(
                f"view {name!r}: Gaussian {observations.gaussians.max()} is outside the map of {self.n_gaussians}"
            )
        if len(observations.slots) and observations.slots.max() >= len(bank):
            raise ValueError(
                f"view {name!r}: observation slot {observations.slots.max()} is outside its bank of {len(bank)} rows"
            )
        segments = self.segments()
        good = next((i for i in range(len(segments)) if self.usable(i, segments)), None)
        if good is not None:  # every view's bank has the width of the first one: the refinement mixes them
            width = self.load(good, segments)[1].shape[1]
            if bank.shape[1] != width:
                raise ValueError(f"view {name!r}: features of width {bank.shape[1]}, the store holds width {width}")
        index = len(segments)
        final = self.folder / "views" / f"{index:06d}"
        tmp = final.with_name(final.name + ".tmp")
        sources = _segment_sources(observations, bank)
        arrays = {key: sources[key].astype(kind) for key, kind in SEGMENT_TYPES.items()}
        try:
            self._write_segment(tmp, name, arrays)
        except OSError as exc:
            # a full disk (or a file-size limit) mid-view: the half-written segment goes, so the
            # next append can take this index once there is room, and the error says where
            shutil.rmtree(tmp, ignore_errors=True)
            size = sum(a.nbytes for a in arrays.values())
            raise OSError(
                exc.errno or errno.EIO,
                f"view {name!r} ({size:,} bytes) could not be written: {exc.strerror or exc}; "
                f"{free_mb(self.folder):,.0f} MB free on its disk",
                str(self.folder),
            ) from exc
        missing = ({f"{key}.npy" for key in arrays} | {"name.txt"}) - {f.name for f in tmp.iterdir()}
        if missing:  # something else removed them: never publish a segment with holes
            raise OSError(f"{tmp}: {sorted(missing)} vanished while the segment was written")
        tmp.rename(final)
        fsync_dir(final.parent)  # the rename: once append returns, the view is on the disk
        self.touched[observations.gaussians] = True
        return index

    @staticmethod
    def _write_segment(tmp: Path, name: str, arrays: dict[str, np.ndarray]) -> None:
        """A view's files into the new folder ``tmp``, each durable (fsync) before it is listed."""
        tmp.mkdir()
        for key, value in arrays.items():
            with open(tmp / f"{key}.npy", "wb") as f:
                np.save(f, value)
                f.flush()
                os.fsync(f.fileno())
                # numpy copies a small array through a C stream whose last failed flush it does not
                # report: a file cut short by a full disk would otherwise be published
                written = os.fstat(f.fileno()).st_size
                if written != f.tell():
                    raise OSError(errno.EIO, f"{key}.npy cut short: {written} of {f.tell()} bytes written")
        with open(tmp / "name.txt", "w") as text:
            text.write(name)
            text.flush()
            os.fsync(text.fileno())
        fsync_dir(tmp)  # the segment's file entries, before it becomes visible

    def usable(self, index: int, segments: list[Path]) -> bool:
        """Whether segment ``index`` is whole and consistent; one that is not (damaged on disk,
        or written by other code) is quarantined: ``QUARANTINED.txt`` in its folder says why, it
        keeps its index (the views folder is numbered by it) and every pass skips it, so one bad
        segment never stops the refinement. Checked once per segment and process."""
        folder = segments[index]
        if folder.name in self.checked:
            return True
        if folder.name in self.quarantined:
            return False
        marker = folder / "QUARANTINED.txt"
        reason = marker.read_text() if marker.exists() else self._problem(index, segments)
        if reason is None:
            self.checked.add(folder.name)
            return True
        if not marker.exists():
            write_atomic(marker, reason.encode())
            log.error("view segment %s quarantined (skipped from now on): %s", folder, reason)
        self.quarantined[folder.name] = reason
        return False

    def _problem(self, index: int, segments: list[Path]) -> str | None:
        try:
            obs, bank = self.load(index, segments)
            n = len(obs.gaussians)
            if len(obs.strength) != n or len(obs.offsets) != n + 1 or bank.ndim != 2:
                return f"inconsistent lengths: {n} Gaussians, {len(obs.strength)} strengths, {len(obs.offsets)} offsets"
            offsets = np.asarray(obs.offsets)
            entries = len(obs.slots)
            if offsets[0] != 0 or (np.diff(offsets) < 0).any() or offsets[-1] != entries or len(obs.weights) != entries:
                return "mixture offsets do not index its entries"
            if n and (np.asarray(obs.gaussians).min() < 0 or np.asarray(obs.gaussians).max() >= self.n_gaussians):
                return f"Gaussian ids outside the map of {self.n_gaussians}"
            if len(obs.slots) and (np.asarray(obs.slots).min() < 0 or np.asarray(obs.slots).max() >= len(bank)):
                return f"slots outside its bank of {len(bank)} rows"
            width = next((self.load(i, segments)[1].shape[1] for i in range(index) if self.usable(i, segments)), None)
            if width is not None and bank.shape[1] != width:
                return f"features of width {bank.shape[1]}, the store holds width {width}"
            if not np.isfinite(np.asarray(obs.strength)).all() or not np.isfinite(np.asarray(bank)).all():
                return "NaN or infinite values"
            (segments[index] / "name.txt").read_text()
        except (OSError, ValueError, EOFError) as exc:
            return f"unreadable: {exc}"
        return None

    def load(self, index: int, segments: list[Path] | None = None) -> tuple[ViewObservations, np.ndarray]:
        """View ``index``'s observations and bank, memory-mapped; ``segments`` is a listing of
        ``segments()`` to reuse (a pass over all views lists the folder once)."""
        folder = (self.segments() if segments is None else segments)[index]
        a = {}
        for key in _ARRAYS:
            path = folder / f"{key}.npy"
            header = self.headers.get((folder.name, key)) or _npy_header(path)
            a[key] = _map_npy(path, header)
            self.headers[(folder.name, key)] = header  # once it mapped: a damaged file's header is read again
        obs = ViewObservations(a["gaussians"], a["strength"], a["offsets"], a["slots"], a["weights"])
        return obs, a["bank"]

    def gather(
        self,
        selected: np.ndarray,
        segments: list[Path] | None = None,
        span: tuple[int, int] | None = None,
        views: tuple[int, int] | None = None,
    ) -> MixedObservations:
        """Every observation of the selected Gaussians [N] bool, view by view in store order, with
        its features as mixtures of the views' banks stacked into one [S, D] float32 bank. With
        ``span`` = (lo, stop) only Gaussians lo <= g < stop: a view's ids are ascending, so its
        part is found by bisection instead of a scan of all of them. With ``views`` = (first,
        stop) only the segments first <= index < stop."""
        segments = self.segments() if segments is None else segments
        parts: list[tuple] = []
        banks: list[np.ndarray] = []
        slot_base = 0
        for index in range(*(views or (0, len(segments)))):
            if not self.usable(index, segments):
                continue
            obs, bank = self.load(index, segments)
            ids = np.asarray(obs.gaussians)
            a, b = (0, len(ids)) if span is None else (int(i) for i in np.searchsorted(ids, span))
            rows = a + np.flatnonzero(selected[ids[a:b]])
            if not len(rows):
                continue
            entries = _take_entries(
                np.asarray(obs.offsets), np.asarray(obs.slots), np.asarray(obs.weights), rows, slot_base
            )
            parts.append((np.asarray(obs.gaussians)[rows], np.asarray(obs.strength)[rows], *entries))
            banks.append(np.asarray(bank, np.float32))
            slot_base += len(bank)
        if not parts:
            return MixedObservations.dense(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 0)))
        entry_offsets = [parts[0][2]]
        for part in parts[1:]:  # each part's offsets continue from the entries before it
            entry_offsets.append(part[2][1:] + entry_offsets[-1][-1])
        return MixedObservations(
            np.concatenate([p[0] for p in parts]).astype(np.int64),
            np.concatenate([p[1] for p in parts]),
            np.concatenate(entry_offsets),
            np.concatenate([p[3] for p in parts]),
            np.concatenate([p[4] for p in parts]),
            np.concatenate(banks),
        )

    def names(self) -> list[str]:
        """The view names in store order (a node uses them to accept each view once); "" for a
        quarantined or unreadable segment, so that its view is stored anew if it comes again."""
        names = []
        for segment in self.segments():
            try:
                names.append("" if (segment / "QUARANTINED.txt").exists() else (segment / "name.txt").read_text())
            except OSError:
                names.append("")
        return names

    def touch_views(self, first: int) -> int:
        """Mark the Gaussians of views ``first``.. as touched (a refiner in another process
        than the writer learns of new views from the disk); returns the number of views."""
        segments = self.segments()
        for index in range(first, len(segments)):
            if self.usable(index, segments):
                self.touched[np.asarray(self.load(index, segments)[0].gaussians)] = True
        return len(segments)

    def observation_counts(self, segments: list[Path] | None = None) -> np.ndarray:
        """[N] int64: in how many views each Gaussian has a kept observation (read-only: the
        store's running count, which each call brings up to date from the segments it has not
        counted yet; a segment found usable stays so, and segments are only ever added)."""
        segments = self.segments() if segments is None else segments
        self._count_into(self.counts, segments, self.counted, len(segments))
        self.counted = max(self.counted, len(segments))
        view = self.counts.view()
        view.flags.writeable = False
        return view

    def refine(
        self,
        F: np.ndarray | None,
        config: AggregationConfig,
        only_touched: bool = True,
        max_observations: int = 4_000_000,
        unit_float16: bool = False,
        max_gaussians: int = 262_144,
        state: tuple[np.ndarray, np.ndarray] | None = None,
        views: tuple[int, int] | None = None,
        gaussians: tuple[int, int] | np.ndarray | None = None,
        evidence: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        upto: int | None = None,
    ):
        """(features [N, D], observed [N] bool). Recomputes the Gaussians touched since the last
        call (all of them when ``only_touched`` is False or F is None); the others keep their
        rows of F, which is updated in place and returned. ``observed`` marks the Gaussians
        with at least one kept observation among the recomputed ones. A pass costs the
        observations of the recomputed Gaussians (a Gaussian is recomputed from all of its
        views) plus a scan of each view's id list. Gaussians are processed in index ranges
        holding at most ``max_observations`` observations (~45 bytes each in mixture form) and
        at most ``max_gaussians`` Gaussians (a range's [n, D] results are float32), so memory
        does not grow with the flight; a Gaussian's result does not depend on the ranges.
        With ``unit_float16`` the features are kept as the snapshot stores them, unit rows in
        float16 (2 bytes per value instead of 4: a live refiner of a large map holds N x D).

        ``state`` = (weight [N], norm [N] float64) is a live map's running state (see
        ``refine_mixed``), written for every Gaussian computed. With ``views`` = (first, stop)
        the pass folds only segments first..stop-1 into F and ``state`` instead (``touched`` is
        left alone): it costs those views' observations, not the flight's; Gaussians first seen
        in them are computed exactly, the others are approximated (the consistency update weighs
        the new views against the current F, without re-weighing the earlier ones). With
        ``gaussians`` = (lo, hi), or an [N] bool mask, the pass recomputes exactly the Gaussians
        lo <= g < hi (or where the mask is True) that any view observed (a live map's refresh),
        and leaves ``touched`` alone too. With ``upto`` only segments 0..upto-1 are read: a live
        map's views, so that a segment written while the pass runs is not taken in twice (now,
        and by the next fold of the views after ``upto``).
        ``evidence`` = (strength sum [N], effective views [N], spread [N]) float64 gets, for
        every Gaussian computed, its sum of d_iv, its effective number of views and the spread
        of its views about its feature (``refine_mixed``)."""
        segments = self.segments()[:upto]
        if views is not None:
            if F is None or state is None or evidence is not None:
                raise ValueError("folding views in needs the current features and their state (and gives no evidence)")
            counts = self._counts_in(segments, *views)
            selected = counts > 0
        else:
            counts = self.observation_counts(segments)
            if isinstance(gaussians, np.ndarray):
                if gaussians.shape != (self.n_gaussians,) or gaussians.dtype != np.bool_:
                    raise ValueError(f"gaussians must be (lo, hi) or an [N={self.n_gaussians}] bool mask")
                selected = gaussians & (counts > 0)
            elif gaussians is not None:
                selected = np.zeros(self.n_gaussians, bool)
                selected[slice(*gaussians)] = counts[slice(*gaussians)] > 0
            elif only_touched and F is not None:
                selected = self.touched.copy()
            else:
                # every Gaussian, but one that no view observed is 0 without being computed: at the
                # first pass of a large flight that is most of the map, and most of the pass's time
                selected = counts > 0
                if F is not None:
                    F[~selected] = 0
            if state is not None:  # an exact pass: no prior (``refine_mixed`` zeroes the recomputed weights)
                for array in state:
                    array[counts == 0] = 0.0
        observed = np.zeros(self.n_gaussians, bool)
        out = F
        cumulative = np.cumsum(counts * selected)
        first, end = gaussians if isinstance(gaussians, tuple) else (0, self.n_gaussians)
        while first < end:
            done_before = cumulative[first - 1] if first else 0
            stop = max(int(np.searchsorted(cumulative, done_before + max_observations, side="right")), first + 1)
            stop = min(stop, first + max_gaussians)
            lo, first = first, stop
            here = selected[lo:stop]
            if not here.any():
                continue
            observations = self.gather(selected, segments, span=(lo, stop), views=views)
            if not len(observations):
                continue
            if out is None:
                dtype = np.float16 if unit_float16 else np.float32
                out = np.zeros((self.n_gaussians, observations.bank.shape[1]), dtype)
            # this range's selected Gaussians only, numbered from 0: the kernels' per-Gaussian
            # arrays and the copies in and out are the size of the selection, not of the range
            whole = bool(here.all())  # a full pass, or a range wholly selected: slices, no index
            picked = lo + np.flatnonzero(here)
            rows: slice | np.ndarray = slice(lo, stop) if whole else picked
            owner = observations.owner - lo if whole else (np.cumsum(here) - 1)[observations.owner - lo]
            range_state = None
            if state is not None:  # a fold's prior is the selected rows; an exact pass has none
                prior = np.asarray(out[rows] if views is not None else out[:0], np.float32)
                range_state = (prior, state[0][rows], state[1][rows])  # slices: written in place
            range_evidence = None if evidence is None else (evidence[0][rows], evidence[1][rows], evidence[2][rows])
            refined, count = refine_mixed(
                replace(observations, owner=owner), len(picked), config, range_state, range_evidence
            )
            if state is not None and range_state is not None and not whole:  # index copies: written back
                state[0][rows], state[1][rows] = range_state[1], range_state[2]
            if evidence is not None and range_evidence is not None and not whole:
                for array, part in zip(evidence, range_evidence, strict=True):
                    array[rows] = part
            if unit_float16:
                normalise_rows(refined)  # in place: ``unit_rows`` without its temporaries
            out[rows] = refined  # recomputed; unobserved ones get 0
            observed[rows] = count > 0
        if views is None and gaussians is None:
            self.touched[:] = False
        return out, observed

    def counts_in(self, first: int, stop: int) -> np.ndarray:
        """[N] int64: in how many of the usable segments first..stop-1 each Gaussian has a kept
        observation (a live map's count of the views it has taken in)."""
        return self._counts_in(self.segments(), first, stop)

    def _counts_in(self, segments: list[Path], first: int, stop: int) -> np.ndarray:
        """[N] int64: in how many of the usable segments first..stop-1 each Gaussian has a kept observation."""
        return self._count_into(np.zeros(self.n_gaussians, np.int64), segments, first, stop)

    def _count_into(self, counts: np.ndarray, segments: list[Path], first: int, stop: int) -> np.ndarray:
        """counts [N] += 1 for each Gaussian with a kept observation in each usable segment first..stop-1."""
        for index in range(first, stop):
            if self.usable(index, segments):
                counts[np.asarray(self.load(index, segments)[0].gaussians)] += 1  # once per view
        return counts
