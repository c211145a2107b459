"""One language map per flight, from a store that holds several flights of one prior map.

A run over several flights names its views ``f<flight>/<frame>`` (``pipeline.offline``), so the
store knows which flight each observation came from. A flight's map is refined from that
flight's views alone, exactly as a run over that flight alone refines them (same views, same
order, same kernels): its features are those of ``olsplat aggregate --scene <that flight>``,
to the bit. It also carries the evidence a change score needs (``LanguageMap.strength_sum``,
``view_count``, ``view_spread``; ``aggregate/change.py``).

Layout, under a run's output folder:

    OUT/language_map.npz                  every flight together (as without per-flight maps)
    OUT/flights/flights.json              {"flights": [{"flight": "f0", "views": 12, "map": "f0/language_map.npz",
                                            "scene": "/abs/A"}, ...]}
    OUT/flights/f0/language_map.npz       flight 0's map with its evidence
    OUT/flights/f1/language_map.npz       ...
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from ..aggregate.config import AggregationConfig
from ..durable import write_atomic
from .snapshot import LanguageMap
from .store import ObservationStore
from .tiles import Tiling, shard_folder

FLIGHTS_DIR = "flights"  # under a run's output folder
FLIGHTS_INDEX = "flights.json"  # in FLIGHTS_DIR
_FLIGHT = re.compile(r"f(\d+)/")


def flight_of(view_name: str) -> str:
    """The flight a stored view belongs to: ``"f1"`` for ``"f1/frame_0003"``; ``"f0"`` for a
    name without a flight prefix (a run over one flight names its views by their frames)."""
    match = _FLIGHT.match(view_name)
    return f"f{int(match.group(1))}" if match else "f0"


def flights_in(folder: str | Path, tiling: Tiling) -> dict[str, int]:
    """{flight: number of views} of a run's store folder (every tile's views, each once), in
    flight order."""
    names: set[str] = set()
    for tile, members in enumerate(tiling.members):
        names |= set(ObservationStore(shard_folder(Path(folder), tiling, tile), len(members)).names()) - {""}
    counts: dict[str, int] = {}
    for name in names:
        counts[flight_of(name)] = counts.get(flight_of(name), 0) + 1
    return dict(sorted(counts.items(), key=lambda item: int(item[0][1:])))


def flight_map(
    folder: str | Path, tiling: Tiling, flight: str, config: AggregationConfig, encoder: str
) -> LanguageMap | None:
    """The language map of one flight's views in the run's store ``folder`` (tiled as
    ``tiling``), with its evidence; None when they observed no Gaussian. Features are unit
    float16 rows, as every offline map."""
    n = len(tiling.tile)
    features: np.ndarray | None = None
    observed = np.zeros(n, bool)
    strength_sum = np.zeros(n, np.float32)
    view_count = np.zeros(n, np.int32)
    effective_views = np.zeros(n, np.float32)
    view_spread = np.full(n, np.nan, np.float32)
    for tile, members in enumerate(tiling.members):
        store = ObservationStore(
            shard_folder(Path(folder), tiling, tile), len(members), keep=lambda name: flight_of(name) == flight
        )
        sums, effective, spread = np.zeros(len(members)), np.zeros(len(members)), np.full(len(members), np.nan)
        part, seen = store.refine(
            None,
            config,
            only_touched=False,
            unit_float16=True,
            evidence=(sums, effective, spread),
        )
        if part is None:
            continue
        if features is None:
            features = np.zeros((n, part.shape[1]), np.float16)
        features[members], observed[members] = part, seen
        strength_sum[members] = sums
        view_count[members] = store.observation_counts()
        effective_views[members] = effective
        view_spread[members] = spread
    if features is None:
        return None
    return LanguageMap(
        features,
        observed,
        encoder,
        strength_sum=strength_sum,
        view_count=view_count,
        effective_views=effective_views,
        view_spread=view_spread,
    )


def write_flight_maps(
    out: str | Path, tiling: Tiling, config: AggregationConfig, encoder: str, scenes: list[str] | None = None
) -> list[dict]:
    """Write every flight's map of the run folder ``out`` (its store at ``out/store``) to
    ``out/flights/<flight>/language_map.npz`` (float16: a codebook's quantisation would swamp
    the small differences a change score looks for) and ``out/flights/flights.json``; ``scenes``
    names flight k's scene folder. Returns the index's records."""
    out = Path(out)
    records = []
    for flight, views in flights_in(out / "store", tiling).items():
        language_map = flight_map(out / "store", tiling, flight, config, encoder)
        if language_map is None:
            continue
        path = out / FLIGHTS_DIR / flight / "language_map.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        language_map.save(path)
        record: dict = {"flight": flight, "views": views, "map": f"{flight}/language_map.npz"}
        index = int(flight[1:])
        if scenes is not None and index < len(scenes):
            record["scene"] = str(Path(scenes[index]).resolve())
        records.append(record)
    write_atomic(out / FLIGHTS_DIR / FLIGHTS_INDEX, json.dumps({"flights": records}, indent=1).encode())
    return records
