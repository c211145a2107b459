"""Frustum culling by cells: which Gaussians of a large map a camera's projection need look at.

A UAV view sees a small part of a survey map (730k of 5.2M Gaussians in a 1280x960 view of the
large preset), yet the projection kernel tested every Gaussian: the transform, two ``exp`` and
the screen test of each, most of a render's projection time. Here the map's Gaussians are
grouped once into world-axis cubes (``CellIndex``), and a camera keeps only the cubes whose
members could pass the kernel's own early screen test (``project._project_kernel``).

The test is the kernel's, bounded over a cube, so it culls nothing the kernel would keep:
- camera depth z is linear in the world point, so over the box of a cube's centres it lies
  between its values at the 8 corners; a cube wholly at z <= near or z >= far is culled;
- with every corner in front (z > near), u = fx x / z + cx is a ratio of linear functions with
  a positive denominator, so over the box it lies between its corner values (likewise v);
- the kernel keeps a Gaussian when u +/- bound reaches the image, with bound = radius_sigmas *
  sqrt(J^2 |W|^2 3 s_max^2 + 2 eps2d + 0.2) + 1 and J^2 <= (fx^2 (1 + Lx^2) + fy^2 (1 + Ly^2)) /
  z^2 (Lx, Ly: the kernel's clamp of x / z and y / z at 1.3x the field of view); over a cube
  that is at most its value at the cube's smallest z and largest member scale;
- a cube that straddles the near plane is kept.
A margin of 1 pixel covers rounding. ``tests/raster/test_cull.py`` holds renders with and without
the cull to be identical, and checks that every Gaussian the kernel keeps is a candidate.

The index is made at a map's first render (``cells_of``: one counting sort of the map, then 4
bytes per Gaussian) and kept while the map object lives; a map's arrays must not be changed in
place after that (olsplat never does: a map is read once and only read). Maps under
``CULL_MIN`` Gaussians are projected whole (the cull would save little).
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..scene import Camera, Gaussians
from .config import RasterConfig

CULL_MIN = 100_000  # Gaussians: smaller maps are projected whole
COLUMNS = 64  # the cubes' side: the map's larger horizontal extent / COLUMNS (at least MIN_CELL_M)
MIN_CELL_M = 1.0
MARGIN_PX = 1.0
MAX_CELLS = 1 << 24  # grid cells (empty ones included) at most: a counting sort's bins


@dataclass(frozen=True)
class CellIndex:
    """A map's Gaussians (those with finite centres and scales; the kernel culls the others)
    grouped by cubes of side ``cell_m`` metres: cube c holds order[start[c]:start[c + 1]]."""

    cell_m: float
    order: np.ndarray  # [N'] int32 Gaussians by cube
    start: np.ndarray  # [C + 1] int64
    low: np.ndarray  # [C, 3] float64 smallest member centre per axis, world metres
    high: np.ndarray  # [C, 3] float64 largest
    scale_max: np.ndarray  # [C] float64 largest member standard deviation exp(max log_scale), metres
    size: int  # N, the map's Gaussians

    @staticmethod
    def build(gaussians: Gaussians, cell_m: float | None = None) -> CellIndex:
        means, log_scales = gaussians.means, gaussians.log_scales
        # the grid spans the bulk of the map (0.1-99.9 % of an even sample of the centres): a
        # trainer's far floaters go to the border cubes, whose boxes hold them (any grouping is
        # exact, since each cube's box and scale are its members'), and do not stretch the cubes
        rows = np.arange(0, len(means), max(1, len(means) // 200_000))
        if not np.isfinite(means[rows]).all() or not np.isfinite(log_scales[rows]).all():
            rows = rows[np.isfinite(means[rows]).all(1) & np.isfinite(log_scales[rows]).all(1)]
            if len(rows) == 0:  # a sample of only non-finite rows: the grid from every finite one
                rows = np.flatnonzero(np.isfinite(means).all(1) & np.isfinite(log_scales).all(1))
        if len(rows) == 0:
            empty = np.zeros((0, 3))
            return CellIndex(1.0, np.zeros(0, np.int32), np.zeros(1, np.int64), empty, empty, np.zeros(0), len(means))
        lowest, highest = np.percentile(means[rows].astype(np.float64), [0.1, 99.9], axis=0)
        if cell_m is None:
            cell_m = max(MIN_CELL_M, float(max(highest[0] - lowest[0], highest[1] - lowest[1])) / COLUMNS)
        dims = np.floor((highest - lowest) / cell_m).astype(np.int64) + 1
        while float(np.prod(dims.astype(np.float64))) > MAX_CELLS:  # a tall bulk: coarser cubes
            cell_m *= 1.5
            dims = np.floor((highest - lowest) / cell_m).astype(np.int64) + 1
        order, start, low, high, scale_max = _by_cell(means, log_scales, lowest, float(cell_m), dims)
        return CellIndex(float(cell_m), order, start, low, high, scale_max, len(means))

    def __len__(self) -> int:
        return len(self.start) - 1

    def visible_cells(self, camera: Camera, config: RasterConfig) -> np.ndarray:
        """[C] bool: the cubes that may hold a Gaussian the projection keeps (module docstring)."""
        corners = np.stack(
            [np.where(np.array([i, j, k], bool), self.high, self.low) for i in (0, 1) for j in (0, 1) for k in (0, 1)],
            axis=1,
        )  # [C, 8, 3]
        view = camera.camera_from_world
        cam = corners @ view[:3, :3].T + view[:3, 3]  # [C, 8, 3]
        z = cam[..., 2]
        z_min, z_max = z.min(1), z.max(1)
        keep = (z_max > config.near_plane) & (z_min < config.far_plane)
        in_front = z_min > config.near_plane
        fx, fy, cx, cy, width, height = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx * cam[..., 0] / z + cx
            v = fy * cam[..., 1] / z + cy
        lim_x = max((width - cx) / fx, cx / fx) + 0.3 * (0.5 * width / fx)
        lim_y = max((height - cy) / fy, cy / fy) + 0.3 * (0.5 * height / fy)
        w_norm2 = float(np.linalg.norm(view[:3, :3], 2)) ** 2 * (1.0 + 1e-6)
        z_near = np.maximum(z_min, config.near_plane)
        jacobian2 = (fx * fx * (1.0 + lim_x * lim_x) + fy * fy * (1.0 + lim_y * lim_y)) / (z_near * z_near)
        bound = config.radius_sigmas * np.sqrt(jacobian2 * w_norm2 * 3.0 * self.scale_max**2 + 2.0 * config.eps2d + 0.2)
        bound = bound + 1.0 + MARGIN_PX
        on_screen = (
            (u.max(1) + bound > 0) & (u.min(1) - bound < width) & (v.max(1) + bound > 0) & (v.min(1) - bound < height)
        )
        return keep & (~in_front | on_screen)

    def candidates(self, camera: Camera, config: RasterConfig) -> np.ndarray:
        """[N] bool: the members of ``visible_cells``, the only Gaussians the projection of this
        camera can keep."""
        return _members(self.order, self.start, np.flatnonzero(self.visible_cells(camera, config)), self.size)


@njit(cache=True, nogil=True)
def _by_cell(means, log_scales, lowest, cell_m, dims):
    """A counting sort of the Gaussians with finite centres and scales by cube (i, j, k), each
    clamped to the grid, stable (map order within a cube): (order [N'] int32, start [C + 1] of
    the C non-empty cubes, and per cube low [C, 3], high [C, 3], scale_max [C] of its members,
    summed in map order: no gather)."""
    bins = dims[0] * dims[1] * dims[2]
    keys = np.full(means.shape[0], -1, np.int64)
    counts = np.zeros(bins + 1, np.int64)
    for g in range(means.shape[0]):
        finite = True
        for d in range(3):
            finite &= np.isfinite(means[g, d]) and np.isfinite(log_scales[g, d])
        if not finite:
            continue
        key = np.int64(0)
        for d in range(3):
            at = np.floor((np.float64(means[g, d]) - lowest[d]) / cell_m)
            key = key * dims[d] + np.int64(min(max(at, 0.0), dims[d] - 1.0))
        keys[g] = key
        counts[key + 1] += 1
    cube_of = np.full(bins, -1, np.int32)
    occupied = 0
    for b in range(bins):
        if counts[b + 1] > 0:
            cube_of[b] = occupied
            occupied += 1
        counts[b + 1] += counts[b]
    start = np.empty(occupied + 1, np.int64)
    for b in range(bins):
        if cube_of[b] >= 0:
            start[cube_of[b]] = counts[b]
    start[occupied] = counts[bins]
    order = np.empty(counts[bins], np.int32)
    low = np.full((occupied, 3), np.inf)
    high = np.full((occupied, 3), -np.inf)
    scale_max = np.zeros(occupied)
    for g in range(means.shape[0]):
        if keys[g] < 0:
            continue
        order[counts[keys[g]]] = g
        counts[keys[g]] += 1
        c = cube_of[keys[g]]
        largest = -np.inf
        for d in range(3):
            x = np.float64(means[g, d])
            low[c, d] = min(low[c, d], x)
            high[c, d] = max(high[c, d], x)
            largest = max(largest, np.float64(log_scales[g, d]))
        scale_max[c] = max(scale_max[c], np.exp(largest))
    return order, start, low, high, scale_max


@njit(cache=True, parallel=True, nogil=True)
def _members(order, start, cells, n):
    """[n] bool: True for the members of the listed cubes."""
    mask = np.zeros(n, np.bool_)
    for j in prange(cells.shape[0]):
        c = cells[j]
        for i in range(start[c], start[c + 1]):
            mask[order[i]] = True
    return mask


_INDEXES: dict[int, tuple[weakref.ref, CellIndex]] = {}  # id(map) -> (the map, its index); a few maps
_LOCK = threading.Lock()


def cells_of(gaussians: Gaussians) -> CellIndex | None:
    """The map's ``CellIndex``, made at the first call and kept while the map object lives (a
    process renders one or two maps: the prior map, a test's subset); None for a map under
    ``CULL_MIN`` Gaussians."""
    if len(gaussians) < CULL_MIN:
        return None
    key = id(gaussians)
    with _LOCK:
        held = _INDEXES.get(key)
        if held is not None and held[0]() is gaussians and held[1].size == len(gaussians):
            return held[1]
        for stale in [k for k, (ref, _) in _INDEXES.items() if ref() is None]:
            del _INDEXES[stale]
        index = CellIndex.build(gaussians)
        _INDEXES[key] = (weakref.ref(gaussians), index)
        return index
