"""Ground-truth 3D Gaussians for a town plan, with a label on every Gaussian.

Surfaces (ground, roofs, walls, cars) are covered by flat Gaussians (thin along the normal)
at one density, set by the Gaussian budget; tree crowns are clumps of rounder ones. Colours
are the surface colour times procedural noise, with sunlight baked in as a photo has it:
faces turned to the sun are brighter and the ground is darker inside cast shadows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from olsplat_nodes.scene import Gaussians

from . import geometry as geo
from .labels import CATEGORY, LABEL, ROOF_COLORS, STUFF_LABEL, building_label
from .layout import GROUND_RES, Building, Layout, generate_layout, sun_direction
from .noise import Noise2D
from .world import GEOMETRY_WORLD_KEY, GeometryWorld

GROUND_COLORS = {
    "bare ground": (0.50, 0.44, 0.35),
    "road": (0.29, 0.29, 0.30),
    "lawn": (0.27, 0.40, 0.16),
    "parking": (0.34, 0.34, 0.35),
    "pavement": (0.60, 0.58, 0.54),
}
PAINT = np.array([0.88, 0.88, 0.84])
GLASS = np.array([0.24, 0.29, 0.35])


@dataclass
class TruthScene:
    gaussians: Gaussians
    category: np.ndarray  # [N] int16 index into labels.CATEGORIES
    instance: np.ndarray  # [N] int32 building/tree/car id, -1 for stuff
    label: np.ndarray  # [N] int16 index into labels.LABELS
    layout: Layout
    glass: np.ndarray | None = None  # [N] bool: windows and car glass (world v2's specular material)

    @property
    def size_m(self) -> float:
        return self.layout.size_m


@dataclass
class _Part:
    means: np.ndarray  # [M, 3]
    normals: np.ndarray | None  # [M, 3] for flat surface Gaussians, None for crowns
    colors: np.ndarray  # [M, 3]
    category: np.ndarray  # [M]
    instance: np.ndarray  # [M]
    label: np.ndarray  # [M]
    glass: np.ndarray | None = None  # [M] bool, None: no glass


def _shade(normals: np.ndarray) -> np.ndarray:
    """[M] brightness of a surface in the baked sunlight: 0.55 ambient + diffuse."""
    return 0.55 + 0.6 * np.clip(normals @ sun_direction(), 0.0, None)


def _part(means, normals, colors, category, instance, label, glass=None) -> _Part:
    m = len(means)
    return _Part(
        np.asarray(means, float), normals, np.clip(colors, 0.0, 1.0),
        np.full(m, category, np.int16), np.full(m, instance, np.int32), np.full(m, label, np.int16), glass,
    )  # fmt: skip


def _ground(layout: Layout, count: int, footprint: np.ndarray, rng, noise: Noise2D) -> _Part:
    half = layout.size_m / 2
    xy = rng.uniform(-half, half, (int(count / max(1e-6, 1.0 - footprint.mean())) + 16, 2))
    row, col = layout.cell(xy)
    keep = ~footprint[row, col]
    xy, row, col = xy[keep][:count], row[keep][:count], col[keep][:count]
    codes = layout.ground[row, col]
    colors = np.zeros((len(xy), 3))
    coarse, fine = noise(xy, 18.0)[:, None], noise(xy * 7.3, 4.0)[:, None]
    for name, rgb in GROUND_COLORS.items():
        mask = codes == CATEGORY[name]
        variation = {"lawn": 0.22 * coarse + 0.12 * fine, "bare ground": 0.12 * coarse + 0.1 * fine}.get(
            name, 0.05 * coarse + 0.07 * fine
        )
        colors[mask] = np.asarray(rgb) * (1.0 + variation[mask])
        if name == "lawn":  # dry, yellower patches
            colors[mask] += np.clip(coarse[mask], 0, None) * np.array([0.12, 0.06, 0.0])
    paint = layout.markings[row, col]
    colors[paint] = PAINT * (1.0 + 0.05 * fine[paint])
    colors *= 1.0 - 0.58 * layout.shadow[row, col][:, None]
    category = codes.astype(np.int16)
    label = np.array(
        [LABEL[STUFF_LABEL[name]] for name in ("bare ground", "road", "lawn", "parking", "pavement")], np.int16
    )[category]
    means = np.c_[xy, np.zeros(len(xy))]
    normals = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    return _Part(means, normals, np.clip(colors, 0, 1), category, np.full(len(xy), -1, np.int32), label)


def _building_area(b: Building) -> tuple[float, float]:
    """(roof area, wall area) in m^2."""
    roof = walls = 0.0
    for x0, y0, x1, y1 in b.boxes:
        w, d = x1 - x0, y1 - y0
        short = min(w, d)
        slope = np.arctan2(b.ridge_rise, short / 2) if b.roof == "gable" else 0.0
        roof += (w + 0.6) * (d + 0.6) / np.cos(slope)
        walls += 2 * (w + d) * b.eave + (short * b.ridge_rise if b.roof == "gable" else 0.0)
    return roof, walls


def _building(b: Building, density: float, rng, noise: Noise2D) -> list[_Part]:
    parts = []
    label = LABEL[building_label(b.roof_color)]
    roof_rgb = np.asarray(ROOF_COLORS[b.roof_color]) * rng.uniform(0.88, 1.1) * rng.uniform(0.97, 1.03, 3)
    commercial = b.roof == "flat" and b.eave > 8
    for k, (x0, y0, x1, y1) in enumerate(b.boxes):
        others = [box for j, box in enumerate(b.boxes) if j != k]
        w, d = x1 - x0, y1 - y0
        along_x = w >= d
        short = min(w, d)
        # walls: four faces; gable ends rise to the ridge
        faces = [
            ((x0, y0), (x1, y0), (0, -1)),
            ((x1, y0), (x1, y1), (1, 0)),
            ((x1, y1), (x0, y1), (0, 1)),
            ((x0, y1), (x0, y0), (-1, 0)),
        ]
        for (ax, ay), (bx, by), (nx, ny) in faces:
            length = np.hypot(bx - ax, by - ay)
            gable_end = b.roof == "gable" and ((nx != 0) == along_x)
            height = b.top if gable_end else b.eave
            m = rng.poisson(density * length * height)
            t, z = rng.uniform(0, 1, m), rng.uniform(0, height, m)
            if gable_end:
                keep = z <= b.eave + b.ridge_rise * (1 - np.abs(2 * t - 1))
                t, z = t[keep], z[keep]
            xy = np.c_[ax + t * (bx - ax), ay + t * (by - ay)]
            inside_other = np.zeros(len(xy), bool)
            for ox0, oy0, ox1, oy1 in others:
                inside_other |= (
                    (xy[:, 0] > ox0 + 0.05)
                    & (xy[:, 0] < ox1 - 0.05)
                    & (xy[:, 1] > oy0 + 0.05)
                    & (xy[:, 1] < oy1 - 0.05)
                )
            xy, z, t = xy[~inside_other], z[~inside_other], t[~inside_other]
            normal = np.array([nx, ny, 0.0])
            s = t * length
            if commercial:
                window = (z % 3.6 > 1.0) & (z % 3.6 < 2.7) & (z > 1.5)
            else:
                window = (s % 3.2 > 1.0) & (s % 3.2 < 2.2) & (z % 3.0 > 0.9) & (z % 3.0 < 2.2) & (z < b.eave - 0.4)
            colors = np.asarray(b.wall_rgb) * (1.0 + 0.06 * noise(np.c_[s, z] + 31.0 * b.instance, 2.0))[:, None]
            colors[window] = GLASS * (1.0 + 0.3 * noise(np.c_[s, z][window], 1.0))[:, None]
            colors *= (_shade(normal[None])[0] * (0.8 + 0.2 * np.clip(z / 1.5, 0, 1)))[:, None]
            parts.append(
                _part(np.c_[xy, z], np.tile(normal, (len(z), 1)), colors, CATEGORY["wall"], b.instance, label, window)
            )
        # roof, overhanging the walls by 0.3 m
        rx0, ry0, rx1, ry1 = x0 - 0.3, y0 - 0.3, x1 + 0.3, y1 + 0.3
        area_flat = (rx1 - rx0) * (ry1 - ry0)
        if b.roof == "gable":
            slope = np.arctan2(b.ridge_rise, short / 2)
            m = rng.poisson(density * area_flat / np.cos(slope))
            xy = np.c_[rng.uniform(rx0, rx1, m), rng.uniform(ry0, ry1, m)]
            across = xy[:, 1] - (y0 + y1) / 2 if along_x else xy[:, 0] - (x0 + x1) / 2
            from_ridge = np.abs(across)
            z = b.eave + b.ridge_rise * (1 - from_ridge / (short / 2))
            side = np.sign(across) + (across == 0)
            normals = np.zeros((m, 3))
            normals[:, 1 if along_x else 0] = side * np.sin(slope)
            normals[:, 2] = np.cos(slope)
            texture = 1.0 + 0.07 * np.where((from_ridge / 0.33).astype(int) % 2 == 0, 1.0, -1.0)
        else:
            m = rng.poisson(density * area_flat)
            xy = np.c_[rng.uniform(rx0, rx1, m), rng.uniform(ry0, ry1, m)]
            z = np.full(m, b.eave)
            normals = np.tile([0.0, 0.0, 1.0], (m, 1))
            edge = np.minimum.reduce([xy[:, 0] - rx0, rx1 - xy[:, 0], xy[:, 1] - ry0, ry1 - xy[:, 1]])
            texture = np.where(edge < 0.5, 0.8, 1.0)  # parapet
        inside_other = np.zeros(m, bool)
        for ox0, oy0, ox1, oy1 in others:  # the lower roof of an L stops where the other starts
            inside_other |= (xy[:, 0] > ox0) & (xy[:, 0] < ox1) & (xy[:, 1] > oy0) & (xy[:, 1] < oy1) & (k == 1)
        stains = 1.0 + 0.1 * noise(xy + 57.0 * b.instance, 6.0) + 0.05 * noise(xy * 5.0, 2.0)
        colors = roof_rgb * (stains * texture * _shade(normals) / 1.15)[:, None]
        keep = ~inside_other
        parts.append(_part(np.c_[xy, z][keep], normals[keep], colors[keep], CATEGORY["roof"], b.instance, label))
    return parts


def _trees(layout: Layout, density: float, rng) -> _Part:
    trees = layout.trees
    if not trees:
        return _part(np.zeros((0, 3)), None, np.zeros((0, 3)), CATEGORY["tree"], -1, LABEL["tree"])
    radius = np.array([t.radius for t in trees])
    counts = rng.poisson(density * 0.8 * 4 * np.pi * radius**2)
    owner = np.repeat(np.arange(len(trees)), counts)
    m = len(owner)
    direction = rng.normal(size=(m, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    # leaf clumps near the crown's surface; lobes (a random low-order wave per tree) make it bumpy
    phase = rng.uniform(0, 2 * np.pi, (len(trees), 3))[owner]
    lobes = 0.12 * (
        np.sin(3 * direction[:, 0] + phase[:, 0])
        + np.sin(3 * direction[:, 1] + phase[:, 1])
        + np.sin(2 * direction[:, 2] + phase[:, 2])
    )
    depth = rng.uniform(0.72, 1.0, m) * (1.0 + lobes)
    centre = np.array([[t.x, t.y, t.centre_z] for t in trees])[owner]
    offset = direction * (radius[owner] * depth)[:, None] * np.array([1.0, 1.0, 0.85])
    rgb = np.array([t.rgb for t in trees])[owner]
    light = _shade(direction) * (0.72 + 0.28 * (direction[:, 2] + 1) / 2) * rng.uniform(0.8, 1.2, m)
    colors = rgb * light[:, None]
    instance = np.array([t.instance for t in trees], np.int32)[owner]
    return _Part(
        centre + offset,
        None,
        np.clip(colors, 0, 1),
        np.full(m, CATEGORY["tree"], np.int16),
        instance,
        np.full(m, LABEL["tree"], np.int16),
    )


def _car(car, density: float, rng) -> _Part:
    hl, hw = car.length / 2, car.width / 2
    faces = [  # (centre offset, normal, extent along u, extent along v) in the car frame (x forward)
        ((0, 0, car.height), (0, 0, 1), (hl, 0, 0), (0, hw, 0)),
        ((hl, 0, car.height / 2), (1, 0, 0), (0, hw, 0), (0, 0, car.height / 2)),
        ((-hl, 0, car.height / 2), (-1, 0, 0), (0, hw, 0), (0, 0, car.height / 2)),
        ((0, hw, car.height / 2), (0, 1, 0), (hl, 0, 0), (0, 0, car.height / 2)),
        ((0, -hw, car.height / 2), (0, -1, 0), (hl, 0, 0), (0, 0, car.height / 2)),
    ]
    parts: tuple[list[np.ndarray], ...] = ([], [], [], [])  # means, normals, colours, glass
    for centre, normal, eu, ev in faces:
        area = 4 * np.linalg.norm(eu) * np.linalg.norm(ev)
        m = max(3, rng.poisson(density * area))
        u, v = rng.uniform(-1, 1, (2, m))
        local = np.asarray(centre) + u[:, None] * np.asarray(eu) + v[:, None] * np.asarray(ev)
        rgb = np.tile(np.asarray(car.rgb) * 0.95, (m, 1))
        if normal[2] == 1:  # windscreen and rear window on the top
            glass = (np.abs(u) > 0.35) & (np.abs(u) < 0.75) & (np.abs(v) < 0.85)
        else:
            glass = local[:, 2] > car.height * 0.62
        rgb[glass] = GLASS * 0.8
        parts[0].append(local)
        parts[1].append(np.tile(normal, (m, 1)).astype(float))
        parts[2].append(rgb * _shade(np.asarray(normal, float)[None])[0])
        parts[3].append(glass)
    means, normals, colors, glass = (np.concatenate(p) for p in parts)
    if not car.along_x:  # rotate the car frame by 90 degrees about z
        means = means[:, [1, 0, 2]] * [-1, 1, 1]
        normals = normals[:, [1, 0, 2]] * [-1, 1, 1]
    means = means + np.array([car.x, car.y, 0.0])  # an array: a shift, not list concatenation
    return _part(means, normals, colors, CATEGORY["car"], car.instance, LABEL["car"], glass)


def _quats_from_normals(normals: np.ndarray, rng) -> np.ndarray:
    """[M, 3] unit normals -> [M, 4] wxyz turning +z onto the normal, random spin about it."""
    spin = rng.uniform(0, np.pi, len(normals))
    q_spin = np.c_[np.cos(spin), np.zeros((len(spin), 2)), np.sin(spin)]
    q_align = np.c_[1.0 + normals[:, 2], np.cross([0.0, 0.0, 1.0], normals)]
    q_align[normals[:, 2] < -0.9999] = [0.0, 1.0, 0.0, 0.0]
    q_align /= np.linalg.norm(q_align, axis=1, keepdims=True)
    w1, v1, w2, v2 = q_align[:, :1], q_align[:, 1:], q_spin[:, :1], q_spin[:, 1:]
    return np.c_[w1 * w2 - (v1 * v2).sum(1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)]


def _shapes(parts: list[_Part], spacing: float, rng) -> tuple[np.ndarray, ...]:
    """(means [N, 3] jittered along their normals, quats [N, 4], scales [N, 3], opacities [N]) of
    the parts' Gaussians: flat surface ones thin along their normal, crown ones rounder."""
    means = np.concatenate([p.means for p in parts])
    n = len(means)
    flat = np.concatenate([np.full(len(p.means), p.normals is not None) for p in parts])
    normals = np.concatenate(
        [p.normals if p.normals is not None else np.tile([0.0, 0, 1], (len(p.means), 1)) for p in parts]
    )
    quats = _quats_from_normals(normals, rng)
    quats[~flat] = rng.normal(size=(int((~flat).sum()), 4))
    size = spacing * rng.uniform(0.6, 1.1, n)
    scales = np.c_[size, size * rng.uniform(0.6, 1.0, n), np.where(flat, 0.04, 0.55) * size]
    scales[~flat, :2] *= 1.5  # leaf clumps: larger and rounder
    means[flat] += normals[flat] * rng.normal(0, 0.01, (int(flat.sum()), 1))
    opacities = np.where(flat, rng.uniform(0.85, 0.99, n), rng.uniform(0.55, 0.95, n))
    return means, quats, scales, opacities


def _follow_labels(ground: _Part, trees: _Part, layout: Layout, density: float, strength: float, noise, rng) -> _Part:
    """geometry.py's ground and crown ties on the parts (in place); returns the kerb faces' part."""
    assert ground.normals is not None  # the ground's Gaussians are flat
    ground.means, ground.normals = geo.roughen_lawns(
        geo.raise_pavements(ground.means, ground.category, strength),
        ground.normals,
        ground.category,
        strength,
        lambda xy: noise(xy * 1.7 + 913.0, 3.0),  # turf bumps: the texture noise, elsewhere on its lattice
        rng,
    )
    trees.means = geo.shape_crowns(trees.means, trees.instance, layout, strength)
    means, normals, colors = geo.kerb_faces(layout, density, strength, rng)
    colors = colors * _shade(normals)[:, None]
    return _part(means, normals, colors, CATEGORY["pavement"], -1, LABEL[STUFF_LABEL["pavement"]])


def generate_scene(n_gaussians: int, size_m: float, seed: int, geometry: GeometryWorld | None = None) -> TruthScene:
    """A town of side ``size_m`` metres with about ``n_gaussians`` labelled Gaussians; ``geometry``
    (world.GeometryWorld) ties its geometry to its labels (geometry.py), None or strength 0: not."""
    rng = np.random.default_rng(seed)
    noise = Noise2D(seed + 1)
    layout = generate_layout(size_m, rng)
    strength = geometry.strength if geometry is not None else 0.0
    geo_rng = None
    if strength > 0:  # its own stream: at strength 0 no draw is made from it nor any other
        geo_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=GEOMETRY_WORLD_KEY))
        geo.tie_roof_colors(layout, strength, geo_rng)
        geo.raise_crowns(layout, strength)
    footprint = footprint_mask(layout)
    areas = [size_m**2 * (1.0 - footprint.mean())]
    areas += [sum(_building_area(b)) for b in layout.buildings]
    areas += [0.8 * 4 * np.pi * t.radius**2 for t in layout.trees]
    areas += [c.length * c.width + 2 * (c.length + c.width) * c.height for c in layout.cars]
    density = n_gaussians / sum(areas)  # Gaussians per square metre of surface
    spacing = 1.0 / np.sqrt(density)

    parts = [_ground(layout, int(round(areas[0] * density)), footprint, rng, noise)]
    for b in layout.buildings:
        parts += _building(b, density, rng, noise)
    trees = _trees(layout, density, rng)
    parts.append(trees)
    parts += [_car(c, density, rng) for c in layout.cars]
    kerbs = [] if geo_rng is None else [_follow_labels(parts[0], trees, layout, density, strength, noise, geo_rng)]
    means, quats, scales, opacities = _shapes(parts, spacing, rng)
    if kerbs:  # last, from their own stream: the other Gaussians keep their spins, sizes and opacities
        extra = _shapes(kerbs, spacing, geo_rng)
        means, quats, scales, opacities = (
            np.concatenate(pair) for pair in zip((means, quats, scales, opacities), extra, strict=True)
        )
        parts += kerbs
    colors = np.concatenate([p.colors for p in parts])
    return TruthScene(
        gaussians=Gaussians.from_colors(means, colors, scales, opacities, quats),
        category=np.concatenate([p.category for p in parts]),
        instance=np.concatenate([p.instance for p in parts]),
        label=np.concatenate([p.label for p in parts]),
        layout=layout,
        glass=np.concatenate([p.glass if p.glass is not None else np.zeros(len(p.means), bool) for p in parts]),
    )


def footprint_mask(layout: Layout) -> np.ndarray:
    """[R, R] bool raster of building footprints (no ground Gaussians there)."""
    mask = np.zeros(layout.markings.shape, np.uint8)
    for b in layout.buildings:
        for x0, y0, x1, y1 in b.boxes:
            p0 = ((np.array([x0, y0]) + layout.size_m / 2) / GROUND_RES).astype(int)
            p1 = ((np.array([x1, y1]) + layout.size_m / 2) / GROUND_RES).astype(int)
            cv2.rectangle(mask, tuple(int(v) for v in p0), tuple(int(v) for v in p1), 1, -1)
    return mask.astype(bool)
