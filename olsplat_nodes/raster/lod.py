"""Level of detail for rendering a large map from afar: merged Gaussians stand in for the
Gaussians of a cube that spans at most a pixel or two in the view.

The cubes: level l = 1..L of a grid of world-axis cubes of side ``cell_m * 2^(l-1)`` metres
(origin at 0), nested (a level-l cube is 8 level-(l-1) cubes). Each non-empty cube holds one
merged Gaussian of its members, by moment matching with weights w = opacity x area (area = pi
times the two largest standard deviations, the footprint of a flat splat):
- mean = sum w mu / sum w; covariance = sum w (Sigma + mu mu^T) / sum w - mean mean^T;
- opacity = min(0.99, sum opacity x area / merged area): the covered area is kept;
- colour: the w-weighted DC term (higher SH coefficients 0); a feature: the w-weighted mean
  of the members' features (``node_features``), zero rows (never observed) included.
Cube moments are sums, so a cube's come from its children's.

For a camera (``select``), a cube passes when its side spans at most ``max_px`` pixels at the
depth of its merged mean (side x focal / depth). Each Gaussian is drawn through the coarsest
passing cube that contains it, or as itself when none does. The cubes are nested, so every
member of a drawn cube is drawn through that cube: each Gaussian is drawn exactly once.
Near a UAV camera nothing passes and the render is exact; towards the horizon a cube of
sub-pixel Gaussians becomes one Gaussian of about a pixel or two.

``_reference.lod_nodes_reference`` is the per-cube numpy oracle of the build.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..scene import Camera, Gaussians
from ..scene.rotations import rotmats_to_quats

# columns of a cube's moment sums
W, WX, WY, WZ, WXX, WXY, WXZ, WYY, WYZ, WZZ, WR, WG, WB, COVER = range(14)
MOMENTS = 14
MAX_OPACITY = 0.99


@dataclass(frozen=True)
class LodConfig:
    cell_m: float = 0.25  # side of the level-1 cubes, metres
    levels: int = 6  # cubes of cell_m * 2^(l-1), l = 1..levels (0.25 m to 8 m by default)
    max_px: float = 2.0  # a cube is drawn merged when its side spans at most this many pixels

    def __post_init__(self) -> None:
        if not (self.cell_m > 0 and self.levels >= 1 and self.max_px >= 0):
            raise ValueError(f"need cell_m > 0, levels >= 1, max_px >= 0, got {self}")


@dataclass
class LodTree:
    """The merged Gaussians of every cube, level 1 first, and how they nest."""

    config: LodConfig
    nodes: Gaussians  # [M] merged Gaussians (the map's SH degree, coefficients above the DC 0)
    node_level: np.ndarray  # [M] int32 level 1..L
    node_side: np.ndarray  # [M] float32 cube side, metres
    parent: np.ndarray  # [M] int32 cube one level up, -1 at level L
    leaf: np.ndarray  # [N] int32 each Gaussian's level-1 cube
    weight: np.ndarray  # [N] float32 each Gaussian's w (opacity x area)
    node_weight: np.ndarray  # [M] float64 sum of the members' w
    # the members of each cube, for sums cube by cube: level-1 cube j holds the Gaussians
    # leaf_order[leaf_first[j]:leaf_first[j+1]]; cube j of a higher level holds the cubes
    # child_order[child_first[j]:child_first[j+1]] (none for level 1)
    leaf_order: np.ndarray  # [N] int64
    leaf_first: np.ndarray  # [leaves + 1] int64
    child_order: np.ndarray  # [M - top-level cubes] int64
    child_first: np.ndarray  # [M + 1] int64

    def __len__(self) -> int:
        return len(self.nodes)


def _cube_keys(coords: np.ndarray) -> np.ndarray:
    """[n] int64 key of integer cube coordinates [n, 3] (any sign, |c| < 2^20)."""
    c = coords + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


@njit(cache=True)
def _leaf_moments(means, quats, log_scales, opacity_logits, dc, leaf, n_leaves):
    """([n_leaves, MOMENTS] float64 sums over each level-1 cube, [N] float32 w)."""
    out = np.zeros((n_leaves, MOMENTS), np.float64)
    weights = np.empty(means.shape[0], np.float32)
    for i in range(means.shape[0]):
        opacity = 1.0 / (1.0 + np.exp(-float(opacity_logits[i])))
        s = np.exp(log_scales[i].astype(np.float64))
        s.sort()
        area = np.pi * s[1] * s[2]
        w = opacity * area
        weights[i] = w
        qw, qx, qy, qz = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
        qn = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        r = np.array(
            [
                [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
                [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
            ]
        )
        variances = np.exp(2.0 * log_scales[i].astype(np.float64))
        m = means[i].astype(np.float64)
        cov = np.zeros((3, 3))
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for k in range(3):
                    acc += r[a, k] * variances[k] * r[b, k]
                cov[a, b] = acc + m[a] * m[b]  # the second moment about 0
        row = out[leaf[i]]
        row[W] += w
        row[WX] += w * m[0]
        row[WY] += w * m[1]
        row[WZ] += w * m[2]
        row[WXX] += w * cov[0, 0]
        row[WXY] += w * cov[0, 1]
        row[WXZ] += w * cov[0, 2]
        row[WYY] += w * cov[1, 1]
        row[WYZ] += w * cov[1, 2]
        row[WZZ] += w * cov[2, 2]
        row[WR] += w * dc[i, 0]
        row[WG] += w * dc[i, 1]
        row[WB] += w * dc[i, 2]
        row[COVER] += w  # opacity x area, summed
    return out, weights


def _merged(moments: np.ndarray, block: int = 262_144) -> Gaussians:
    """Gaussians [M] of SH degree 0 from cube moment sums [M, MOMENTS] (the module docstring's
    rules), block by block: the per-cube 3x3 temporaries stay small."""
    parts = [_merged_block(moments[a : a + block]) for a in range(0, len(moments), block)]
    return Gaussians(
        means=np.concatenate([part.means for part in parts]),
        quats=np.concatenate([part.quats for part in parts]),
        log_scales=np.concatenate([part.log_scales for part in parts]),
        opacity_logits=np.concatenate([part.opacity_logits for part in parts]),
        sh=np.concatenate([part.sh for part in parts]),
    )


def _merged_block(moments: np.ndarray) -> Gaussians:
    total = moments[:, W]
    mean = moments[:, WX : WZ + 1] / total[:, None]
    second = np.empty((len(moments), 3, 3))
    for (a, b), column in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(WXX, WZZ + 1), strict=True):
        second[:, a, b] = second[:, b, a] = moments[:, column] / total
    cov = second - mean[:, :, None] * mean[:, None, :]
    variances, axes = np.linalg.eigh(cov)  # ascending
    variances = np.maximum(variances, 1e-12)  # a flat cube (one flat member) stays flat, not degenerate
    axes[np.linalg.det(axes) < 0, :, 0] *= -1  # a rotation, not a reflection
    scales = np.sqrt(variances)
    area = np.pi * scales[:, 1] * scales[:, 2]
    opacity = np.clip(moments[:, COVER] / area, 1e-6, MAX_OPACITY)
    sh = (moments[:, WR : WB + 1] / total[:, None]).astype(np.float32)[:, None, :]
    return Gaussians(
        means=mean,
        quats=rotmats_to_quats(axes),
        log_scales=np.log(scales),
        opacity_logits=np.log(opacity / (1.0 - opacity)),
        sh=sh,
    )


def build_lod(gaussians: Gaussians, config: LodConfig = LodConfig()) -> LodTree:
    """The cubes of ``gaussians`` and their merged Gaussians (~25 s for 5.2M Gaussians, 3.5M
    cubes, on this project's slow 2-core VM).
    Gaussians must be finite (``read_ply``'s default)."""
    n = len(gaussians)
    coords = np.floor(gaussians.means.astype(np.float64) / config.cell_m).astype(np.int64)
    keys, inverse = np.unique(_cube_keys(coords), return_inverse=True)
    leaf = inverse.astype(np.int32).reshape(n)
    level_coords = np.zeros((len(keys), 3), np.int64)
    level_coords[leaf] = coords  # every member of a cube has the cube's coordinates
    moments, weights = _leaf_moments(
        gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits,
        np.ascontiguousarray(gaussians.sh[:, 0, :]), leaf, len(keys),
    )  # fmt: skip
    all_moments, levels, parents = [moments], [np.full(len(keys), 1, np.int32)], []
    for level in range(2, config.levels + 1):
        up = level_coords >> 1  # floor(c / 2), also for negative coordinates
        up_keys, parent = np.unique(_cube_keys(up), return_inverse=True)
        parent = parent.reshape(-1)
        up_coords = np.zeros((len(up_keys), 3), np.int64)
        up_coords[parent] = up
        up_moments = np.zeros((len(up_keys), MOMENTS))
        np.add.at(up_moments, parent, all_moments[-1])
        parents.append(parent)
        all_moments.append(up_moments)
        levels.append(np.full(len(up_keys), level, np.int32))
        level_coords = up_coords
    starts = np.cumsum([0] + [len(m) for m in all_moments])
    parent_global = np.full(starts[-1], -1, np.int32)
    for level_index, parent in enumerate(parents):  # level l's parents are level l + 1's cubes
        parent_global[starts[level_index] : starts[level_index + 1]] = parent + starts[level_index + 1]
    stacked = np.concatenate(all_moments)
    del all_moments
    node_level = np.concatenate(levels)
    has_parent = np.flatnonzero(parent_global >= 0)
    return LodTree(
        config=config,
        nodes=_merged(stacked),
        node_level=node_level,
        node_side=(config.cell_m * 2.0 ** (node_level - 1)).astype(np.float32),
        parent=parent_global,
        leaf=leaf,
        weight=weights,
        node_weight=stacked[:, W].copy(),
        leaf_order=np.argsort(leaf, kind="stable"),
        leaf_first=np.concatenate([[0], np.cumsum(np.bincount(leaf, minlength=len(keys)))]),
        child_order=has_parent[np.argsort(parent_global[has_parent], kind="stable")],
        child_first=np.concatenate([[0], np.cumsum(np.bincount(parent_global[has_parent], minlength=starts[-1]))]),
    )


@njit(cache=True, parallel=True)
def _passing(means, side, rotation, translation, focal, max_px, near):
    """[M] bool: the cube's side spans at most max_px pixels at its merged mean's depth."""
    out = np.zeros(means.shape[0], np.bool_)
    for j in prange(means.shape[0]):
        z = rotation[2, 0] * means[j, 0] + rotation[2, 1] * means[j, 1] + rotation[2, 2] * means[j, 2] + translation[2]
        out[j] = z > near and side[j] * focal <= max_px * z
    return out


def select(tree: LodTree, camera: Camera, near: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(Gaussians drawn as themselves [N] bool, cubes drawn merged [M] bool) for ``camera``."""
    view = camera.camera_from_world
    passing = _passing(
        tree.nodes.means, tree.node_side, view[:3, :3], view[:3, 3], max(camera.fx, camera.fy), tree.config.max_px, near
    )
    covered = passing.copy()  # the cube or one above it passes; filled from the top level down
    drawn = passing.copy()
    for level in range(tree.config.levels - 1, 0, -1):
        at = np.flatnonzero(tree.node_level == level)
        above = covered[tree.parent[at]]
        covered[at] |= above
        drawn[at] &= ~above
    return ~covered[tree.leaf], drawn


def _group_means(values_of, weights, order, first, group_weight, out, block: int = 131_072) -> None:
    """out[j] = sum over the members m = order[first[j]:first[j+1]] of weights[m] values_of(m)
    / group_weight[j], for the groups j of ``out`` (first [len(out) + 1] absolute positions in
    order), ``block`` groups at a time: their members' float32 values and one sum per group."""
    for a in range(0, len(out), block):
        b = min(a + block, len(out))
        members = order[first[a] : first[b]]
        values = values_of(members) * weights[members, None].astype(np.float32)
        sums = np.add.reduceat(values, first[a:b] - first[a], axis=0)  # every cube has a member
        out[a:b] = sums / group_weight[a:b, None]


def node_features(tree: LodTree, table: np.ndarray, rows: np.ndarray | None, dtype=np.float32) -> np.ndarray:
    """[M, D] ``dtype``: each cube's w-weighted mean of its members' features, Gaussian g's being
    table[rows[g]] (table [N, D] and rows None: row g), zero where the row is -1. Cube by cube
    in blocks (a level-1 cube from its Gaussians, a higher one from its eight children's means
    and weights), in float32 sums: the only array the size of the cubes is the result (float16:
    2 bytes per value, 450 MB for the large map's 3.5M cubes at D = 64)."""
    out = np.empty((len(tree), table.shape[1]), dtype)
    leaves = len(tree.leaf_first) - 1  # level 1 comes first
    if rows is None:
        values_of = lambda members: np.asarray(table[members], np.float32)  # noqa: E731
    else:
        padded = np.concatenate([np.asarray(table, np.float32), np.zeros((1, table.shape[1]), np.float32)])
        values_of = lambda members: padded[rows[members]]  # noqa: E731 (row -1: the zero row)
    _group_means(values_of, tree.weight, tree.leaf_order, tree.leaf_first, tree.node_weight, out[:leaves])
    for level in range(2, tree.config.levels + 1):  # a cube's mean from its children's (levels are stacked)
        at = np.flatnonzero(tree.node_level == level)
        lo, hi = int(at[0]), int(at[-1]) + 1
        _group_means(
            lambda members: np.asarray(out[members], np.float32),
            tree.node_weight,
            tree.child_order,
            tree.child_first[lo : hi + 1],
            tree.node_weight[lo:hi],
            out[lo:hi],
        )
    return out


def with_nodes(gaussians: Gaussians, tree: LodTree) -> Gaussians:
    """[N + M] the map's Gaussians followed by the cubes' merged ones: what a level-of-detail
    heatmap draws from, with ``drawn`` as its ``active`` mask. SH degree 0 (the DC colour only:
    heatmaps composite features, not colours; degree 3 would be 1.7 GB for the large map);
    extras are not carried."""
    nodes = tree.nodes
    return Gaussians(
        means=np.concatenate([gaussians.means, nodes.means]),
        quats=np.concatenate([gaussians.quats, nodes.quats]),
        log_scales=np.concatenate([gaussians.log_scales, nodes.log_scales]),
        opacity_logits=np.concatenate([gaussians.opacity_logits, nodes.opacity_logits]),
        sh=np.concatenate([gaussians.sh[:, :1], nodes.sh]),
    )


def drawn(tree: LodTree, camera: Camera) -> np.ndarray:
    """[N + M] bool ``active`` mask over ``with_nodes``'s Gaussians for ``camera`` (``select``)."""
    own, merged = select(tree, camera)
    return np.concatenate([own, merged])


def with_node_features(
    table: np.ndarray, rows: np.ndarray | None, merged: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None]:
    """The feature table and rows of ``with_nodes``'s Gaussians, from the map's (table [N, D]
    with rows None, or a codebook's centres [K, D] with rows [N]) and the cubes' features
    ``merged`` [M, D] (``node_features``), stored in the cubes' dtype."""
    combined = np.concatenate([np.asarray(table, merged.dtype), merged])
    if rows is None:
        return combined, None
    return combined, np.concatenate([rows, len(table) + np.arange(len(merged), dtype=rows.dtype)])


@dataclass
class LodMap:
    """A map's level of detail ready to render one map version's features: the tree, the
    Gaussians with the cubes' merged ones (``with_nodes``) and the feature table and rows over
    them (``with_node_features``)."""

    tree: LodTree
    gaussians: Gaussians  # [N + M]
    table: np.ndarray  # [N + M, D] (rows None) or [K + M, D]
    rows: np.ndarray | None  # [N + M] int32 or None

    @staticmethod
    def of(
        tree: LodTree, gaussians_with_nodes: Gaussians, table: np.ndarray, rows: np.ndarray | None, dtype=np.float16
    ) -> LodMap:
        """From the map's features (table [N, D] with rows None, or centres [K, D] with rows [N]);
        the combined table in ``dtype`` (float16: the heatmap kernel reads it as it is)."""
        combined, combined_rows = with_node_features(table, rows, node_features(tree, table, rows, dtype))
        return LodMap(tree, gaussians_with_nodes, combined, combined_rows)

    def drawn(self, camera: Camera) -> np.ndarray:
        """[N + M] bool: what a render of ``camera`` draws (``drawn``)."""
        return drawn(self.tree, camera)
