"""The plan of a procedural town: roads, blocks, buildings, trees, cars and ground rasters.

World frame: metres, +x east, +y north, +z up; the town is a square of side ``size_m``
centred on the origin, ground at z = 0. Roads run along x and y at irregular spacing; each
block between them becomes houses with gardens, a commercial lot with a parking area, a park
or a parking lot. Street trees stand on the pavements and overhang the roads; cars drive on
the lanes and fill the parking lots.

The ground is described by rasters at ``GROUND_RES`` metres per cell (row = y, column = x):
its category, the road markings and the sun shadows cast by buildings, trees and cars.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .labels import CATEGORY, ROOF_COLORS

GROUND_RES = 0.2  # metres per raster cell
SUN_AZIMUTH, SUN_ELEVATION = np.radians(215.0), np.radians(52.0)  # afternoon sun from the south-west


def sun_direction() -> np.ndarray:
    """[3] unit vector from the ground towards the sun."""
    c = np.cos(SUN_ELEVATION)
    return np.array([c * np.cos(SUN_AZIMUTH), c * np.sin(SUN_AZIMUTH), np.sin(SUN_ELEVATION)])


@dataclass
class Building:
    boxes: list[tuple[float, float, float, float]]  # footprint rectangles (x0, y0, x1, y1); 2 for an L
    eave: float  # wall height, metres
    roof: str  # "flat" or "gable"
    ridge_along_x: bool  # gable ridge direction
    ridge_rise: float  # gable: ridge height above the eaves
    roof_color: str  # key of ROOF_COLORS
    wall_rgb: tuple[float, float, float]
    instance: int

    @property
    def top(self) -> float:
        return self.eave + (self.ridge_rise if self.roof == "gable" else 0.0)


@dataclass
class Tree:
    x: float
    y: float
    radius: float  # crown radius, metres
    centre_z: float  # crown centre height
    rgb: tuple[float, float, float]
    instance: int


@dataclass
class Car:
    x: float
    y: float
    along_x: bool
    length: float
    width: float
    height: float
    rgb: tuple[float, float, float]
    instance: int


@dataclass
class Layout:
    size_m: float
    roads: list[tuple[str, float, float]]  # (axis "x" or "y", coordinate of the centre line, half width)
    ground: np.ndarray  # [R, R] uint8 CATEGORY codes
    markings: np.ndarray  # [R, R] bool white paint
    buildings: list[Building] = field(default_factory=list)
    trees: list[Tree] = field(default_factory=list)
    cars: list[Car] = field(default_factory=list)
    # [R, R] float32 0 (sunlit) .. 1 (full shadow); computed last, from everything above
    shadow: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))

    def cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raster (row, column) of world points [M, 2], clipped to the raster."""
        n = self.ground.shape[0]
        col = np.clip(((xy[:, 0] + self.size_m / 2) / GROUND_RES).astype(np.int64), 0, n - 1)
        row = np.clip(((xy[:, 1] + self.size_m / 2) / GROUND_RES).astype(np.int64), 0, n - 1)
        return row, col


def _road_lines(size_m: float, rng: np.random.Generator) -> list[float]:
    half = size_m / 2
    lines, position = [], -half + rng.uniform(18, 35)
    while position < half - 18:
        lines.append(position)
        position += rng.uniform(55, 85)
    return lines


def _overlaps(box, boxes, margin: float) -> bool:
    x0, y0, x1, y1 = box
    return any(x0 < b[2] + margin and b[0] < x1 + margin and y0 < b[3] + margin and b[1] < y1 + margin for b in boxes)


class _Builder:
    """Mutable state while placing things: the layout, the rng, footprints taken so far."""

    def __init__(self, layout: Layout, rng: np.random.Generator):
        self.layout, self.rng = layout, rng
        self.footprints: list[tuple[float, float, float, float]] = []
        self.next_instance = 0

    def instance(self) -> int:
        self.next_instance += 1
        return self.next_instance - 1

    def building(self, box, eave, roof, roof_color=None, l_shape=False) -> bool:
        rng = self.rng
        boxes = [box]
        if l_shape:
            x0, y0, x1, y1 = box
            w, d = x1 - x0, y1 - y0
            if rng.random() < 0.5:
                boxes.append((x0, y1 - 0.1, x0 + w * rng.uniform(0.35, 0.55), y1 + d * rng.uniform(0.4, 0.8)))
            else:
                boxes.append((x1 - 0.1, y0, x1 + w * rng.uniform(0.4, 0.7), y0 + d * rng.uniform(0.35, 0.55)))
        if any(_overlaps(b, self.footprints, 1.5) for b in boxes):
            return False
        half = self.layout.size_m / 2
        if any(b[0] < -half + 1 or b[1] < -half + 1 or b[2] > half - 1 or b[3] > half - 1 for b in boxes):
            return False
        self.footprints.extend(boxes)
        color = roof_color or rng.choice(list(ROOF_COLORS), p=[0.32, 0.18, 0.2, 0.3])
        along_x = (box[2] - box[0]) >= (box[3] - box[1])
        short = min(box[2] - box[0], box[3] - box[1])
        wall = rng.choice(
            [(0.86, 0.83, 0.76), (0.78, 0.74, 0.66), (0.70, 0.70, 0.70), (0.74, 0.56, 0.45), (0.9, 0.9, 0.88)]
        )
        self.layout.buildings.append(
            Building(
                boxes,
                eave,
                roof,
                along_x,
                0.5 * short * np.tan(np.radians(rng.uniform(25, 38))),
                str(color),
                tuple(wall),
                self.instance(),
            )
        )
        return True

    def tree(self, x, y, radius=None) -> None:
        rng = self.rng
        radius = radius or rng.uniform(2.0, 4.8)
        green = np.array([0.17, 0.33, 0.12]) * rng.uniform(0.75, 1.25) + rng.uniform(-0.03, 0.03, 3)
        self.layout.trees.append(
            Tree(x, y, radius, radius + rng.uniform(2.5, 6.0), tuple(np.clip(green, 0, 1)), self.instance())
        )

    def car(self, x, y, along_x) -> None:
        rng = self.rng
        palette = [
            (0.85, 0.85, 0.85),
            (0.1, 0.1, 0.11),
            (0.55, 0.56, 0.58),
            (0.6, 0.08, 0.07),
            (0.1, 0.2, 0.5),
            (0.92, 0.92, 0.9),
        ]
        rgb = np.array(palette[rng.integers(len(palette))]) * rng.uniform(0.9, 1.1)
        self.layout.cars.append(
            Car(
                x,
                y,
                along_x,
                rng.uniform(4.0, 4.9),
                rng.uniform(1.7, 1.95),
                rng.uniform(1.4, 1.6),
                tuple(np.clip(rgb, 0, 1)),
                self.instance(),
            )
        )


def _fill_residential(b: _Builder, block, ground) -> None:
    rng = b.rng
    x0, y0, x1, y1 = block
    paint(ground, block, "lawn", b.layout.size_m)
    for side in range(4):  # houses facing each street around the block
        length = (x1 - x0) if side % 2 == 0 else (y1 - y0)
        # sides 0 and 2 take the corners; sides 1 and 3 start behind those corner houses
        t, end = (rng.uniform(1, 4), length) if side % 2 == 0 else (rng.uniform(17, 19), length - 17)
        while t < end - 8:
            w, d, setback = rng.uniform(8, 13), rng.uniform(8, 11), rng.uniform(2, 5)
            if t + w > end - 1:
                break
            if side == 0:
                box = (x0 + t, y0 + setback, x0 + t + w, y0 + setback + d)
            elif side == 1:
                box = (x1 - setback - d, y0 + t, x1 - setback, y0 + t + w)
            elif side == 2:
                box = (x1 - t - w, y1 - setback - d, x1 - t, y1 - setback)
            else:
                box = (x0 + setback, y1 - t - w, x0 + setback + d, y1 - t)
            b.building(
                box, rng.uniform(3.0, 7.5), "gable" if rng.random() < 0.75 else "flat", l_shape=rng.random() < 0.25
            )
            t += w + rng.uniform(2.5, 6)
    for _ in range(int((x1 - x0) * (y1 - y0) / 120)):  # back-garden houses where they fit
        w, d = rng.uniform(8, 12, 2)
        bx, by = rng.uniform(x0 + 2, max(x0 + 2, x1 - 2 - w)), rng.uniform(y0 + 2, max(y0 + 2, y1 - 2 - d))
        if bx + w < x1 - 1 and by + d < y1 - 1:
            b.building((bx, by, bx + w, by + d), rng.uniform(3.0, 7.0), "gable" if rng.random() < 0.75 else "flat")
    for _ in range(int((x1 - x0) * (y1 - y0) / 250)):  # garden trees
        x, y = rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2)
        if not _overlaps((x - 1.5, y - 1.5, x + 1.5, y + 1.5), b.footprints, 0.5):
            b.tree(x, y)


def _fill_commercial(b: _Builder, block, ground) -> None:
    rng = b.rng
    x0, y0, x1, y1 = block
    paint(ground, block, "pavement", b.layout.size_m)
    w = min(x1 - x0 - 6, rng.uniform(20, 45))
    d = min(y1 - y0 - 6, rng.uniform(16, 35))
    if w > 10 and d > 10:
        # w may fill the block exactly: keep rounding from putting the high end below the low one
        bx, by = rng.uniform(x0 + 3, max(x0 + 3, x1 - 3 - w)), rng.uniform(y0 + 3, max(y0 + 3, y1 - 3 - d))
        b.building((bx, by, bx + w, by + d), rng.uniform(8, 26), "flat", l_shape=rng.random() < 0.3)
    # the largest free strip becomes a parking lot
    lot = max(
        [(x0 + 2, y0 + 2, x1 - 2, min(y1 - 2, y0 + 2 + 16)), (x0 + 2, max(y0 + 2, y1 - 2 - 16), x1 - 2, y1 - 2)],
        key=lambda r: 0 if _overlaps(r, b.footprints, 1.0) else (r[2] - r[0]) * (r[3] - r[1]),
    )
    if not _overlaps(lot, b.footprints, 1.0):
        _parking_lot(b, lot, ground)


def _fill_park(b: _Builder, block, ground) -> None:
    rng = b.rng
    x0, y0, x1, y1 = block
    paint(ground, block, "lawn", b.layout.size_m)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    paint(ground, (x0, cy - 1.2, x1, cy + 1.2), "bare ground", b.layout.size_m)  # footpaths
    paint(ground, (cx - 1.2, y0, cx + 1.2, y1), "bare ground", b.layout.size_m)
    for _ in range(int((x1 - x0) * (y1 - y0) / 90)):
        x, y = rng.uniform(x0 + 3, x1 - 3), rng.uniform(y0 + 3, y1 - 3)
        if abs(x - cx) > 3.5 and abs(y - cy) > 3.5:
            b.tree(x, y, rng.uniform(2.5, 5.5))


def _parking_lot(b: _Builder, lot, ground) -> None:
    rng = b.rng
    x0, y0, x1, y1 = lot
    paint(ground, lot, "parking", b.layout.size_m)
    n = ground.shape[0]
    markings = b.layout.markings
    stall = 2.6
    rows = []  # back-to-back double rows of 5 m stalls with 6 m aisles between them
    for y in np.arange(y0 + 0.5, y1 - 5.0, 16.0):
        rows.append((y, y + 5.0))
        if y + 10.0 < y1 - 0.5:
            rows.append((y + 5.0, y + 10.0))
    for ry0, ry1 in rows:
        x = x0 + 1.0
        while x + stall < x1 - 1.0:
            line = _to_cells((x, ry0, x + 0.12, ry1), b.layout.size_m, n)
            markings[line] = True
            if rng.random() < 0.65:
                b.car(x + stall / 2, (ry0 + ry1) / 2, along_x=False)
            x += stall
        markings[_to_cells((x, ry0, x + 0.12, ry1), b.layout.size_m, n)] = True


def _to_cells(rect, size_m, n):
    x0, y0, x1, y1 = rect
    c0, c1 = (np.clip(np.array([x0, x1]) + size_m / 2, 0, size_m) / GROUND_RES).astype(int)
    r0, r1 = (np.clip(np.array([y0, y1]) + size_m / 2, 0, size_m) / GROUND_RES).astype(int)
    return slice(r0, max(r1, r0 + 1)), slice(c0, max(c1, c0 + 1))


def paint(ground: np.ndarray, rect, category: str, size_m: float) -> None:
    ground[_to_cells(rect, size_m, ground.shape[0])] = CATEGORY[category]


def _roads(b: _Builder, ground) -> None:
    layout, rng = b.layout, b.rng
    size_m, half = layout.size_m, layout.size_m / 2
    n = ground.shape[0]
    for axis, c, hw in layout.roads:  # pavements first, then roads over them at crossings
        rect = (-half, c - hw - 2.2, half, c + hw + 2.2) if axis == "x" else (c - hw - 2.2, -half, c + hw + 2.2, half)
        paint(ground, rect, "pavement", size_m)
    for axis, c, hw in layout.roads:
        rect = (-half, c - hw, half, c + hw) if axis == "x" else (c - hw, -half, c + hw, half)
        paint(ground, rect, "road", size_m)
    crossings = {axis: [c for a, c, _ in layout.roads if a != axis] for axis in ("x", "y")}
    for axis, c, hw in layout.roads:
        for t0 in np.arange(-half, half, 6.0):  # dashed centre line, 3 m dashes, off at crossings
            if any(abs(t0 + 1.5 - other) < 12 for other in crossings[axis]):
                continue
            dash = (t0, c - 0.08, t0 + 3.0, c + 0.08) if axis == "x" else (c - 0.08, t0, c + 0.08, t0 + 3.0)
            layout.markings[_to_cells(dash, size_m, n)] = True
        for edge in (c - hw + 0.4, c + hw - 0.4):  # solid edge lines
            line = (-half, edge - 0.06, half, edge + 0.06) if axis == "x" else (edge - 0.06, -half, edge + 0.06, half)
            layout.markings[_to_cells(line, size_m, n)] = True
        for other in crossings[axis]:  # zebra crossings before each intersection
            for side in (-1, 1):
                t = other + side * 10.0
                for k in np.arange(-hw + 0.6, hw - 0.6, 1.0):
                    stripe = (
                        (t - 1.5, c + k, t + 1.5, c + k + 0.5)
                        if axis == "x"
                        else (c + k, t - 1.5, c + k + 0.5, t + 1.5)
                    )
                    layout.markings[_to_cells(stripe, size_m, n)] = True
        # street trees on the pavement of some roads
        if rng.random() < 0.6:
            for t in np.arange(-half + 6, half - 6, rng.uniform(9, 14)):
                if any(abs(t - other) < 14 for other in crossings[axis]):
                    continue
                pavement = c + (hw + 1.2) * (1 if rng.random() < 0.5 else -1)
                x, y = (t, pavement) if axis == "x" else (pavement, t)
                if not _overlaps((x - 1, y - 1, x + 1, y + 1), b.footprints, 0.5):
                    b.tree(x, y, rng.uniform(2.8, 4.5))
        # cars on the lanes
        for t in np.arange(-half + 5, half - 5, 5.0):
            if rng.random() < 0.07 and not any(abs(t - other) < hw + 4 for other in crossings[axis]):
                lane = c + hw / 2 * (1 if rng.random() < 0.5 else -1)
                x, y = (t, lane) if axis == "x" else (lane, t)
                b.car(x, y, along_x=axis == "x")


def _shadows(layout: Layout) -> np.ndarray:
    """Soft sun shadows on the ground: each caster's footprint swept along the sun's rays."""
    n = layout.ground.shape[0]
    shadow = np.zeros((n, n), np.float32)
    sun = sun_direction()
    run = -sun[:2] / np.tan(SUN_ELEVATION)  # ground offset per metre of height
    to_px = lambda pts: np.round((np.asarray(pts) + layout.size_m / 2) / GROUND_RES).astype(np.int32)  # noqa: E731

    def cast(corners_xy, height):
        pts = np.concatenate([corners_xy, corners_xy + run * height])
        cv2.fillConvexPoly(shadow, cv2.convexHull(to_px(pts)), 1.0)

    for building in layout.buildings:
        for x0, y0, x1, y1 in building.boxes:
            cast(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), building.top)
    for tree in layout.trees:
        centre = np.array([tree.x, tree.y]) + run * tree.centre_z
        cv2.ellipse(
            shadow, tuple(int(v) for v in to_px(centre)), (int(tree.radius / GROUND_RES),) * 2, 0, 0, 360, 1.0, -1
        )
    for car in layout.cars:
        hl, hw = (car.length / 2, car.width / 2) if car.along_x else (car.width / 2, car.length / 2)
        cast(
            np.array(
                [[car.x - hl, car.y - hw], [car.x + hl, car.y - hw], [car.x + hl, car.y + hw], [car.x - hl, car.y + hw]]
            ),
            car.height,
        )
    return cv2.GaussianBlur(shadow, (0, 0), 0.35 / GROUND_RES)


def generate_layout(size_m: float, rng: np.random.Generator) -> Layout:
    """A town plan on a ``size_m`` square (see the module docstring)."""
    roads = [("y", x, rng.uniform(3.5, 6.0)) for x in _road_lines(size_m, rng)]
    roads += [("x", y, rng.uniform(3.5, 6.0)) for y in _road_lines(size_m, rng)]
    n = int(round(size_m / GROUND_RES))
    layout = Layout(
        size_m, roads, ground=np.full((n, n), CATEGORY["bare ground"], np.uint8), markings=np.zeros((n, n), bool)
    )
    builder = _Builder(layout, rng)
    half = size_m / 2
    xs = [-half, *sorted(c for a, c, _ in roads if a == "y"), half]
    ys = [-half, *sorted(c for a, c, _ in roads if a == "x"), half]
    widths = {c: hw for _, c, hw in roads}
    blocks = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            block = (
                xs[i] + widths.get(xs[i], 0.0) + 2.5,
                ys[j] + widths.get(ys[j], 0.0) + 2.5,
                xs[i + 1] - widths.get(xs[i + 1], 0.0) - 2.5,
                ys[j + 1] - widths.get(ys[j + 1], 0.0) - 2.5,
            )
            if block[2] - block[0] >= 12 and block[3] - block[1] >= 12:
                blocks.append(block)
    # every kind of block appears (as far as there are blocks), the rest are drawn at random
    kinds = ["residential", "parking", "residential", "commercial", "park"][: len(blocks)]
    kinds += list(
        rng.choice(
            ["residential", "commercial", "park", "parking"], p=[0.66, 0.16, 0.08, 0.1], size=len(blocks) - len(kinds)
        )
    )
    fill = {"residential": _fill_residential, "commercial": _fill_commercial, "park": _fill_park}
    for block, kind in zip(blocks, rng.permutation(kinds), strict=True):
        if kind == "parking":
            _parking_lot(builder, (block[0] + 1, block[1] + 1, block[2] - 1, block[3] - 1), layout.ground)
        else:
            fill[kind](builder, block, layout.ground)
    _roads(builder, layout.ground)
    layout.shadow = _shadows(layout)
    return layout
