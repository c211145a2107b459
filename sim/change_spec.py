"""What changes between flights, as numbers: the spec (how many of each kind), the records (what
changed, where), and the geometry both use (polygon area, point in polygon). ``changes.py`` makes
the changes in the true scene; ``change_truth.py`` turns the records into per-Gaussian and
per-view truth. Polygons are (x, y) ENU metres, counter-clockwise; ground z = 0.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from .labels import CATEGORY
from .scene import TruthScene

# The flight seed M's streams are children of SeedSequence(M, spawn_key=(4,)): flight, sensor and
# pose (make._streams), the world's weather (world.FLIGHT_SEED_WORLD_KEY = (4, 3)); the changes
# draw from the next one, so that every existing stream and byte stays as it was.
CHANGES_KEY = (4, 4)
OBJECT_CATEGORY = -1  # tents, containers, debris: no category of labels.CATEGORIES names them
GROUND_CATEGORIES = [CATEGORY[c] for c in ("bare ground", "road", "lawn", "parking", "pavement")]
KINDS = ("car_moved", "car_added", "car_removed", "object_added", "roof_damaged", "roof_recoloured",
         "tree_felled", "flooded", "burnt")  # fmt: skip
# `--changes default` per 10,000 m^2 of town (the tiny preset's area), each count at least 1
DEFAULT_PER_HECTARE = {"cars_moved": 2, "cars_added": 2, "cars_removed": 2, "objects_added": 3, "roofs_damaged": 1,
                       "roofs_recoloured": 1, "trees_felled": 2, "flooded_m2": 150.0, "burnt_m2": 100.0}  # fmt: skip


@dataclass(frozen=True)
class ChangeSpec:
    """How many changes of each kind a later flight sees (counts; areas in m^2)."""

    cars_moved: int = 0
    cars_added: int = 0
    cars_removed: int = 0
    objects_added: int = 0  # tents, containers, debris (in turn)
    roofs_damaged: int = 0
    roofs_recoloured: int = 0
    trees_felled: int = 0
    flooded_m2: float = 0.0  # one flooded area of about this size (0: none)
    burnt_m2: float = 0.0  # one burnt area of about this size (0: none)
    # fewer cars moved or removed, trees felled and roofs changed where the town has fewer (default's
    # mix); False: such a spec is refused
    fit_town: bool = False

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def default(size_m: float) -> ChangeSpec:
        """``DEFAULT_PER_HECTARE`` scaled by the town's area (``size_m`` side, metres), counts >= 1."""
        scale = size_m**2 / 10_000.0
        values: dict[str, Any] = {
            k: float(round(v * scale)) if isinstance(v, float) else max(1, round(v * scale))
            for k, v in DEFAULT_PER_HECTARE.items()
        }
        return ChangeSpec(**values, fit_town=True)

    @staticmethod
    def parse(text: str, size_m: float) -> ChangeSpec:
        """``default``, ``none`` or ``kind=N,...`` (optionally after ``default,`` or ``none,``): a spec
        for a town of side ``size_m`` metres. Raises ValueError with one line naming the problem."""
        items = [item.strip() for item in text.split(",")]
        if not text.strip() or "" in items:
            raise ValueError(f"--changes: expected default, none or kind=N,... (comma-separated), got {text!r}")
        spec = ChangeSpec()
        if items[0] in ("default", "none"):
            spec = ChangeSpec.default(size_m) if items.pop(0) == "default" else spec
        types = {f.name: f.type for f in fields(ChangeSpec) if f.name != "fit_town"}
        values: dict[str, Any] = {}
        for item in items:
            key, sep, value = item.partition("=")
            key = key.strip()
            if not sep or key not in types:
                raise ValueError(f"--changes: unknown item {item!r} (kinds: default, none, {', '.join(types)})")
            try:
                number = float(value) if types[key] == "float" else int(value)
            except ValueError:
                wanted = "a number" if types[key] == "float" else "an integer"
                raise ValueError(f"--changes: {key} needs {wanted}, got {value.strip()!r}") from None
            if not (np.isfinite(number) and number >= 0):
                raise ValueError(f"--changes: {key} must be >= 0, got {value.strip()}")
            values[key] = number
        return dataclasses.replace(spec, **values)


@dataclass(frozen=True)
class ChangeRecord:
    """One changed object. Polygons are (x, y) ENU metres, counter-clockwise."""

    id: int  # index of the record; masks store id + 1
    kind: str  # one of KINDS
    instance: int | None  # the car, tree, building or object instance (ground_truth_labels.npz); None: ground
    label_before: str | None  # LABELS name the place showed from above before, None: none
    label_after: str | None
    footprint: tuple[tuple[float, float], ...]  # where it is (for removed or felled: where it was)
    z_range: tuple[float, float]  # metres, its extent +- Z_MARGIN
    centre: tuple[float, float, float]
    footprint_before: tuple[tuple[float, float], ...] | None = None  # car_moved: where it was

    @property
    def area_m2(self) -> float:
        return polygon_area(np.asarray(self.footprint))

    def to_json(self) -> dict:
        doc = dataclasses.asdict(self)
        doc["centre"] = [round(float(v), 3) for v in self.centre]
        doc["z_range"] = [round(float(v), 3) for v in self.z_range]
        doc["area_m2"] = round(self.area_m2, 3)
        return doc


@dataclass
class ChangedTruth:
    truth: TruthScene  # the scene of the later flight
    records: list[ChangeRecord]
    before_ids: np.ndarray  # [N before] int32: the record that removes or restyles each truth Gaussian, -1 none
    after_ids: np.ndarray  # [N after] int32: the record behind each changed truth Gaussian, -1 none
    shadow_owner: np.ndarray  # [R, R] int32 ground raster (layout.py): the record whose shadow changed a cell, -1 none


def changes_rng(flight_seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(flight_seed, spawn_key=CHANGES_KEY))


def polygon_area(points: np.ndarray) -> float:
    """Signed shoelace area of [P, 2] points (> 0 counter-clockwise)."""
    x, y = points[:, 0], points[:, 1]
    return float(0.5 * (x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def inside_polygon(xy: np.ndarray, polygon) -> np.ndarray:
    """[M] bool: points [M, 2] inside the polygon [P, 2] (crossing number; edges count as either)."""
    poly = np.asarray(polygon, float)
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < at)
    return inside


def change_summary(spec: ChangeSpec, records: list[ChangeRecord]) -> dict:
    """scene.json's ``changes``: the spec and the number of records per kind."""
    return {"spec": dataclasses.asdict(spec), "records": len(records),
            "per_kind": {kind: sum(r.kind == kind for r in records) for kind in KINDS}}  # fmt: skip
