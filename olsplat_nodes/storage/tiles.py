"""Tiles: the prior map partitioned by ground area, each tile owning its part of the store.

A map larger than one computer holds is split into square ground cells of ``tile_m`` metres on
the world x-y plane (z is up, as in the simulator's and a geo-referenced survey's frame); a
Gaussian belongs to the cell of its mean, on a grid anchored at x = y = 0 so that every flight
over the same prior map gets the same tiles. ``tile_m`` = 0 is one tile holding the whole map:
the single-machine case of the same code.

Tile t holds an ``ObservationStore`` over its own Gaussians, numbered 0..n_t-1 in the order of
their map indices (``members`` [n_t] int64 ascending map ids). A view's observations are split
by tile (``split_view``): each tile records the view once, with its Gaussians' rows and the part
of the view's region bank they use. A Gaussian's refined feature depends on its own
observations only, and each tile keeps them in view order, so the union of the tiles' maps is
the single-store map of the same views, row for row.

Folders: ``<folder>/tiles.json`` (the grid and the tiles) and one store per tile at
``<folder>/<tile name>/`` (``x<ix>_y<iy>``), with the tile's own map ``language_map.npz`` (tile
rows) once refined; with one tile the store is ``<folder>`` itself, as a single-machine run has
always laid it out, and its map is the run's map.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..aggregate.config import AggregationConfig
from ..aggregate.observe import ViewObservations
from ..durable import write_atomic
from ..errors import OlsplatInputError
from .snapshot import LanguageMap
from .store import ObservationStore

WHOLE_MAP = "whole"  # the name of the one tile when tile_m = 0
TILE_MAP = "language_map.npz"  # a tile's own map, in its shard folder (tile rows)


@dataclass(frozen=True)
class TileGrid:
    """Square ground cells of ``tile_m`` metres (0: one cell, the whole map); cell (ix, iy)
    covers ix * tile_m <= x < (ix + 1) * tile_m, likewise y."""

    tile_m: float

    def __post_init__(self) -> None:
        if not (self.tile_m >= 0 and math.isfinite(self.tile_m)):
            raise OlsplatInputError(f"the tile size must be >= 0 metres (0: one tile), got {self.tile_m}")

    def names_of(self, means: np.ndarray) -> tuple[list[str], np.ndarray]:
        """(tile names, sorted; [N] int32 index into them of each Gaussian of ``means`` [N, 3]).
        A non-finite mean (never drawn) goes to the cell of the origin."""
        if self.tile_m == 0:
            return [WHOLE_MAP], np.zeros(len(means), np.int32)
        xy = np.nan_to_num(np.asarray(means, np.float64)[:, :2], nan=0.0, posinf=0.0, neginf=0.0)
        cells = np.floor(xy / self.tile_m).astype(np.int64)
        keys, index = np.unique(cells, axis=0, return_inverse=True)
        return [f"x{ix}_y{iy}" for ix, iy in keys], index.reshape(-1).astype(np.int32)


@dataclass(frozen=True)
class Tiling:
    """Which tile each Gaussian of an N-Gaussian map is in, and its row there."""

    grid: TileGrid
    names: list[str]  # [T] tile names
    tile: np.ndarray  # [N] int32 tile of each Gaussian
    local: np.ndarray  # [N] int32 row of each Gaussian in its tile
    members: list[np.ndarray]  # per tile [n_t] int64 ascending map ids

    @staticmethod
    def of(means: np.ndarray, grid: TileGrid) -> Tiling:
        """The tiling of a map's Gaussian centres [N, 3] (world metres)."""
        names, tile = grid.names_of(means)
        order = np.argsort(tile, kind="stable")  # map ids grouped by tile, ascending within each
        starts = np.searchsorted(tile[order], np.arange(len(names) + 1))
        members = [order[starts[t] : starts[t + 1]].astype(np.int64) for t in range(len(names))]
        local = np.empty(len(tile), np.int32)
        for ids in members:
            local[ids] = np.arange(len(ids), dtype=np.int32)
        return Tiling(grid, names, tile, local, members)

    def __len__(self) -> int:
        return len(self.names)


def split_view(
    tiling: Tiling, observations: ViewObservations, bank: np.ndarray
) -> dict[int, tuple[ViewObservations, np.ndarray]]:
    """One view's observations (map ids) and stacked bank [R, D], split by tile: tile index ->
    (its observations in the tile's own Gaussian rows, the bank rows they use [R_t, D], slots
    renumbered into them). Tiles the view did not observe are absent."""
    ids = np.asarray(observations.gaussians, np.int64)
    if not len(ids):
        return {}
    offsets = np.asarray(observations.offsets, np.int64)
    slots, weights = np.asarray(observations.slots), np.asarray(observations.weights)
    of_tile = tiling.tile[ids]
    parts = {}
    for t in np.unique(of_tile):
        rows = np.flatnonzero(of_tile == t)  # ascending, so the tile's ids stay ascending
        counts = offsets[rows + 1] - offsets[rows]
        part_offsets = np.concatenate([[0], np.cumsum(counts)])
        # entries of the chosen rows, in order: each row's run offsets[r]..offsets[r + 1]
        entries = np.repeat(offsets[rows] - part_offsets[:-1], counts) + np.arange(part_offsets[-1])
        used, part_slots = np.unique(slots[entries], return_inverse=True)
        parts[int(t)] = (
            ViewObservations(
                tiling.local[ids[rows]].astype(np.int32),
                np.asarray(observations.strength)[rows],
                part_offsets,
                part_slots.reshape(-1).astype(np.int32),
                weights[entries],
            ),
            np.asarray(bank)[used],
        )
    return parts


def check_manifest(folder: Path, tiling: Tiling, write: bool) -> None:
    """``folder/tiles.json`` must say this tiling (tile size and each tile's Gaussian count);
    with ``write`` a folder without one gets it. OlsplatInputError naming the file otherwise:
    views of one map tiled two ways would be split inconsistently."""
    manifest = {
        "tile_m": tiling.grid.tile_m,
        "tiles": {n: len(m) for n, m in zip(tiling.names, tiling.members, strict=True)},
    }
    path = folder / "tiles.json"
    if path.exists():
        found = json.loads(path.read_text())
        if found != manifest:
            raise OlsplatInputError(
                f"{path}: the store was tiled with {found['tile_m']} m tiles over another map "
                f"({len(found['tiles'])} tiles); this run has {tiling.grid.tile_m} m tiles ({len(tiling)} tiles)"
            )
    elif write:
        folder.mkdir(parents=True, exist_ok=True)
        write_atomic(path, json.dumps(manifest, indent=1).encode())


def shard_folder(folder: Path, tiling: Tiling, tile: int) -> Path:
    """Tile ``tile``'s store folder (the folder itself for the one tile of tile_m = 0)."""
    return folder if tiling.grid.tile_m == 0 else folder / tiling.names[tile]


class TileShard:
    """One tile's store and what the tile does with it: record a view's part once (by view
    name: a restarted run, or a retried task, sends a view again), refine the tile's map. The
    same class serves the single machine (``TiledStore``) and a cluster's tile actor."""

    def __init__(self, folder: str | Path, n_gaussians: int, writer: bool = True):
        self.store = ObservationStore(folder, n_gaussians, writer)
        self.names = set(self.store.names())  # from the disk: a restarted shard knows what it holds

    def __len__(self) -> int:
        return len(self.names)

    def record(self, name: str, part: ViewObservations, bank: np.ndarray) -> bool:
        """Append a view's part (tile rows, from ``split_view``) unless a view of this name is
        here already; whether it was added."""
        if name in self.names:
            return False
        self.store.append(name, part, bank)
        self.names.add(name)
        return True

    def refine(self, config: AggregationConfig, encoder: str | None = None) -> tuple[np.ndarray | None, np.ndarray]:
        """The tile's map over its rows, from every view it holds: (features [n_t, D] float16
        unit rows, or None when it holds no observation; observed [n_t] bool). With ``encoder``
        (the features' encoder name) it is also written as the tile's own language map,
        ``<shard>/language_map.npz``, which a tiled query reads one tile at a time."""
        features, observed = self.store.refine(None, config, only_touched=False, unit_float16=True)
        if encoder is not None and features is not None:
            LanguageMap(features, observed, encoder).save(self.store.folder / TILE_MAP)
        return features, observed


class TiledStore:
    """The tiles' shards of a map under one folder: what the single store is for a map that
    one computer holds. ``append`` records a view in each tile it observed, once; ``refine``
    gives the union of the tiles' maps."""

    def __init__(self, folder: str | Path, tiling: Tiling, writer: bool = False):
        self.folder = Path(folder)
        self.tiling = tiling
        check_manifest(self.folder, tiling, write=writer)
        self.shards = [
            TileShard(shard_folder(self.folder, tiling, t), len(m), writer) for t, m in enumerate(tiling.members)
        ]

    def shard_folder(self, tile: int) -> Path:
        return shard_folder(self.folder, self.tiling, tile)

    def __len__(self) -> int:
        """The number of distinct views recorded in any tile."""
        return len(set().union(*(shard.names for shard in self.shards)))

    def append(self, name: str, observations: ViewObservations, bank: np.ndarray) -> list[int]:
        """Record one view (map-id observations, stacked bank) in the tiles it observed; returns
        the tiles it was added to now (not those that already held a view of this name)."""
        parts = split_view(self.tiling, observations, bank)
        return [tile for tile, (part, part_bank) in parts.items() if self.shards[tile].record(name, part, part_bank)]

    def refine(self, config: AggregationConfig, encoder: str | None = None) -> tuple[np.ndarray | None, np.ndarray]:
        """(features [N, D] float16 unit rows, 0 for the unobserved, or None when no tile
        observed anything; observed [N] bool): every tile refined in full, the union in map rows.
        With ``encoder`` and more than one tile, each tile's map is written too (``TileShard.refine``)."""
        encoder = encoder if len(self.tiling) > 1 else None  # one tile: its map is the union
        return union_of(self.tiling, [shard.refine(config, encoder) for shard in self.shards])


def union_of(tiling: Tiling, parts: list[tuple[np.ndarray | None, np.ndarray]]) -> tuple[np.ndarray | None, np.ndarray]:
    """The map of the tiles' maps (per tile: features [n_t, D] or None, observed [n_t]), in map rows."""
    n = len(tiling.tile)
    features: np.ndarray | None = None
    observed = np.zeros(n, bool)
    for members, (part, seen) in zip(tiling.members, parts, strict=True):
        if part is None:
            continue
        if features is None:
            features = np.zeros((n, part.shape[1]), np.float16)
        features[members], observed[members] = part, seen
    return features, observed
