"""Queries on a tiled map (``storage/tiles.py``): scattered to the tiles, their instances gathered.

A city-scale map need not fit one computer: each tile's own map (``<shard>/language_map.npz``,
tile rows) is loaded in turn with the tile's Gaussians only, asked the query like a whole map
(``answer_query``: relevance, then 3D instances by DBSCAN), and the tiles' instances are
gathered, largest first. Memory: the largest tile, not the map. The cluster radius is the whole
map's (``default_cluster_radius`` of every centre) unless given, so every tile clusters alike.

An object that straddles a tile border is found as one instance per tile it touches: DBSCAN runs
within a tile. At 100 m tiles that is a small share of a town's roofs; a halo of ``eps`` around
each tile would join them and is not done yet.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import OlsplatInputError
from ..scene import Gaussians
from ..storage.snapshot import LanguageMap
from ..storage.tiles import TILE_MAP, TileGrid, Tiling, check_manifest, shard_folder
from .answer import answer_query
from .localize import Instance3D, default_cluster_radius


@dataclass
class TiledAnswer:
    text: str
    negatives: list[str]
    chosen: int  # Gaussians that pick the text over the negatives, over every tile
    instances: list[Instance3D]  # every tile's, largest first (world metres)
    tiles: dict[str, tuple[int, int]] = field(default_factory=dict)  # tile -> (chosen, instances)


def is_tiled(folder: Path) -> bool:
    """Whether ``folder`` is an aggregation's output with more than one tile (``--tile-m``)."""
    manifest = folder / "store" / "tiles.json"
    return manifest.is_file() and len(json.loads(manifest.read_text())["tiles"]) > 1


def tile_maps(folder: Path) -> list[Path]:
    """The tile maps of a tiled aggregation's output folder (tiles no view observed have none)."""
    return sorted((folder / "store").glob(f"*/{TILE_MAP}"))


def answer_tiled(
    folder: Path,
    gaussians: Gaussians,
    encoder,
    text: str,
    negatives: list[str] | tuple[str, ...],
    cluster_radius: float | None = None,
    min_points: int = 20,
) -> TiledAnswer:
    """``text`` against every tile of the tiled map at ``folder`` (``olsplat aggregate --tile-m``'s
    --out) over the prior map ``gaussians``; OlsplatInputError when the folder's tiling is not
    that map's, or a tile's map does not match its Gaussians."""
    manifest = folder / "store" / "tiles.json"
    if not manifest.is_file():
        raise OlsplatInputError(f"{folder}: not a tiled map (no store/tiles.json)")
    tiling = Tiling.of(gaussians.means, TileGrid(float(json.loads(manifest.read_text())["tile_m"])))
    check_manifest(folder / "store", tiling, write=False)
    radius = cluster_radius if cluster_radius is not None else default_cluster_radius(gaussians.means, min_points)
    answer = TiledAnswer(text, list(negatives), 0, [])
    for tile, members in enumerate(tiling.members):
        path = shard_folder(folder / "store", tiling, tile) / TILE_MAP
        if not path.is_file():  # no view observed this tile
            continue
        part = answer_query(
            LanguageMap.load(path),
            gaussians.subset(members),
            encoder,
            text,
            negatives,
            cluster_radius=radius,
            min_points=min_points,
        )
        answer.negatives = part.negatives
        answer.chosen += part.chosen_count
        answer.instances.extend(part.instances)
        answer.tiles[tiling.names[tile]] = (part.chosen_count, len(part.instances))
    answer.instances.sort(key=lambda instance: -instance.gaussians)
    return answer
