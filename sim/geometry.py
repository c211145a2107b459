"""Geometry that partly follows labels (world.GeometryWorld, strength S in [0, 1]).

In the town of ``layout.py`` and ``scene.py`` a roof's colour (which of four labels its building
takes) is drawn independently of the building's shape, and every ground class lies flat at
z = 0, so no 3D feature can tell labels apart. At strength S the town gets, each scaled by S:

- **roof material tied to building type and size** (``tie_roof_colors``): with probability S a
  building takes a colour drawn from its type's distribution (``TIED_ROOF_COLORS``: large flat
  roofs grey bitumen or white membrane, gabled houses mostly red tiles, small flat roofs mostly
  white or blue) instead of today's independent draw;
- **curbs** (``raise_pavements``): pavements stand ``KERB_M`` x S above the road (0.12 m at
  S = 1, a common kerb height), with a vertical kerb face where pavement meets road or parking;
- **rough grass against smooth asphalt** (``roughen_lawns``): lawn Gaussians rise by blades of
  0..``GRASS_M`` x S plus turf bumps of +-``TURF_M`` x S and tilt by ``TURF_TILT_DEG`` x S; road,
  parking, pavement and bare ground stay as flat as today;
- **tree crowns** (``shape_crowns``): the crown's vertical semi-axis goes from 0.85 to
  0.85 + ``CROWN_STRETCH`` x S of its radius (1.3 at S = 1: an upright ovoid, taller than wide),
  its base kept at its height (the centre and the baked shadow rise with it).

Every draw comes from the town's geometry stream (``world.geometry_stream``), and only when
S > 0: at S = 0 nothing here runs and the town is byte-identical to the one before. The draws
are made for every building whatever S, so a larger S ties a superset of a smaller S's roofs.
"""

from __future__ import annotations

import numpy as np

from .labels import CATEGORY, ROOF_COLORS
from .layout import GROUND_RES, Layout, _shadows

KERB_M = 0.12  # kerb height at S = 1, metres (typical kerbs: 0.10-0.15 m)
GRASS_M = 0.06  # grass blades: a lawn Gaussian rises by uniform(0, GRASS_M) x S, metres
TURF_M = 0.04  # smooth turf bumps (about 3 m across): +-TURF_M x S, metres
TURF_TILT_DEG = 12.0  # std of a lawn Gaussian's tilt from vertical at S = 1, per axis, degrees
CROWN_STRETCH = 0.45  # added to the crown's vertical semi-axis (0.85 of its radius) at S = 1
LARGE_ROOF_M2 = 150.0  # a flat roof on at least this footprint is "large" (commercial)

# the tied colour distributions (probabilities in ROOF_COLORS order: red, blue, white, grey). With
# the town's mix of roofs (about 70 % gabled, 22 % small flat, 8 % large flat by count) they keep
# each colour's share near today's (red 0.32 -> ~0.39, blue 0.18 -> ~0.21, white 0.20 -> ~0.17,
# grey 0.30 -> ~0.24), so a tie changes what a roof's shape says, not much how common a label is
TIED_ROOF_COLORS = {
    "large flat": (0.0, 0.0, 0.4, 0.6),  # membrane or bitumen
    "small flat": (0.0, 0.3, 0.45, 0.25),  # sheet metal, membrane, felt
    "gable": (0.55, 0.2, 0.05, 0.2),  # clay tiles, glazed or metal, slate
}


def roof_type(boxes, roof: str) -> str:
    """A building's key into TIED_ROOF_COLORS: its roof shape and, for flat roofs, its footprint."""
    if roof == "gable":
        return "gable"
    area = sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in boxes)
    return "large flat" if area >= LARGE_ROOF_M2 else "small flat"


def tie_roof_colors(layout: Layout, strength: float, rng: np.random.Generator) -> None:
    """With probability ``strength`` per building, its roof colour from its type's distribution."""
    names = list(ROOF_COLORS)
    for b in layout.buildings:
        tied, u = rng.choice(names, p=TIED_ROOF_COLORS[roof_type(b.boxes, b.roof)]), rng.random()
        if u < strength:
            b.roof_color = str(tied)


def raise_crowns(layout: Layout, strength: float) -> None:
    """Raise each crown's centre so its base stays where it was once ``shape_crowns`` stretches it,
    and recast the baked shadows (``layout._shadows`` draws nothing)."""
    for t in layout.trees:
        t.centre_z += t.radius * CROWN_STRETCH * strength
    layout.shadow = _shadows(layout)


def shape_crowns(means: np.ndarray, instance: np.ndarray, layout: Layout, strength: float) -> np.ndarray:
    """[M, 3] crown Gaussian means (trees of ``raise_crowns``'d ``layout``) -> stretched vertically
    about their tree's centre, from 0.85 to 0.85 + CROWN_STRETCH x S of the radius."""
    centre_z = {t.instance: t.centre_z for t in layout.trees}
    centres = np.array([centre_z[i] for i in instance.tolist()]) if len(instance) else np.zeros(0)
    out = means.copy()
    out[:, 2] = centres + (means[:, 2] - centres) * (0.85 + CROWN_STRETCH * strength) / 0.85
    return out


def raise_pavements(means: np.ndarray, category: np.ndarray, strength: float) -> np.ndarray:
    """[M, 3] ground means -> pavement ones at the kerb height KERB_M x S."""
    out = means.copy()
    out[category == CATEGORY["pavement"], 2] += KERB_M * strength
    return out


def roughen_lawns(
    means: np.ndarray, normals: np.ndarray, category: np.ndarray, strength: float, bumps, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(means, normals) [M, 3] of ground Gaussians -> lawn ones raised and tilted (module docstring).
    ``bumps(xy [K, 2]) -> [K]`` is a smooth field in about [-1, 1] (scene.py's noise)."""
    lawn = np.flatnonzero(category == CATEGORY["lawn"])
    means, normals = means.copy(), normals.copy()
    blades = rng.uniform(0.0, GRASS_M, len(lawn))
    tilt = rng.normal(0.0, np.radians(TURF_TILT_DEG), (len(lawn), 2))
    means[lawn, 2] += strength * (blades + TURF_M * np.clip(bumps(means[lawn, :2]), -1.0, 1.0))
    tilted = np.c_[np.sin(strength * tilt), np.ones(len(lawn))]
    normals[lawn] = tilted / np.linalg.norm(tilted, axis=1, keepdims=True)
    return means, normals


def kerb_faces(
    layout: Layout, density: float, strength: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(means [K, 3], normals [K, 3], colours [K, 3]) of the vertical kerb faces, z in
    [0, KERB_M x S], on the raster edges between a pavement cell and a road or parking cell
    (normal towards the lower cell), ``density`` Gaussians per m^2. Labelled pavement by the caller."""
    ground, height = layout.ground, KERB_M * strength
    pave = ground == CATEGORY["pavement"]
    low = (ground == CATEGORY["road"]) | (ground == CATEGORY["parking"])
    edges = []  # (row, col of the pavement cell, normal x, normal y)
    for axis, step in ((0, 1), (0, -1), (1, 1), (1, -1)):  # axis 0: rows (y), 1: columns (x)
        neighbour_low = np.roll(low, -step, axis=axis)
        edge = pave & neighbour_low
        border = [slice(None), slice(None)]
        border[axis] = slice(-1, None) if step == 1 else slice(0, 1)
        edge[tuple(border)] = False  # np.roll wraps around: not an edge
        rows, cols = np.nonzero(edge)
        dx, dy = (step, 0) if axis == 1 else (0, step)
        edges.append(np.c_[rows, cols, np.full(len(rows), dx), np.full(len(rows), dy)])
    cells = np.concatenate(edges)
    count = rng.poisson(density * len(cells) * GROUND_RES * height)
    pick = cells[rng.integers(len(cells), size=count)] if len(cells) else np.zeros((0, 4), np.int64)
    along, z = rng.uniform(0.0, 1.0, count), rng.uniform(0.0, height, count)
    half = layout.size_m / 2
    nx, ny = pick[:, 2].astype(float), pick[:, 3].astype(float)
    # the cell's side facing the neighbour: centre + half a cell along the normal, spread along it
    x = -half + (pick[:, 1] + 0.5 + 0.5 * nx + (along - 0.5) * (nx == 0)) * GROUND_RES
    y = -half + (pick[:, 0] + 0.5 + 0.5 * ny + (along - 0.5) * (ny == 0)) * GROUND_RES
    normals = np.c_[nx, ny, np.zeros(count)]
    colors = np.tile(np.array([0.66, 0.65, 0.62]), (count, 1)) * rng.uniform(0.9, 1.05, (count, 1))  # kerb stone
    return np.c_[x, y, z], normals, colors
