"""Where the queried things are: regions in a view and instances in 3D.

In a view: connected components of the query's mask (8-connected, >= ``min_pixels``), with
box, centre and area. In 3D: the Gaussians that pick the query over the negatives (highest
cosine among query + negatives) and are observed, clustered with DBSCAN (radius ``eps``,
``min_points``) on their centres; each cluster is an instance with an axis-aligned box in world
metres.

DBSCAN is computed here on a voxel grid in numba rather than by open3d, whose KD-tree version
took 0.4-7 s on the 80k-320k selected centres of a 390k-Gaussian map, most of a query's latency;
this takes 15-60 ms there (18 ms for 130k centres on planes plus noise, where open3d took 3.5-8
s), on a shared 2-core machine. Voxels have side ``eps``, so a point's eps-ball lies within its own voxel and the 26
touching ones, and every search looks at those 27 voxels only (points sorted by int64 voxel
key; touching voxels found by binary search on the keys):

1. Core points, DBSCAN's own test and the noise rule: at least ``min_points`` selected centres,
   itself included, within ``eps``. Whole half-side cells of a voxel that lie within ``eps``
   count without a distance each (``_core``), counting stops at ``min_points``, and voxels whose
   27-voxel block holds fewer points are skipped outright, so dense data costs little.
2. Clusters: voxels holding core points are linked when they touch and a core point of one lies
   within ``eps`` of a core point of the other (union-find over voxels; a pair already joined
   through other voxels is not looked at). The one departure from DBSCAN: all core points of a
   voxel are in one cluster, even the rare ones that no chain of eps-steps joins (they are less
   than sqrt(3) ``eps`` apart).
3. Border points: a point that is not core but lies within ``eps`` of core points joins the
   cluster of the voxel with the most core points among those holding such a core point (ties:
   the lowest voxel (i, j, k)); DBSCAN leaves that choice to its visiting order. Border points
   never link clusters.
4. Clusters of at least ``min_points`` points, border points included, are the instances.

As with DBSCAN, objects more than ``eps`` apart are separate instances (unless both crowd into
one voxel, which needs them less than sqrt(3) ``eps`` apart) and sparse noise forms none.
Against open3d's DBSCAN on a simulated 390k-Gaussian map: for seven real query selections
(80k-320k centres) the instances are the same, their sizes within 3 points (border points
DBSCAN gave to a neighbouring instance); for each label's Gaussians as the selection, with and
without 3% scattered false picks, the point-wise adjusted Rand index is >= 0.999. The simpler
rule of linking touching voxels that hold at least a few points (no distances at all; 13 ms
instead of 18 ms for the 130k centres) linked objects up to 2 ``eps`` apart, merging two roofs
2-2.6 m apart at ``eps`` = 1.5 m in a "red roof buildings" query, and its per-voxel density test
let uniform noise of 0.17 points/m^3 form instances, where DBSCAN needs about 0.5.

``olsplat_nodes/query/_reference.py`` is the brute-force oracle of the same rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import get_num_threads, njit, prange

# One of each +/- pair of the 26 neighbour offsets: searching keys + offset for all 13 finds
# every touching pair of occupied voxels once.
_HALF_NEIGHBOURS = np.array(
    [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)], np.int64
)  # [13, 3]


# Voxels per iteration of the parallel core test: each iteration makes one small scratch array
# for its run of voxels instead of one per voxel.
VOXEL_RUN = 64


@dataclass
class Region2D:
    box: tuple[int, int, int, int]  # x0, y0, x1, y1 pixels (exclusive end)
    centre: tuple[float, float]  # pixel coordinates, centre of the top-left pixel at (0.5, 0.5)
    pixels: int


@dataclass
class Instance3D:
    box_min: tuple[float, float, float]  # world metres
    box_max: tuple[float, float, float]
    centre: tuple[float, float, float]  # mean of the member centres
    gaussians: int


def regions_in_view(mask: np.ndarray, min_pixels: int = 50) -> list[Region2D]:
    count, _labels, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    out = []
    for i in range(1, count):
        x, y, w, h, area = stats[i]
        if area >= min_pixels:
            out.append(
                Region2D(
                    (int(x), int(y), int(x + w), int(y + h)),
                    (float(centroids[i][0] + 0.5), float(centroids[i][1] + 0.5)),
                    int(area),
                )
            )
    return sorted(out, key=lambda r: -r.pixels)


def default_cluster_radius(means: np.ndarray, min_points: int = 20) -> float:
    """A DBSCAN radius (metres) that suits the map's density: a map is mostly a surface seen from
    above, so its mean spacing is about sqrt(ground area / N) (area from the 1st-99th percentiles
    of x and y); a disc of radius r holds ~min_points Gaussians when r = spacing * sqrt(min_points
    / pi), and twice that leaves room for thinner objects. Never below 1.5 m. The small preset
    (390k Gaussians over 150 m) gets 1.5 m; the tiny one (26k), ~3 m."""
    return radius_for_density(ground_density(means), min_points)


def radius_for_density(density: float, min_points: int = 20) -> float:
    """``default_cluster_radius`` (metres) of a map with ``density`` Gaussians per m² of ground
    (``ground_density``), for callers that need the density for something else too."""
    if not density > 0:
        return 1.5
    spacing = math.sqrt(1.0 / density)
    return max(1.5, 2.0 * spacing * math.sqrt(min_points / math.pi))


def ground_density(means: np.ndarray) -> float:
    """A map's Gaussians per square metre of ground: its finite centres (``means`` [N, 3], map
    metres) over the area of the box between the 1st and 99th percentiles of x and y (a few
    far-flung Gaussians do not dilute it). 0 for fewer than two centres. The small preset: ~23 per
    m²; the tiny one: ~2.6."""
    xy = np.asarray(means, np.float64)[:, :2]
    xy = xy[np.isfinite(xy).all(1)]
    if len(xy) < 2:
        return 0.0
    low, high = np.percentile(xy, 1, axis=0), np.percentile(xy, 99, axis=0)
    return len(xy) / max(float(np.prod(high - low)), 1e-6)


@dataclass(frozen=True)
class VoxelIndex:
    """A map's Gaussians sorted once by their voxel of side ``eps`` on a grid anchored at the
    map's lowest centre: a query then takes its selection in this order instead of sorting it
    (the sort was half the clustering of 855k selected Gaussians of a 5M map). The instances are
    DBSCAN's either way; the voxel grid only moves the two documented approximations (points of
    one voxel, border ties), so an instance may differ by a few border points."""

    eps: float
    lowest: np.ndarray  # [3] the grid's origin, metres
    dims: np.ndarray  # [3] int64 key radix
    order: np.ndarray  # [N'] int64 Gaussians (finite centres only) by voxel key
    voxel_keys: np.ndarray  # [V] int64 the occupied voxels' keys, ascending
    voxel_start: np.ndarray  # [V + 1] int64 voxel v's Gaussians at order[voxel_start[v]:voxel_start[v + 1]]
    points: np.ndarray  # [N', 3] their centres in this order, in the means' own float type (float32
    # for a PLY's: 12 bytes per Gaussian, widened exactly as a query copies them): a selection is
    # then a sequential compress of these rows, not a random gather of means

    @staticmethod
    def build(means: np.ndarray, eps: float) -> VoxelIndex:
        means = np.asarray(means)
        finite = np.flatnonzero(np.isfinite(means).all(1))
        points = means[finite] if means.dtype == np.float32 else means[finite].astype(np.float64)
        lowest, highest = _bounds(points) if len(points) else (np.zeros(3), np.zeros(3))
        lowest, highest = lowest.astype(np.float64), highest.astype(np.float64)
        dims = np.floor((highest - lowest) / eps).astype(np.int64) + 3
        keys = _voxel_keys(points, lowest, float(eps), dims)
        order = np.argsort(keys, kind="stable")
        keys = keys[order]
        new = np.ones(len(keys), bool)
        np.not_equal(keys[1:], keys[:-1], out=new[1:])
        voxel_start = np.append(np.flatnonzero(new), len(keys)).astype(np.int64)
        return VoxelIndex(
            float(eps), lowest, dims, finite[order].astype(np.int64), keys[new], voxel_start, points[order]
        )


def instances_in_3d(
    means: np.ndarray,
    selected: np.ndarray | None,
    eps: float = 1.5,
    min_points: int = 20,
    index: VoxelIndex | None = None,
    in_order: np.ndarray | None = None,
) -> list[Instance3D]:
    """DBSCAN clusters of the selected Gaussians' centres, largest first (module docstring).

    means [N, 3] world metres; selected: [N] bool mask or integer indices (None when
    ``in_order`` is given); eps: DBSCAN radius
    and voxel side, metres; min_points: points within eps (itself included) that make a point
    core, and the smallest instance; index: the map's ``VoxelIndex`` for this ``eps``;
    in_order: ``selected`` already in the index's order ([N'] bool), when the caller has it.
    """
    if not eps > 0:
        raise ValueError(f"eps must be a positive distance in metres, got eps={eps!r}")
    if selected is None and (in_order is None or index is None or index.eps != float(eps)):
        raise ValueError("instances_in_3d needs selected, unless in_order comes with its index")
    if index is not None and index.eps == float(eps):
        if in_order is not None:
            take, count = in_order, int(np.count_nonzero(in_order))
        else:
            selected = np.asarray(selected)
            if selected.dtype != np.bool_:
                mask = np.zeros(len(means), bool)
                mask[selected] = True
                selected = mask
            take, count = _in_order(selected, index.order)
        if count < max(min_points, 1):
            return []
        # a copy (the clustering reorders it in place), grouped by voxel
        points, keys, start = _grouped(take, index.points, index.voxel_keys, index.voxel_start)
        dims, lowest = index.dims, index.lowest
    else:
        points = np.asarray(means)[selected].astype(np.float64)  # [M, 3]
        if not np.isfinite(points.sum()):  # rare: a NaN/inf centre is nowhere, noise as DBSCAN has it
            points = points[np.isfinite(points).all(1)]
        if len(points) == 0 or len(points) < min_points:
            return []
        points, keys, start, dims, lowest = _voxelise(points, eps)  # points now sorted by voxel
    first, second = _touching_pairs(keys, dims)
    cluster = _cluster_points(points, start, first, second, float(eps), int(min_points), lowest)  # [M]
    count, low, high, total = _cluster_stats(points, cluster, len(keys), get_num_threads())
    order = np.flatnonzero(count >= max(min_points, 1))
    order = order[np.argsort(-count[order], kind="stable")]  # largest first; ties by lowest voxel
    return [Instance3D(_floats(low[c]), _floats(high[c]), _floats(total[c] / count[c]), int(count[c])) for c in order]


@njit(cache=True)
def _in_order(selected, order):
    """([N'] bool: selected[order], how many are True), in one pass."""
    take = np.empty(order.shape[0], np.bool_)
    count = 0
    for i in range(order.shape[0]):
        take[i] = selected[order[i]]
        count += take[i]
    return take, count


# Runs of the index's voxels per parallel chunk in ``_grouped`` (many more chunks than threads:
# even loads).
GROUP_CHUNKS = 64


@njit(cache=True, parallel=True)
def _grouped(take, points, voxel_keys, voxel_start):
    """The taken rows of an index (``VoxelIndex``: points [N', 3], voxels' keys [V] and start
    [V + 1]) by ``take`` [N'] bool: (points [M, 3] float64 for the M taken, distinct keys [V'],
    start [V' + 1] with voxel v's points at start[v]:start[v + 1]).

    In parallel over chunks of the voxels, in two passes: each chunk counts its taken rows and
    the voxels holding some, then writes them at its offsets. (Sequential, with a key per
    Gaussian read, it took 13-15 ms of a 0.9M-point query on a 5M map.)"""
    n = voxel_keys.shape[0]
    chunks = max(1, min(GROUP_CHUNKS, n))
    size = (n + chunks - 1) // chunks
    taken = np.zeros(chunks + 1, np.int64)
    voxels = np.zeros(chunks + 1, np.int64)
    for c in prange(chunks):
        for v in range(c * size, min(n, (c + 1) * size)):
            here = 0
            for i in range(voxel_start[v], voxel_start[v + 1]):
                here += take[i]
            taken[c + 1] += here
            voxels[c + 1] += here > 0
    taken = np.cumsum(taken)
    voxels = np.cumsum(voxels)
    out = np.empty((taken[chunks], 3))
    distinct = np.empty(voxels[chunks], np.int64)
    start = np.empty(voxels[chunks] + 1, np.int64)
    start[voxels[chunks]] = taken[chunks]
    for c in prange(chunks):
        r, w = taken[c], voxels[c]
        for v in range(c * size, min(n, (c + 1) * size)):
            first = r
            for i in range(voxel_start[v], voxel_start[v + 1]):
                if take[i]:
                    out[r, 0], out[r, 1], out[r, 2] = points[i, 0], points[i, 1], points[i, 2]
                    r += 1
            if r > first:
                distinct[w], start[w] = voxel_keys[v], first
                w += 1
    return out, distinct, start


def _floats(row: np.ndarray) -> tuple[float, float, float]:
    return (float(row[0]), float(row[1]), float(row[2]))


def _voxelise(points: np.ndarray, eps: float):
    """(the points sorted by voxel [M, 3], distinct voxel keys [V] int64 ascending, start [V + 1]
    with voxel v's points at start[v]:start[v + 1], dims [3], the grid's origin lowest [3]).

    A key is the voxel's (i, j, k) + 1 in mixed radix ``dims``, so key order is (i, j, k) order;
    the one-voxel margin on each side means key + offset of a neighbour never wraps into
    another row.
    """
    lowest, highest = _bounds(points)  # numpy's min(0) on [M, 3] is ten times slower
    dims = np.floor((highest - lowest) / eps).astype(np.int64) + 3  # floor is monotonic
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        raise ValueError(
            f"eps={eps!r} m is too small for the selection's extent {np.ptp(points, 0)} m: too many voxels for int64 "
            "keys"
        )
    point_keys = _voxel_keys(points, lowest, eps, dims)
    order = np.argsort(point_keys)
    point_keys = point_keys[order]
    new = np.ones(len(point_keys), bool)
    np.not_equal(point_keys[1:], point_keys[:-1], out=new[1:])
    start = np.append(np.flatnonzero(new), len(point_keys))
    return np.take(points, order, axis=0), point_keys[new], start, dims, lowest


@njit(cache=True)
def _bounds(points):
    """(lowest [3], highest [3]) coordinates of points [M >= 1, 3]."""
    low = points[0].copy()
    high = points[0].copy()
    for p in range(1, points.shape[0]):
        for d in range(3):
            low[d] = min(low[d], points[p, d])
            high[d] = max(high[d], points[p, d])
    return low, high


@njit(cache=True)
def _voxel_keys(points, lowest, eps, dims):
    """[M] int64 key of each point's voxel (i, j, k) = floor((p - lowest) / eps), plus one."""
    keys = np.empty(points.shape[0], np.int64)
    for p in range(points.shape[0]):
        i = np.int64(np.floor((points[p, 0] - lowest[0]) / eps)) + 1
        j = np.int64(np.floor((points[p, 1] - lowest[1]) / eps)) + 1
        k = np.int64(np.floor((points[p, 2] - lowest[2]) / eps)) + 1
        keys[p] = (i * dims[1] + j) * dims[2] + k
    return keys


def _touching_pairs(keys: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of occupied voxels that touch, once: two [E] int64 voxel index arrays (for
    each of the 13 half-neighbour offsets in turn, by the first voxel)."""
    offsets = (_HALF_NEIGHBOURS[:, 0] * dims[1] + _HALF_NEIGHBOURS[:, 1]) * dims[2] + _HALF_NEIGHBOURS[:, 2]
    return _pairs_at(keys, offsets)


@njit(cache=True)
def _pairs_at(keys, offsets):
    """(first, second): every (v, w) with keys[w] == keys[v] + offset, for each offset in turn;
    keys ascending, so one merge walk per offset (13 binary searches per voxel took 12-14 ms for
    the 30k voxels of a 600k-point selection; this, 5 ms)."""
    n = keys.shape[0]
    first = np.empty(n * offsets.shape[0], np.int64)
    second = np.empty(n * offsets.shape[0], np.int64)
    m = 0
    for o in range(offsets.shape[0]):
        w = 0
        for v in range(n):
            wanted = keys[v] + offsets[o]
            while w < n and keys[w] < wanted:
                w += 1
            if w == n:
                break
            if keys[w] == wanted:
                first[m], second[m] = v, w
                m += 1
    return first[:m].copy(), second[:m].copy()


@njit(cache=True)
def _root(parent: np.ndarray, v: int) -> int:
    while parent[v] != v:
        parent[v] = parent[parent[v]]  # path halving
        v = parent[v]
    return v


@njit(cache=True)
def _neighbourhoods(n, first, second):
    """Each voxel itself, then the occupied voxels touching it, as CSR lists: voxel v's are
    around[begin[v]:begin[v + 1]]."""
    degree = np.ones(n, np.int64)
    for e in range(first.shape[0]):
        degree[first[e]] += 1
        degree[second[e]] += 1
    begin = np.zeros(n + 1, np.int64)
    begin[1:] = np.cumsum(degree)
    fill = begin[:-1].copy()
    around = np.empty(begin[n], np.int64)
    for v in range(n):
        around[fill[v]] = v
        fill[v] += 1
    for e in range(first.shape[0]):
        a, b = first[e], second[e]
        around[fill[a]] = b
        fill[a] += 1
        around[fill[b]] = a
        fill[b] += 1
    return begin, around


@njit(cache=True)
def _box(points, lo, hi):
    """(low [3], high [3]) of points[lo:hi]; inverted when empty."""
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for p in range(lo, hi):
        for d in range(3):
            low[d] = min(low[d], points[p, d])
            high[d] = max(high[d], points[p, d])
    return low, high


@njit(cache=True, parallel=True)
def _cores_first(points, start, core):
    """([V] core points per voxel, low [V, 3], high [V, 3]: the box of each voxel's core points,
    inverted when it has none); reorders each voxel's points (and ``core``) in place so that its
    core points come first. The boxes are made while the voxel's points are in cache."""
    n = start.shape[0] - 1
    cores = np.zeros(n, np.int64)
    low = np.empty((n, 3))
    high = np.empty((n, 3))
    for v in prange(n):
        for p in range(start[v], start[v + 1]):
            if core[p]:
                q = start[v] + cores[v]
                for d in range(3):
                    points[p, d], points[q, d] = points[q, d], points[p, d]
                core[p], core[q] = core[q], core[p]
                cores[v] += 1
        low[v], high[v] = _box(points, start[v], start[v] + cores[v])
    return cores, low, high


@njit(cache=True)
def _count_near(points, p, lo, hi, low, high, reach2, enough) -> int:
    """How many of points[lo:hi] (their box: low, high) lie within sqrt(reach2) of point p,
    counting up to ``enough``."""
    gap2 = 0.0
    for d in range(3):
        g = max(low[d] - points[p, d], 0.0, points[p, d] - high[d])
        gap2 += g * g
    found = 0
    if gap2 > reach2:  # most far voxels end here
        return found
    x, y, z = points[p, 0], points[p, 1], points[p, 2]
    for q in range(lo, hi):
        dx, dy, dz = x - points[q, 0], y - points[q, 1], z - points[q, 2]
        if dx * dx + dy * dy + dz * dz <= reach2:
            found += 1
            if found >= enough:
                break
    return found


@njit(cache=True, parallel=True)
def _core(points, start, begin, around, reach2, min_points, lowest, eps):
    """[M] bool: DBSCAN's core test, at least min_points points (itself included) within eps,
    counted over the point's own and touching voxels (its whole eps-ball).

    Shortcut, exact: split a voxel into its eight half-side cells and take each cell's box (of
    its points); when every corner of a cell's box is within eps of a point, so is every point of
    that cell, and the counts of such cells add up without a distance each. A point's own cell
    always qualifies (its diagonal is sqrt(3)/2 eps < eps); on the flat lawns and roads of a
    survey map a point's own cell and the two beside it usually do, and hold min_points (96 %
    of the points of a 0.9M-point "lawn" query, where the own cell alone decided a third and
    the core test was half of that query's time). The other points count distances, in a
    second pass that prunes far voxels by their boxes (made in the first)."""
    core = np.zeros(points.shape[0], np.bool_)
    n = start.shape[0] - 1
    low = np.empty((n, 3))
    high = np.empty((n, 3))
    runs = (n + VOXEL_RUN - 1) // VOXEL_RUN
    # voxels are independent in each pass: in parallel, by runs of VOXEL_RUN voxels
    for run in prange(runs):
        cell = np.zeros(8, np.int64)
        near_cell = np.zeros(8, np.int64)
        box = np.empty((8, 6))
        for v in range(run * VOXEL_RUN, min(n, (run + 1) * VOXEL_RUN)):
            low[v], high[v] = _box(points, start[v], start[v + 1])
            _whole_cells(points, start, begin, around, reach2, min_points, lowest, eps, v, cell, near_cell, box, core)
    for run in prange(runs):
        for v in range(run * VOXEL_RUN, min(n, (run + 1) * VOXEL_RUN)):
            _core_by_distances(points, start, begin, around, low, high, reach2, min_points, v, core)
    return core


@njit(cache=True)
def _whole_cells(points, start, begin, around, reach2, min_points, lowest, eps, v, cell, near_cell, box, core):
    """``_core``'s shortcut for voxel v's points (scratch arrays: cell [8] counts, near_cell [8]
    counts within eps of a whole cell, box [8, 6] boxes, low then high)."""
    if start[v + 1] - start[v] < min_points or _block(start, begin, around, v) < min_points:
        return  # the shortcut counts this voxel's points only; the block: no point can be core
    half = 0.5 * eps
    # the voxel's corner: its points share floor((p - lowest) / eps) (``_voxel_keys``)
    corner = np.floor((points[start[v]] - lowest) / eps) * eps + lowest
    cell[:] = 0
    box[:, :3] = np.inf
    box[:, 3:] = -np.inf
    for p in range(start[v], start[v + 1]):
        c = _half_cell(points, p, corner, half)
        cell[c] += 1
        for d in range(3):
            box[c, d] = min(box[c, d], points[p, d])
            box[c, 3 + d] = max(box[c, 3 + d], points[p, d])
    for a in range(8):  # whole cells first: every point of cell a is within eps of cell b's
        near_cell[a] = 0
        for b in range(8):
            if cell[a] > 0 and cell[b] > 0 and _farthest2_boxes(box, a, b) <= reach2:
                near_cell[a] += cell[b]
    for p in range(start[v], start[v + 1]):
        c = _half_cell(points, p, corner, half)
        if near_cell[c] >= min_points:
            core[p] = True
            continue
        near = 0  # then the point itself against each cell
        for b in range(8):
            if cell[b] > 0 and _farthest2(points, p, box, b) <= reach2:
                near += cell[b]
        core[p] = near >= min_points


@njit(cache=True)
def _block(start, begin, around, v) -> int:
    """Points in voxel v and the occupied voxels touching it: all that can lie within eps."""
    block = 0
    for i in range(begin[v], begin[v + 1]):
        block += start[around[i] + 1] - start[around[i]]
    return block


@njit(cache=True)
def _core_by_distances(points, start, begin, around, low, high, reach2, min_points, v, core):
    """``_core``'s test by distances for voxel v's points that the shortcut left undecided."""
    if _block(start, begin, around, v) < min_points:
        return  # no point here can have min_points within eps
    for p in range(start[v], start[v + 1]):
        if core[p]:
            continue
        found = 0
        for i in range(begin[v], begin[v + 1]):  # its own voxel first: the likeliest
            w = around[i]
            found += _count_near(points, p, start[w], start[w + 1], low[w], high[w], reach2, min_points - found)
            if found >= min_points:
                core[p] = True
                break


@njit(cache=True)
def _farthest2(points, p, box, c) -> float:
    """Squared distance from point p to the farthest corner of box[c] ([6]: low, high), computed
    as ``_count_near`` computes a point's: rounding is monotonic, so no point of the box comes
    out farther than this bound."""
    x, y, z = points[p, 0], points[p, 1], points[p, 2]
    dx = max(x - box[c, 0], box[c, 3] - x)
    dy = max(y - box[c, 1], box[c, 4] - y)
    dz = max(z - box[c, 2], box[c, 5] - z)
    return dx * dx + dy * dy + dz * dz


@njit(cache=True)
def _farthest2_boxes(box, a, b) -> float:
    """Squared distance between the farthest corners of box[a] and box[b] ([6]: low, high), an
    upper bound of any point of one to any point of the other as ``_count_near`` computes it
    (per axis p - q <= high_a - low_b exactly, and rounding is monotonic)."""
    dx = max(box[a, 3] - box[b, 0], box[b, 3] - box[a, 0])
    dy = max(box[a, 4] - box[b, 1], box[b, 4] - box[a, 1])
    dz = max(box[a, 5] - box[b, 2], box[b, 5] - box[a, 2])
    return dx * dx + dy * dy + dz * dz


@njit(cache=True)
def _half_cell(points, p, corner, half) -> int:
    """Which of its voxel's eight half-side cells (0..7) a point lies in; a point on the far
    face (rounding) counts in the outer cell, so two points of one cell are never more than
    sqrt(3) * half apart."""
    cell = 0
    for d in range(3):
        if points[p, d] - corner[d] >= half:
            cell |= 1 << d
    return cell


@njit(cache=True)
def _cluster_points(points, start, first, second, eps, min_points, lowest):
    """[M] int64 cluster of each point, named by its cluster's lowest voxel index; -1 for noise.

    points [M, 3] sorted by voxel, voxel v's at start[v]:start[v + 1]; this reorders each
    voxel's points in place so that its core points come first.
    """
    n = start.shape[0] - 1
    reach2 = eps * eps
    begin, around = _neighbourhoods(n, first, second)
    core = _core(points, start, begin, around, reach2, min_points, lowest, eps)
    # voxel v's core points: points[start[v]:start[v] + cores[v]], their box low[v], high[v]
    cores, low, high = _cores_first(points, start, core)

    parent = np.arange(n)
    for e in range(first.shape[0]):
        a, b = first[e], second[e]
        if cores[a] == 0 or cores[b] == 0:
            continue
        ra, rb = _root(parent, a), _root(parent, b)
        if ra == rb:
            continue  # already linked some other way: no need to look at points
        for p in range(start[a], start[a] + cores[a]):
            if _count_near(points, p, start[b], start[b] + cores[b], low[b], high[b], reach2, 1):
                # the lower index becomes the root, so a cluster's root is its lowest voxel
                if ra < rb:
                    parent[rb] = ra
                else:
                    parent[ra] = rb
                break
    root = np.empty(n, np.int64)
    for v in range(n):
        root[v] = _root(parent, v)
    return _labels(points, start, begin, around, cores, low, high, reach2, root)


@njit(cache=True, parallel=True)
def _labels(points, start, begin, around, cores, low, high, reach2, root):
    """[M] int64 cluster of each point (``_cluster_points``), given each voxel's cluster ``root``
    [V]: core points take their voxel's; a border point, of the voxels with a core point within
    eps of it, the one with the most core points (ties: the lowest index); -1 for noise."""
    n = start.shape[0] - 1
    cluster = np.full(points.shape[0], -1, np.int64)
    for v in prange(n):
        if cores[v] > 0:
            cluster[start[v] : start[v] + cores[v]] = root[v]
        for p in range(start[v] + cores[v], start[v + 1]):
            best = -1
            for i in range(begin[v], begin[v + 1]):
                w = around[i]
                if cores[w] == 0:
                    continue
                if best >= 0 and (cores[w] < cores[best] or (cores[w] == cores[best] and w > best)):
                    continue
                if _count_near(points, p, start[w], start[w] + cores[w], low[w], high[w], reach2, 1):
                    best = w
            if best >= 0:
                cluster[p] = root[best]
    return cluster


@njit(cache=True, parallel=True)
def _cluster_stats(points: np.ndarray, cluster_of: np.ndarray, n: int, parts: int):
    """Per cluster label 0..n-1: (point count [n], min [n, 3], max [n, 3], sum [n, 3]); -1 skipped.

    In parallel: ``parts`` shares of the points (one per thread) into their own [n] sums, then
    added up in order (the sums' rounding depends on ``parts``, not on the timing)."""
    parts = max(1, min(parts, points.shape[0]))
    size = (points.shape[0] + parts - 1) // parts
    counts = np.zeros((parts, n), np.int64)
    lows = np.full((parts, n, 3), np.inf)
    highs = np.full((parts, n, 3), -np.inf)
    totals = np.zeros((parts, n, 3))
    for part in prange(parts):
        for p in range(part * size, min(points.shape[0], (part + 1) * size)):
            c = cluster_of[p]
            if c < 0:
                continue
            counts[part, c] += 1
            for d in range(3):
                x = points[p, d]
                lows[part, c, d] = min(lows[part, c, d], x)
                highs[part, c, d] = max(highs[part, c, d], x)
                totals[part, c, d] += x
    count = counts[0].copy()
    low, high, total = lows[0].copy(), highs[0].copy(), totals[0].copy()
    for part in range(1, parts):
        count += counts[part]
        low = np.minimum(low, lows[part])
        high = np.maximum(high, highs[part])
        total += totals[part]
    return count, low, high, total
