"""Changes between flights: the town of a later flight, after stated changes, and their truth.

A ``ChangeSpec`` (change_spec.py) says how many of each kind (``ChangeSpec.parse("default" |
"none" | "cars_added=3,trees_felled=2")``); ``apply_changes`` applies it to the TRUE scene with its own
random stream (``changes_rng``) and returns the changed truth with one ``ChangeRecord`` per
changed object. The prior map is made from the unchanged truth (make.py): a change shows up as
new appearance on old geometry. What each kind does (world frame: ENU metres, ground z = 0):

- car_moved / car_removed / car_added: a town car (or a new one from the town's palette) on a
  free road lane or parking spot; object_added: a tent, a container or a debris pile (boxes of
  Gaussians, label -1 and category ``OBJECT_CATEGORY``: no annotation label names them);
- roof_damaged: a blob on one roof darkened or covered in brown debris (the label stays);
  roof_recoloured: a roof painted another ``ROOF_COLORS`` colour (its building's label changes);
- tree_felled: a tree gone, a 1 m patch of bare ground where its trunk stood;
- flooded / burnt: a blob of ground (and whatever stands in it below 0.5 m) muddy water
  (label -1) or charcoal (ground labelled bare ground).

Cars, objects and felled trees also change the sun shadows baked into the ground (layout.py).
change_truth.py turns the records into the per-Gaussian and per-view truth.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from olsplat_nodes.scene import Gaussians
from olsplat_nodes.scene.gaussians import SH_C0

from .change_spec import (
    GROUND_CATEGORIES,
    OBJECT_CATEGORY,
    ChangedTruth,
    ChangeRecord,
    ChangeSpec,
    inside_polygon,
    polygon_area,
)
from .labels import CATEGORY, LABEL, LABELS, ROOF_COLORS, building_label
from .layout import Car, Tree, _Builder, _shadows
from .scene import GROUND_COLORS, TruthScene, _car, _Part, _part, _shade, _shapes, footprint_mask

Z_MARGIN = 0.5  # metres above and below an object's extent in its z range (the map's Gaussians sit off the surface)
OBJECTS = {  # kind -> ((length range), (width range), (height range), colours); metres, linear rgb
    "tent": ((3.0, 6.0), (2.5, 4.5), (1.8, 2.8),
             [(0.9, 0.9, 0.88), (0.85, 0.45, 0.12), (0.25, 0.4, 0.22), (0.2, 0.35, 0.7)]),
    "container": ((6.06, 12.19), (2.44, 2.44), (2.59, 2.59),  # ISO 20 ft and 40 ft
                  [(0.55, 0.22, 0.12), (0.15, 0.3, 0.55), (0.2, 0.4, 0.25), (0.5, 0.5, 0.5)]),
    "debris": ((2.0, 6.0), (2.0, 5.0), (0.4, 1.2), [(0.45, 0.4, 0.34), (0.38, 0.35, 0.32)]),
}  # fmt: skip
DEBRIS_RGB = np.array([0.36, 0.28, 0.20])  # a damaged roof's brown debris
WATER_RGB = np.array([0.33, 0.30, 0.21])  # muddy flood water
CHARCOAL_RGB = np.array([0.10, 0.09, 0.085])


def _rect(cx: float, cy: float, hx: float, hy: float) -> tuple[tuple[float, float], ...]:
    return _poly([(cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)])


def _poly(points) -> tuple[tuple[float, float], ...]:
    """Rounded to the millimetre (the written numbers are the truth), counter-clockwise."""
    pts = np.round(np.asarray(points, float), 3)
    pts = pts if polygon_area(pts) >= 0 else pts[::-1]
    return tuple((float(x), float(y)) for x, y in pts)


def _blob(cx: float, cy: float, area: float, rng, n: int = 16) -> tuple[tuple[float, float], ...]:
    """A star-shaped blob of ``area`` m^2 around (cx, cy): a circle wobbled by low harmonics."""
    theta = np.linspace(0, 2 * np.pi, n, endpoint=False)
    radius = 1.0 + sum(0.12 * np.cos(j * theta + rng.uniform(0, 2 * np.pi)) for j in (1, 2, 3))
    pts = np.c_[np.cos(theta) * radius, np.sin(theta) * radius]
    pts *= np.sqrt(area / polygon_area(pts))
    return _poly(pts + np.array([cx, cy]))


def _roof_outline(boxes) -> tuple[tuple[float, float], ...]:
    """The outline of a building's roof (its boxes grown by the 0.3 m overhang; an L's union)."""
    res = 0.05
    grown = np.array([(x0 - 0.3, y0 - 0.3, x1 + 0.3, y1 + 0.3) for x0, y0, x1, y1 in boxes])
    lo = grown[:, :2].min(0) - 2 * res
    cells = np.ceil((grown[:, 2:].max(0) - lo) / res).astype(int) + 2
    mask = np.zeros((cells[1], cells[0]), np.uint8)
    for x0, y0, x1, y1 in grown:
        (c0, r0), (c1, r1) = np.round((np.array([[x0, y0], [x1, y1]]) - lo) / res).astype(int)
        mask[r0:r1, c0:c1] = 1
    contour = max(cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)[0], key=cv2.contourArea)
    # a contour runs through pixel centres; the mask's edge lies half a cell outside them
    pts = contour[:, 0, :].astype(float)
    centre = pts.mean(0)
    pts += 0.5 + 0.5 * np.sign(pts - centre + 1e-9)
    return _poly(pts * res + lo)


class _Editor:
    """Mutable state while changing the truth: colours, labels, removals, new parts, free space."""

    def __init__(self, truth: TruthScene, rng: np.random.Generator):
        self.truth, self.rng, self.layout = truth, rng, truth.layout
        g = truth.gaussians
        self.n = len(g)
        self.spacing = float(np.median(np.exp(g.log_scales[:, 0]))) / 0.85  # as reconstruct.py reads it
        self.density = 1.0 / self.spacing**2
        self.xy = g.means[:, :2].astype(np.float64)
        self.z = g.means[:, 2].astype(np.float64)
        self.colors = g.sh[:, 0].astype(np.float64) * SH_C0 + 0.5  # [N, 3] DC colours
        self.label = truth.label.copy()
        self.removed = np.full(self.n, -1, np.int32)
        self.modified = np.full(self.n, -1, np.int32)
        self.recoloured = np.zeros(self.n, bool)  # DC colour rewritten (others keep their bytes)
        self.matte = np.zeros(self.n, bool)  # new material: no view-dependent lobes (world v2's SH)
        self.ground = np.isin(truth.category, GROUND_CATEGORIES)
        self.parts: list[tuple[_Part, int]] = []  # new Gaussians and their record id
        self.records: list[ChangeRecord] = []
        self.cars, self.trees = list(self.layout.cars), list(self.layout.trees)
        self.buildings = list(self.layout.buildings)
        self.casters: list[tuple[int, Car]] = []  # (record id, a box casting a shadow) of new things
        self.removed_casters: list[tuple[int, Car | Tree]] = []  # (record id, car or tree) gone
        self.next_instance = int(truth.instance.max()) + 1
        self.footprint = footprint_mask(self.layout)
        half = self.layout.size_m / 2
        self.taken = [
            (c.x - c.length / 2, c.y - c.length / 2, c.x + c.length / 2, c.y + c.length / 2) for c in self.cars
        ]
        self.taken += [(t.x - t.radius, t.y - t.radius, t.x + t.radius, t.y + t.radius) for t in self.trees]
        self.taken += [(x0 - 0.8, y0 - 0.8, x1 + 0.8, y1 + 0.8) for b in self.buildings for x0, y0, x1, y1 in b.boxes]
        self.taken += [(-half, -half, -half + 2, half), (half - 2, -half, half, half)]  # the town's edges
        self.taken += [(-half, -half, half, -half + 2), (-half, half - 2, half, half)]

    def add(self, kind: str, **fields_) -> int:
        k = len(self.records)
        self.records.append(ChangeRecord(k, kind, **fields_))
        return k

    def majority_label(self, mask: np.ndarray) -> str | None:
        labels = self.label[mask]
        labels = labels[labels >= 0]
        return LABELS[int(np.bincount(labels).argmax())] if len(labels) else None

    def ground_label(self, polygon) -> str | None:
        """The label most ground Gaussians under ``polygon`` carry now."""
        return self.majority_label(self.ground & (self.removed < 0) & inside_polygon(self.xy, polygon))

    def free(self, box, margin: float = 0.5) -> bool:
        x0, y0, x1, y1 = box
        return not any(x0 < b[2] + margin and b[0] < x1 + margin and y0 < b[3] + margin and b[1] < y1 + margin
                       for b in self.taken)  # fmt: skip

    def on(self, box, categories) -> bool:
        """All ground cells of ``box`` are of ``categories`` (CATEGORY codes) and none under a building."""
        xs, ys = np.meshgrid(np.linspace(box[0], box[2], 6), np.linspace(box[1], box[3], 6))
        row, col = self.layout.cell(np.c_[xs.ravel(), ys.ravel()])
        return bool(np.isin(self.layout.ground[row, col], categories).all() and not self.footprint[row, col].any())

    def spot(self, length: float, width: float, categories, lanes: bool = False) -> tuple[float, float, bool]:
        """A free place (x, y, along_x) for a box on ground of ``categories``; with ``lanes``, half
        the tries on a road's lane (along the road), the others across (as in a parking stall)."""
        half = self.layout.size_m / 2
        for _ in range(400):
            along_x, allowed = bool(self.rng.random() < 0.5), categories
            x, y = self.rng.uniform(-half + 3, half - 3, 2)
            if lanes and self.layout.roads and self.rng.random() < 0.5:
                axis, c, hw = self.layout.roads[self.rng.integers(len(self.layout.roads))]
                lane = c + hw / 2 * self.rng.choice([-1.0, 1.0])
                x, y, along_x = (x, lane, True) if axis == "x" else (lane, y, False)
            elif lanes:
                allowed, along_x = [CATEGORY["parking"]], False
            hx, hy = (length / 2, width / 2) if along_x else (width / 2, length / 2)
            box = (x - hx, y - hy, x + hx, y + hy)
            if self.free(box) and self.on(box, allowed):
                self.taken.append(box)
                return float(x), float(y), along_x
        raise ValueError(f"--changes: no free place left in the town for a {length:.1f} m x {width:.1f} m change")

    def new_part(self, part: _Part, k: int) -> None:
        self.parts.append((part, k))


def _fit(counts: tuple[int, ...], available: int, fit: bool, what: str) -> tuple[int, ...]:
    """``counts`` of things to take from ``available`` (in turn, as far as they go, when ``fit``)."""
    if sum(counts) <= available:
        return counts
    if not fit:
        raise ValueError(f"--changes: {sum(counts)} {what} but the town has {available}")
    taken = np.minimum(counts, available - np.r_[0, np.cumsum(counts)[:-1]].clip(max=available))
    return tuple(int(v) for v in taken)


def _cars(ed: _Editor, spec: ChangeSpec) -> None:
    lanes = [CATEGORY["road"]]
    removed, moved = _fit((spec.cars_removed, spec.cars_moved), len(ed.cars), spec.fit_town, "cars to remove or move")
    chosen = ed.rng.choice(len(ed.cars), removed + moved, replace=False)
    for n, index in enumerate(chosen):
        car = ed.cars[index]
        old = _rect(
            car.x, car.y, *((car.length / 2, car.width / 2) if car.along_x else (car.width / 2, car.length / 2))
        )
        own = ed.truth.instance == car.instance
        z = (-Z_MARGIN, round(car.height + Z_MARGIN, 3))
        if n < removed:
            k = ed.add(
                "car_removed",
                instance=car.instance,
                label_before="car",
                label_after=None,
                footprint=old,
                z_range=z,
                centre=(car.x, car.y, car.height / 2),
            )
            ed.records[k] = dataclasses.replace(ed.records[k], label_after=ed.ground_label(old))
        else:
            x, y, along_x = ed.spot(car.length, car.width, lanes, lanes=True)
            moved = dataclasses.replace(car, x=x, y=y, along_x=along_x)
            new = _rect(x, y, *((car.length / 2, car.width / 2) if along_x else (car.width / 2, car.length / 2)))
            k = ed.add(
                "car_moved",
                instance=car.instance,
                label_before=ed.ground_label(new),
                label_after="car",
                footprint=new,
                z_range=z,
                centre=(x, y, car.height / 2),
                footprint_before=old,
            )
            ed.new_part(_car(moved, ed.density, ed.rng), k)
            ed.casters.append((k, moved))
        ed.removed[own] = k
        ed.removed_casters.append((k, car))
    ed.cars = [c for i, c in enumerate(ed.cars) if i not in set(chosen.tolist())] + [c for _, c in ed.casters]
    for _ in range(spec.cars_added):
        scratch = dataclasses.replace(ed.layout, buildings=[], trees=[], cars=[])
        builder = _Builder(scratch, ed.rng)
        builder.next_instance = ed.next_instance
        x, y, along_x = ed.spot(4.9, 1.95, lanes, lanes=True)
        builder.car(x, y, along_x)
        car = scratch.cars[0]
        ed.next_instance += 1
        foot = _rect(x, y, *((car.length / 2, car.width / 2) if along_x else (car.width / 2, car.length / 2)))
        k = ed.add(
            "car_added",
            instance=car.instance,
            label_before=ed.ground_label(foot),
            label_after="car",
            footprint=foot,
            z_range=(-Z_MARGIN, round(car.height + Z_MARGIN, 3)),
            centre=(x, y, car.height / 2),
        )
        ed.new_part(_car(car, ed.density, ed.rng), k)
        ed.casters.append((k, car))
        ed.cars.append(car)


def _box(
    ed: _Editor, cx: float, cy: float, along_x: bool, length: float, width: float, height: float, rgb, noise: float
):
    """Top and four sides of a box of Gaussians (like layout's cars), colour ``rgb`` +- ``noise``."""
    hx, hy = (length / 2, width / 2) if along_x else (width / 2, length / 2)
    faces = [((0, 0, height), (0, 0, 1), (hx, 0, 0), (0, hy, 0)),
             ((hx, 0, height / 2), (1, 0, 0), (0, hy, 0), (0, 0, height / 2)),
             ((-hx, 0, height / 2), (-1, 0, 0), (0, hy, 0), (0, 0, height / 2)),
             ((0, hy, height / 2), (0, 1, 0), (hx, 0, 0), (0, 0, height / 2)),
             ((0, -hy, height / 2), (0, -1, 0), (hx, 0, 0), (0, 0, height / 2))]  # fmt: skip
    means, normals, colors = [], [], []
    for centre, normal, eu, ev in faces:
        m = max(3, ed.rng.poisson(ed.density * 4 * np.linalg.norm(eu) * np.linalg.norm(ev)))
        u, v = ed.rng.uniform(-1, 1, (2, m))
        means.append(np.asarray(centre) + u[:, None] * np.asarray(eu) + v[:, None] * np.asarray(ev) + [cx, cy, 0.0])
        normals.append(np.tile(np.asarray(normal, float), (m, 1)))
        shade = _shade(np.asarray(normal, float)[None])[0]
        colors.append(np.asarray(rgb) * shade * (1 + noise * ed.rng.uniform(-1, 1, (m, 1))))
    return np.concatenate(means), np.concatenate(normals), np.concatenate(colors)


def _objects(ed: _Editor, spec: ChangeSpec) -> None:
    kinds = list(OBJECTS)
    where = {"tent": ["lawn", "bare ground"], "container": ["parking", "pavement", "bare ground"],
             "debris": ["lawn", "bare ground", "pavement", "parking"]}  # fmt: skip
    for i in range(spec.objects_added):
        name = kinds[i % len(kinds)]
        (l0, l1), (w0, w1), (h0, h1), palette = OBJECTS[name]
        length = float(ed.rng.choice([l0, l1])) if name == "container" else float(ed.rng.uniform(l0, l1))
        width, height = float(ed.rng.uniform(w0, w1)), float(ed.rng.uniform(h0, h1))
        rgb = palette[ed.rng.integers(len(palette))]
        try:
            x, y, along_x = ed.spot(
                length,
                width,
                [CATEGORY[c] for c in where[name]],
            )
        except ValueError:  # a town without such ground: anywhere on the ground
            x, y, along_x = ed.spot(
                length,
                width,
                GROUND_CATEGORIES,
            )
        means, normals, colors = _box(ed, x, y, along_x, length, width, height, rgb, 0.3 if name == "debris" else 0.05)
        instance, ed.next_instance = ed.next_instance, ed.next_instance + 1
        hx, hy = (length / 2, width / 2) if along_x else (width / 2, length / 2)
        foot = _rect(x, y, hx, hy)
        k = ed.add(
            "object_added",
            instance=instance,
            label_before=ed.ground_label(foot),
            label_after=None,
            footprint=foot,
            z_range=(-Z_MARGIN, round(height + Z_MARGIN, 3)),
            centre=(x, y, height / 2),
        )
        ed.new_part(_part(means, normals, colors, OBJECT_CATEGORY, instance, -1), k)
        ed.casters.append((k, Car(x, y, along_x, length, width, height, (rgb[0], rgb[1], rgb[2]), instance)))


def _trees(ed: _Editor, spec: ChangeSpec) -> None:
    (felled,) = _fit((spec.trees_felled,), len(ed.trees), spec.fit_town, "trees to fell")
    chosen = ed.rng.choice(len(ed.trees), felled, replace=False)
    for index in chosen:
        tree = ed.trees[index]
        own = ed.truth.instance == tree.instance
        reach = float(np.hypot(*(ed.xy[own] - [tree.x, tree.y]).T).max()) if own.any() else tree.radius
        theta = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        foot = _poly(np.c_[tree.x + reach * np.cos(theta), tree.y + reach * np.sin(theta)])
        top = float(ed.z[own].max()) if own.any() else tree.centre_z + tree.radius
        k = ed.add(
            "tree_felled",
            instance=tree.instance,
            label_before="tree",
            label_after=None,
            footprint=foot,
            z_range=(-Z_MARGIN, round(top + Z_MARGIN, 3)),
            centre=(tree.x, tree.y, tree.centre_z),
        )
        ed.removed[own] = k
        ed.removed_casters.append((k, tree))
        stump = ed.ground & (np.hypot(*(ed.xy - [tree.x, tree.y]).T) < 1.0) & (ed.modified < 0)
        ed.colors[stump] = np.asarray(GROUND_COLORS["bare ground"]) * ed.rng.uniform(0.8, 1.1, (int(stump.sum()), 1))
        ed.label[stump] = LABEL["bare ground"]
        ed.modified[stump], ed.recoloured[stump], ed.matte[stump] = k, True, True
        ed.records[k] = dataclasses.replace(ed.records[k], label_after=ed.ground_label(foot))
    ed.trees = [t for i, t in enumerate(ed.trees) if i not in set(chosen.tolist())]


def _roofs(ed: _Editor, spec: ChangeSpec) -> None:
    damaged, recoloured = _fit(
        (spec.roofs_damaged, spec.roofs_recoloured), len(ed.buildings), spec.fit_town, "roofs to change"
    )
    roof = ed.truth.category == CATEGORY["roof"]
    for n, index in enumerate(ed.rng.choice(len(ed.buildings), damaged + recoloured, replace=False)):
        b = ed.buildings[index]
        own = roof & (ed.truth.instance == b.instance)
        label = building_label(b.roof_color)
        if n < damaged:
            x0, y0, x1, y1 = b.boxes[0]
            area = (x1 - x0) * (y1 - y0) * ed.rng.uniform(0.15, 0.35)
            r = min(np.sqrt(area / np.pi), 0.4 * min(x1 - x0, y1 - y0))
            cx, cy = ed.rng.uniform(x0 + r, x1 - r), ed.rng.uniform(y0 + r, y1 - r)
            foot = _blob(cx, cy, np.pi * r**2, ed.rng)
            hit = own & inside_polygon(ed.xy, foot)
            brown = ed.rng.random(int(hit.sum())) < 0.5  # half brown debris, half darkened roof
            dark = ed.colors[hit] * ed.rng.uniform(0.35, 0.6, (int(hit.sum()), 1))
            ed.colors[hit] = np.where(brown[:, None], DEBRIS_RGB * ed.rng.uniform(0.75, 1.2, (len(brown), 1)), dark)
            ed.matte[hit] = True
            z = ed.z[hit] if hit.any() else np.array([b.eave])
            k = ed.add("roof_damaged", instance=b.instance, label_before=label, label_after=label, footprint=foot,
                       z_range=(round(float(z.min()) - Z_MARGIN, 3), round(float(z.max()) + Z_MARGIN, 3)),
                       centre=(cx, cy, float(z.mean())))  # fmt: skip
        else:
            colour = str(ed.rng.choice([c for c in ROOF_COLORS if c != b.roof_color]))
            hit = own
            ed.colors[hit] *= np.asarray(ROOF_COLORS[colour]) / np.asarray(ROOF_COLORS[b.roof_color])
            ed.label[ed.truth.instance == b.instance] = LABEL[building_label(colour)]
            foot = _roof_outline(b.boxes)
            centre = np.asarray(foot).mean(0)
            k = ed.add("roof_recoloured", instance=b.instance, label_before=label, label_after=building_label(colour),
                       footprint=foot, z_range=(round(b.eave - Z_MARGIN, 3), round(float(b.top) + Z_MARGIN, 3)),
                       centre=(float(centre[0]), float(centre[1]), (b.eave + b.top) / 2))  # fmt: skip
            ed.buildings[index] = dataclasses.replace(b, roof_color=colour)
        ed.modified[hit], ed.recoloured[hit] = k, True


def _areas(ed: _Editor, spec: ChangeSpec, shadow: np.ndarray) -> None:
    """One flooded and one burnt blob of ground, clear of the other changes and mostly not under buildings."""
    half = ed.layout.size_m / 2
    for kind, area, centres, rgb, after in (
        ("flooded", spec.flooded_m2, ["road", "lawn"], WATER_RGB, None),
        ("burnt", spec.burnt_m2, ["lawn", "bare ground"], CHARCOAL_RGB, "bare ground"),
    ):
        if area <= 0:
            continue
        r = np.sqrt(area / np.pi)
        for _ in range(400):
            cx, cy = ed.rng.uniform(-half + r + 2, half - r - 2, 2) if half > r + 2 else (0.0, 0.0)
            foot = _blob(float(cx), float(cy), area, ed.rng)
            changed = [rec.footprint for rec in ed.records] + [
                rec.footprint_before for rec in ed.records if rec.footprint_before
            ]
            clear = not any(
                inside_polygon(np.asarray(f), foot).any() or inside_polygon(np.asarray(foot), f).any() for f in changed
            )
            if clear and ed.on((cx - 0.5, cy - 0.5, cx + 0.5, cy + 0.5), [CATEGORY[c] for c in centres]):
                break
        else:
            raise ValueError(f"--changes: no place for {area:.0f} m^2 {kind} in a {2 * half:.0f} m town")
        hit = inside_polygon(ed.xy, foot) & (ed.z < Z_MARGIN) & (ed.removed < 0) & (ed.modified < 0)
        k = ed.add(kind, instance=None, label_before=ed.majority_label(hit & ed.ground), label_after=after,
                   footprint=foot, z_range=(-Z_MARGIN, Z_MARGIN), centre=(float(cx), float(cy), 0.0))  # fmt: skip
        row, col = ed.layout.cell(ed.xy[hit])
        light = (1.0 - 0.58 * shadow[row, col])[:, None]  # the old shadow: the shadow pass updates it
        ed.colors[hit] = rgb * ed.rng.uniform(0.85, 1.15, (int(hit.sum()), 1)) * light
        hit_ground = hit & ed.ground
        ed.label[hit_ground] = -1 if after is None else LABEL[after]
        ed.modified[hit], ed.recoloured[hit], ed.matte[hit] = k, True, True


def _reshade(ed: _Editor) -> tuple[np.ndarray, np.ndarray]:
    """(new shadow raster, owner raster): the ground's baked sun shadows redone without the removed
    cars and trees and with the new ones; a cell belongs to the first record whose casters shadow it."""
    layout = ed.layout
    new = _shadows(
        dataclasses.replace(
            layout,
            buildings=ed.buildings,
            trees=ed.trees,
            cars=ed.cars + [c for k, c in ed.casters if ed.records[k].kind == "object_added"],
        )
    )
    changed = np.abs((1 - 0.58 * new) / (1 - 0.58 * layout.shadow) - 1) > 0.03
    owner = np.full(new.shape, -1, np.int32)
    for rec in ed.records:
        mine = [c for k, c in ed.casters + ed.removed_casters if k == rec.id]
        if not mine:
            continue
        cars = [c for c in mine if isinstance(c, Car)]
        trees = [c for c in mine if isinstance(c, Tree)]
        own = _shadows(dataclasses.replace(layout, buildings=[], trees=trees, cars=cars)) > 0.05
        owner[own & changed & (owner < 0)] = rec.id
    shaded = np.flatnonzero(ed.ground & (ed.removed < 0) & (ed.z < Z_MARGIN))
    row, col = layout.cell(ed.xy[shaded])
    ratio = (1 - 0.58 * new[row, col]) / (1 - 0.58 * layout.shadow[row, col])
    moved = ratio != 1.0  # every change of light is drawn; only those over 3 % are counted as a change
    ed.colors[shaded[moved]] *= ratio[moved, None]
    ed.recoloured[shaded[moved]] = True
    counted = changed[row, col] & (owner[row, col] >= 0)
    first = counted & (ed.modified[shaded] < 0)
    ed.modified[shaded[first]] = owner[row, col][first]
    return new, owner


def apply_changes(truth: TruthScene, spec: ChangeSpec, rng: np.random.Generator) -> ChangedTruth:
    """The truth of a later flight after ``spec``'s changes, drawn from ``rng`` (``changes_rng``).
    Kept Gaussians keep their order and bytes unless recoloured; new ones (cars, objects) follow.
    Raises ValueError (one line) when the town has too few cars, trees or buildings for ``spec``."""
    ed = _Editor(truth, rng)
    _cars(ed, spec)
    _objects(ed, spec)
    _trees(ed, spec)
    _roofs(ed, spec)
    _areas(ed, spec, truth.layout.shadow)
    shadow, owner = _reshade(ed)

    g = truth.gaussians
    keep = ed.removed < 0
    sh = g.sh.copy()
    sh[ed.recoloured, 0] = (np.clip(ed.colors[ed.recoloured], 0, 1) - 0.5) / SH_C0
    sh[ed.matte, 1:] = 0.0
    kept = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, sh).subset(keep)
    parts = [p for p, _ in ed.parts]
    glass = truth.glass if truth.glass is not None else np.zeros(ed.n, bool)
    after_ids = ed.modified[keep]
    category, instance, label, glasses = truth.category[keep], truth.instance[keep], ed.label[keep], glass[keep]
    if parts:
        means, quats, scales, opacities = _shapes(parts, ed.spacing, rng)
        colors = np.concatenate([p.colors for p in parts])
        new = Gaussians.from_colors(means, colors, scales, opacities, quats)
        new_sh = np.zeros((len(new), sh.shape[1], 3), np.float32)
        new_sh[:, :1] = new.sh
        kept = Gaussians(
            means=np.concatenate([kept.means, new.means]),
            quats=np.concatenate([kept.quats, new.quats]),
            log_scales=np.concatenate([kept.log_scales, new.log_scales]),
            opacity_logits=np.concatenate([kept.opacity_logits, new.opacity_logits]),
            sh=np.concatenate([kept.sh, new_sh]),
        )
        after_ids = np.concatenate([after_ids, *[np.full(len(p.means), k, np.int32) for p, k in ed.parts]])
        category = np.concatenate([category, *[p.category for p in parts]])
        instance = np.concatenate([instance, *[p.instance for p in parts]])
        label = np.concatenate([label, *[p.label for p in parts]])
        glasses = np.concatenate(
            [glasses, *[p.glass if p.glass is not None else np.zeros(len(p.means), bool) for p in parts]]
        )
    layout = dataclasses.replace(truth.layout, buildings=ed.buildings, trees=ed.trees, cars=ed.cars, shadow=shadow)
    after = TruthScene(
        kept, category.astype(np.int16), instance.astype(np.int32), label.astype(np.int16), layout, glasses
    )
    before_ids = np.where(ed.removed >= 0, ed.removed, ed.modified).astype(np.int32)
    return ChangedTruth(after, ed.records, before_ids, after_ids.astype(np.int32), owner)
