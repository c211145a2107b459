"""A procedural town as 3D Gaussians, sized like a trained UAV-scene splat.

World frame: metres, +z up, the town centred on the origin at ground level z = 0.
Surfaces (ground, roofs, walls) are covered by flat Gaussians (thin along the surface
normal) at a density set by the Gaussian budget; tree crowns are clumps of rounder ones.
Colours come from procedural noise so that no region is a flat colour. Every Gaussian keeps
its category and instance id, the ground truth later issues evaluate against.

This is the first, small scene generator (for the demo and the rasterizer benchmark); the
replay simulator extends it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from olsplat_nodes.scene import Gaussians

CATEGORIES = ("ground", "road", "lawn", "roof", "wall", "tree")
ROOF_COLORS = {"red": (0.62, 0.18, 0.12), "blue": (0.18, 0.32, 0.62), "white": (0.88, 0.88, 0.86), "grey": (0.45, 0.45, 0.47)}


@dataclass
class Town:
    gaussians: Gaussians
    category: np.ndarray  # [N] int16 index into CATEGORIES
    instance: np.ndarray  # [N] int32, -1 for stuff (ground, road, lawn)
    size_m: float  # side of the square footprint in metres


def _value_noise(points: np.ndarray, scale: float, rng: np.random.Generator, octaves: int = 3) -> np.ndarray:
    """[M, 2] metres -> [M] noise in about -1..1, smooth at ``scale`` metres."""
    total = np.zeros(len(points))
    amplitude = 1.0
    for _ in range(octaves):
        grid = rng.uniform(-1, 1, (64, 64))
        uv = points / scale
        i0 = np.floor(uv).astype(np.int64)
        f = uv - i0
        f = f * f * (3 - 2 * f)
        a, b = i0[:, 0] % 64, i0[:, 1] % 64
        a1, b1 = (a + 1) % 64, (b + 1) % 64
        top = grid[a, b] * (1 - f[:, 0]) + grid[a1, b] * f[:, 0]
        bottom = grid[a, b1] * (1 - f[:, 0]) + grid[a1, b1] * f[:, 0]
        total += amplitude * (top * (1 - f[:, 1]) + bottom * f[:, 1])
        scale, amplitude = scale / 2.0, amplitude / 2.0
    return total / 1.75


def _quats_from_normals(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """[M, 3] unit normals -> [M, 4] wxyz rotating +z onto the normal, random spin about it."""
    spin = rng.uniform(0, np.pi, len(normals))
    q_spin = np.stack([np.cos(spin), np.zeros_like(spin), np.zeros_like(spin), np.sin(spin)], 1)
    axis = np.cross([0.0, 0.0, 1.0], normals)
    cos = normals[:, 2]
    q_align = np.concatenate([(1 + cos)[:, None], axis], 1)
    q_align[cos < -0.9999] = [0.0, 1.0, 0.0, 0.0]
    q_align /= np.linalg.norm(q_align, axis=1, keepdims=True)
    w1, v1 = q_align[:, :1], q_align[:, 1:]
    w2, v2 = q_spin[:, :1], q_spin[:, 1:]
    return np.concatenate([w1 * w2 - (v1 * v2).sum(1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], 1)


def make_town(n_gaussians: int = 100_000, size_m: float = 150.0, seed: int = 0) -> Town:
    """A square town of side ``size_m`` with about ``n_gaussians`` Gaussians."""
    rng = np.random.default_rng(seed)
    half = size_m / 2
    # Layout: a road grid every ~50 m, buildings in the blocks, trees along roads and lawns.
    road_pitch, road_half_width = 50.0, 4.0
    n_blocks = max(1, int(size_m // road_pitch))
    buildings = []  # (x0, y0, x1, y1, height, roof colour)
    for bx in range(n_blocks):
        for by in range(n_blocks):
            cx0 = -half + bx * road_pitch + road_half_width + 3
            cy0 = -half + by * road_pitch + road_half_width + 3
            for _ in range(rng.integers(1, 4)):
                w, d = rng.uniform(8, 20, 2)
                x0, y0 = cx0 + rng.uniform(0, road_pitch - 2 * road_half_width - 6 - w), cy0 + rng.uniform(0, road_pitch - 2 * road_half_width - 6 - d)
                if any(x0 < b[2] + 2 and b[0] < x0 + w + 2 and y0 < b[3] + 2 and b[1] < y0 + d + 2 for b in buildings):
                    continue
                buildings.append((x0, y0, x0 + w, y0 + d, rng.uniform(6, 25), list(ROOF_COLORS)[rng.integers(4)]))
    n_trees = int(size_m * size_m / 400)
    tree_xy = rng.uniform(-half, half, (n_trees, 2))
    tree_r = rng.uniform(2.0, 4.5, n_trees)

    roof_area = sum((b[2] - b[0]) * (b[3] - b[1]) for b in buildings)
    wall_area = sum(2 * ((b[2] - b[0]) + (b[3] - b[1])) * b[4] for b in buildings)
    tree_area = float((4 * np.pi * tree_r**2).sum()) * 0.6
    areas = np.array([size_m * size_m, roof_area, wall_area, tree_area])
    counts = np.maximum((areas / areas.sum() * n_gaussians).astype(int), 1)
    spacing = np.sqrt(areas.sum() / n_gaussians)

    parts = []  # (means, normals or None, colours, category, instance, flat)

    # ground: road grid, lawns, bare ground
    p = rng.uniform(-half, half, (counts[0], 2))
    on_road = (np.abs(((p + half) % road_pitch) - road_half_width) < road_half_width).any(1)
    lawn = _value_noise(p, 25.0, rng) > 0.05
    noise = _value_noise(p, 3.0, rng)[:, None]
    colors = np.where(lawn[:, None], [0.25, 0.45, 0.18], [0.55, 0.48, 0.38]) + 0.08 * noise
    markings = on_road & (np.abs(((p + half) % road_pitch) - road_half_width) < 0.15).any(1)
    colors = np.where(on_road[:, None], 0.32 + 0.05 * noise, colors)
    colors[markings] = 0.92
    category = np.where(on_road, 1, np.where(lawn, 2, 0))
    parts.append((np.c_[p, np.zeros(len(p))], np.tile([0.0, 0, 1], (len(p), 1)), colors, category, np.full(len(p), -1)))

    # buildings: roofs and walls, one instance per building
    per_roof = np.array([(b[2] - b[0]) * (b[3] - b[1]) for b in buildings]) / max(roof_area, 1e-9)
    per_wall = np.array([2 * ((b[2] - b[0]) + (b[3] - b[1])) * b[4] for b in buildings]) / max(wall_area, 1e-9)
    for k, (x0, y0, x1, y1, height, roof) in enumerate(buildings):
        m = max(1, int(per_roof[k] * counts[1]))
        q = np.c_[rng.uniform(x0, x1, m), rng.uniform(y0, y1, m)]
        c = np.asarray(ROOF_COLORS[roof]) * (1 + 0.15 * _value_noise(q, 2.0, rng)[:, None])
        parts.append((np.c_[q, np.full(m, height)], np.tile([0.0, 0, 1], (m, 1)), c, np.full(m, 3), np.full(m, k)))
        m = max(4, int(per_wall[k] * counts[2]))
        perimeter = 2 * ((x1 - x0) + (y1 - y0))
        s = rng.uniform(0, perimeter, m)
        z = rng.uniform(0, height, m)
        w = x1 - x0
        d = y1 - y0
        side = np.searchsorted([w, w + d, 2 * w + d], s, side="right")
        t = s - np.array([0, w, w + d, 2 * w + d])[side]
        xy = np.select(
            [(side == j)[:, None] for j in range(4)],
            [np.c_[x0 + t, np.full(m, y0)], np.c_[np.full(m, x1), y0 + t], np.c_[x1 - t, np.full(m, y1)], np.c_[np.full(m, x0), y1 - t]],
        )
        normals = np.array([[0.0, -1, 0], [1.0, 0, 0], [0.0, 1, 0], [-1.0, 0, 0]])[side]
        stripes = (np.floor(z / 3.0) % 2)[:, None]  # storeys
        c = 0.62 + 0.06 * stripes + 0.06 * _value_noise(np.c_[s, z], 1.5, rng)[:, None]
        parts.append((np.c_[xy, z], normals, np.repeat(c, 3, 1), np.full(m, 4), np.full(m, k)))

    # trees: crowns as clumps of rounder Gaussians near a sphere surface
    per_tree = tree_r**2 / (tree_r**2).sum()
    for k in range(n_trees):
        m = max(4, int(per_tree[k] * counts[3]))
        direction = rng.normal(size=(m, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        direction[:, 2] = np.abs(direction[:, 2]) * 0.8 + 0.2 * direction[:, 2]
        centre = np.array([*tree_xy[k], tree_r[k] + rng.uniform(2, 5)])
        pts = centre + direction * tree_r[k] * rng.uniform(0.75, 1.0, (m, 1))
        c = np.array([0.16, 0.36, 0.12]) * (1 + 0.35 * rng.uniform(-1, 1, (m, 1)))
        parts.append((pts, None, c, np.full(m, 5), np.full(m, len(buildings) + k)))

    means = np.concatenate([p[0] for p in parts])
    n = len(means)
    normals = np.concatenate([p[1] if p[1] is not None else np.tile([0.0, 0, 1], (len(p[0]), 1)) for p in parts])
    is_flat = np.concatenate([np.full(len(p[0]), p[1] is not None) for p in parts])
    quats = _quats_from_normals(normals, rng)
    quats[~is_flat] = rng.normal(size=(int((~is_flat).sum()), 4))
    size = spacing * rng.uniform(0.6, 1.1, (n, 1))
    scales = np.concatenate([size, size * rng.uniform(0.6, 1.0, (n, 1)), np.where(is_flat[:, None], 0.03 * size, size * 0.8)], 1)
    means[is_flat] += normals[is_flat] * rng.normal(0, 0.01, (int(is_flat.sum()), 1))
    colors = np.clip(np.concatenate([p[2] for p in parts]), 0.0, 1.0)
    opacities = rng.uniform(0.6, 0.99, n)
    gaussians = Gaussians.from_colors(means, colors, scales, opacities, quats)
    return Town(
        gaussians=gaussians,
        category=np.concatenate([p[3] for p in parts]).astype(np.int16),
        instance=np.concatenate([p[4] for p in parts]).astype(np.int32),
        size_m=size_m,
    )
