"""Per-Gaussian projection to the image: EWA splatting with gsplat's "classic" conventions.

For each Gaussian: camera-space mean, 3D covariance R S S^T R^T, 2D covariance J W Σ W^T J^T
(J the perspective Jacobian at the mean, with the mean's x/z and y/z clamped to 1.3x the
field of view as gsplat does), plus ``eps2d`` on the diagonal; its inverse (the conic); a
screen radius of 3 sigma of the largest eigenvalue; the covered tile rectangle: the tiles of
the 3-sigma square (gsplat's rule) that the box where alpha >= alpha_min is possible reaches
(the others would evaluate nothing); opacity and the SH colour for the viewing direction.
Degenerate Gaussians (non-finite parameters, zero scale, behind the near plane, off-screen, too
transparent to ever reach alpha_min) get radius 0 and are never rasterized.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..scene import Camera, Gaussians
from .config import RasterConfig
from .cull import cells_of
from .sh import eval_sh

# Columns of the per-Gaussian record: one 64-byte cache line per Gaussian, so the compositing
# loop touches one line per Gaussian instead of one per array.
MX, MY, CA, CB, CC, OPACITY, CUT, EX, EY, RED, GREEN, BLUE, DEPTH = range(13)
RECORD = 16


@dataclass
class Projected:
    """Screen-space Gaussians: row j is Gaussian j of the input map, or with ``ids`` Gaussian
    ids[j] (a culled projection: only the cull's candidates have rows). ``records`` [M, RECORD]
    float32 (columns named above) is what the compositing kernels read; ``means2d`` and
    ``depths`` are column views of it. M = N without ``ids``."""

    records: np.ndarray  # [M, RECORD] float32; all zero for a culled Gaussian
    radii: np.ndarray  # [M] int32 screen radius in pixels; 0 = culled
    tile_rects: np.ndarray  # [M, 4] int32 (tx0, ty0, tx1, ty1), tiles tx0 <= tx < tx1, ty0 <= ty < ty1
    ids: np.ndarray | None = None  # [M] int64 ascending Gaussian of each row; None: row j is Gaussian j

    def aligned(self, n: int) -> Projected:
        """The same projection with a row per Gaussian of the n-Gaussian map (zero rows, radius
        0, for those without one here)."""
        if self.ids is None:
            return self
        out = Projected(np.zeros((n, RECORD), np.float32), np.zeros(n, np.int32), np.zeros((n, 4), np.int32))
        out.records[self.ids], out.radii[self.ids], out.tile_rects[self.ids] = self.records, self.radii, self.tile_rects
        return out

    @property
    def means2d(self) -> np.ndarray:  # [N, 2] pixel coordinates (u, v), pixel centres at +0.5
        return self.records[:, MX : MY + 1]

    @property
    def depths(self) -> np.ndarray:  # [N] camera z
        return self.records[:, DEPTH]


@njit(parallel=True, cache=True, nogil=True)
def _project_kernel(
    means, quats, log_scales, opacity_logits, sh, viewmat, fx, fy, cx, cy, campos,
    width, height, tile_size, eps2d, near, far, radius_sigmas, alpha_min, records, radii, tile_rects, w_norm2,
    active, ids, compact,
):  # fmt: skip
    """Row j of the outputs for Gaussian ids[j] (``compact``) or Gaussian j; ``active`` [N] bool
    (empty: all) skips the others."""
    n = ids.shape[0] if compact else means.shape[0]
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    for j in prange(n):
        radii[j] = 0
        i = np.int64(ids[j]) if compact else np.int64(j)
        if active.shape[0] > 0 and not active[i]:  # not drawn in this render
            continue
        finite = True
        for k in range(3):
            finite &= np.isfinite(means[i, k]) and np.isfinite(log_scales[i, k])
        for k in range(4):
            finite &= np.isfinite(quats[i, k])
        finite &= np.isfinite(opacity_logits[i])
        if not finite:
            continue
        # camera-space mean
        px = viewmat[0, 0] * means[i, 0] + viewmat[0, 1] * means[i, 1] + viewmat[0, 2] * means[i, 2] + viewmat[0, 3]
        py = viewmat[1, 0] * means[i, 0] + viewmat[1, 1] * means[i, 1] + viewmat[1, 2] * means[i, 2] + viewmat[1, 3]
        pz = viewmat[2, 0] * means[i, 0] + viewmat[2, 1] * means[i, 1] + viewmat[2, 2] * means[i, 2] + viewmat[2, 3]
        if not (pz > near and pz < far):
            continue
        opacity = 1.0 / (1.0 + math.exp(-float(opacity_logits[i])))
        if opacity < alpha_min:  # can never reach alpha_min anywhere
            continue
        # Off-screen early, before the covariance and the colour (most of a large map's
        # Gaussians are outside any one view): lambda_max <= trace(cov2d) <= |J|_F^2 |M|_F^2 +
        # 2 eps2d (+ 0.1 from the 0.01 floor below) bounds the radius from above, so a Gaussian
        # that fails the screen test with the bound fails it with its radius too (same output).
        # |M|_F^2 <= |W|_2^2 * 3 s_max^2 (w_norm2: the view rotation's squared spectral norm, 1).
        s_max = math.exp(float(max(log_scales[i, 0], log_scales[i, 1], log_scales[i, 2])))
        cx_clamped = min(lim_x_pos, max(-lim_x_neg, px / pz))
        cy_clamped = min(lim_y_pos, max(-lim_y_neg, py / pz))
        jacobian2 = (fx * fx * (1.0 + cx_clamped * cx_clamped) + fy * fy * (1.0 + cy_clamped * cy_clamped)) / (pz * pz)
        bound = radius_sigmas * math.sqrt(jacobian2 * w_norm2 * 3.0 * s_max * s_max + 2.0 * eps2d + 0.2) + 1.0
        u_early = fx * px / pz + cx
        v_early = fy * py / pz + cy
        if not (u_early + bound > 0 and u_early - bound < width and v_early + bound > 0 and v_early - bound < height):
            continue
        # world covariance M M^T with M = R(q) diag(s)
        qw, qx, qy, qz = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if qn == 0.0:
            continue
        qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        # camera-space M = W R(q) diag(s), kept in scalars: no allocation in this hot loop
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        s0, s1, s2 = (
            math.exp(float(log_scales[i, 0])),
            math.exp(float(log_scales[i, 1])),
            math.exp(float(log_scales[i, 2])),
        )
        m00 = (viewmat[0, 0] * r00 + viewmat[0, 1] * r10 + viewmat[0, 2] * r20) * s0
        m01 = (viewmat[0, 0] * r01 + viewmat[0, 1] * r11 + viewmat[0, 2] * r21) * s1
        m02 = (viewmat[0, 0] * r02 + viewmat[0, 1] * r12 + viewmat[0, 2] * r22) * s2
        m10 = (viewmat[1, 0] * r00 + viewmat[1, 1] * r10 + viewmat[1, 2] * r20) * s0
        m11 = (viewmat[1, 0] * r01 + viewmat[1, 1] * r11 + viewmat[1, 2] * r21) * s1
        m12 = (viewmat[1, 0] * r02 + viewmat[1, 1] * r12 + viewmat[1, 2] * r22) * s2
        m20 = (viewmat[2, 0] * r00 + viewmat[2, 1] * r10 + viewmat[2, 2] * r20) * s0
        m21 = (viewmat[2, 0] * r01 + viewmat[2, 1] * r11 + viewmat[2, 2] * r21) * s1
        m22 = (viewmat[2, 0] * r02 + viewmat[2, 1] * r12 + viewmat[2, 2] * r22) * s2
        # Jacobian rows at the clamped mean
        tx = pz * min(lim_x_pos, max(-lim_x_neg, px / pz))
        ty = pz * min(lim_y_pos, max(-lim_y_neg, py / pz))
        j00, j02 = fx / pz, -fx * tx / (pz * pz)
        j11, j12 = fy / pz, -fy * ty / (pz * pz)
        # T = J M (2x3); cov2d = T T^T
        t00, t01, t02 = j00 * m00 + j02 * m20, j00 * m01 + j02 * m21, j00 * m02 + j02 * m22
        t10, t11, t12 = j11 * m10 + j12 * m20, j11 * m11 + j12 * m21, j11 * m12 + j12 * m22
        cov_a = t00 * t00 + t01 * t01 + t02 * t02 + eps2d
        cov_b = t00 * t10 + t01 * t11 + t02 * t12
        cov_c = t10 * t10 + t11 * t11 + t12 * t12 + eps2d
        det = cov_a * cov_c - cov_b * cov_b
        if not det > 0.0:
            continue
        half = 0.5 * (cov_a + cov_c)
        lambda_max = half + math.sqrt(max(0.01, half * half - det))
        radius = math.ceil(radius_sigmas * math.sqrt(lambda_max))
        u = fx * px / pz + cx
        v = fy * py / pz + cy
        if not (u + radius > 0 and u - radius < width and v + radius > 0 and v - radius < height):
            continue
        tx0 = min(max(int(math.floor((u - radius) / tile_size)), 0), tiles_x)
        tx1 = min(max(int(math.ceil((u + radius) / tile_size)), 0), tiles_x)
        ty0 = min(max(int(math.floor((v - radius) / tile_size)), 0), tiles_y)
        ty1 = min(max(int(math.ceil((v + radius) / tile_size)), 0), tiles_y)
        if tx0 >= tx1 or ty0 >= ty1:
            continue
        # alpha >= alpha_min  <=>  d^T cov^-1 d <= 2 sigma_cut: an ellipse with this bounding box
        sigma_cut = math.log(opacity / alpha_min)
        extent_x = math.sqrt(2.0 * sigma_cut * cov_a)
        extent_y = math.sqrt(2.0 * sigma_cut * cov_c)
        # Only the tiles that box reaches are listed (the kernels evaluate a Gaussian only over
        # its box): 24 % fewer Gaussian-tile pairs on a near view of the large map, 14 % on a
        # far one, the same image. The box as the kernels take it, one pixel wider against the C
        # kernels' rounding.
        px0, px1, py0, py1 = pixel_box(u, v, extent_x, extent_y)
        tx0, tx1 = max(tx0, (px0 - 1) // tile_size), min(tx1, -(-(px1 + 1) // tile_size))
        ty0, ty1 = max(ty0, (py0 - 1) // tile_size), min(ty1, -(-(py1 + 1) // tile_size))
        if tx0 >= tx1 or ty0 >= ty1:  # no pixel centre in its box: on screen (radius), in no tile's list
            tx0 = tx1 = ty0 = ty1 = 0
        # SH colour
        dx, dy, dz = means[i, 0] - campos[0], means[i, 1] - campos[1], means[i, 2] - campos[2]
        dn = math.sqrt(dx * dx + dy * dy + dz * dz)
        dn = dn if dn > 0.0 else 1.0
        rec = records[j]
        color_ok = True
        for ch in range(3):
            acc = eval_sh(sh[i, :, ch], dx / dn, dy / dn, dz / dn)
            rec[RED + ch] = max(acc + 0.5, 0.0)
            color_ok &= np.isfinite(acc)
        if not color_ok:
            rec[RED], rec[GREEN], rec[BLUE] = 0.0, 0.0, 0.0
            continue
        rec[MX], rec[MY] = u, v
        rec[CA], rec[CB], rec[CC] = cov_c / det, -cov_b / det, cov_a / det
        rec[DEPTH] = pz
        rec[OPACITY] = opacity
        rec[EX], rec[EY] = extent_x, extent_y
        rec[CUT] = sigma_cut
        tile_rects[j, 0], tile_rects[j, 1], tile_rects[j, 2], tile_rects[j, 3] = tx0, ty0, tx1, ty1
        radii[j] = radius


@njit(cache=True, nogil=True)
def pixel_box(u, v, extent_x, extent_y):
    """(px0, px1, py0, py1): the image pixels [px0, px1) x [py0, py1) where a Gaussian with
    centre (u, v) and extents (EX, EY) may reach alpha >= alpha_min: pixel x (centre x + 0.5) is
    in when |x + 0.5 - u| <= extent, the extent widened by 0.1 % + 0.01 px (more than the 1e-3
    margin on the sigma cut moves the ellipse; the exact sigma test decides). In float32, as
    the record stores them: the binning (the tiles a Gaussian is listed in) and the numba
    compositing kernel take this box; the C kernels' ``pixel_box`` (native/tile_pass.h) is the
    same arithmetic."""
    mx, my = np.float32(u), np.float32(v)
    ex = np.float32(extent_x) * np.float32(1.001) + np.float32(0.01)
    ey = np.float32(extent_y) * np.float32(1.001) + np.float32(0.01)
    half = np.float32(0.5)
    px0 = int(math.ceil(mx - ex - half))
    px1 = int(math.floor(mx + ex - half)) + 1
    py0 = int(math.ceil(my - ey - half))
    py1 = int(math.floor(my + ey - half)) + 1
    return px0, px1, py0, py1


def project(
    gaussians: Gaussians,
    camera: Camera,
    config: RasterConfig,
    active: np.ndarray | None = None,
    cull: bool = True,
) -> Projected:
    """Project every Gaussian of the map into ``camera`` (see the module docstring); with
    ``active`` ([N] bool) only those where it is True, the others culled (radius 0). With
    ``cull`` a large map's Gaussians outside the view's cells are not looked at (``cull.py``)
    and the result has rows for the cull's candidates only (``Projected.ids``; ``aligned``
    gives the map-aligned arrays, equal to those without the cull): on a 5M-Gaussian map a
    near view's ~1M candidates write 64 MB of records instead of 330 MB of fresh pages."""
    n = len(gaussians)
    drawn = np.zeros(0, np.bool_) if active is None else np.ascontiguousarray(active, np.bool_)
    if len(drawn) not in (0, n):
        raise ValueError(f"active must be [N={n}] bool, got {drawn.shape}")
    cells = cells_of(gaussians) if cull else None
    ids = np.zeros(0, np.int64)
    if cells is not None:
        candidates = cells.candidates(camera, config)
        ids = np.flatnonzero(candidates if active is None else np.logical_and(candidates, drawn, out=candidates))
        drawn = np.zeros(0, np.bool_)  # the ids are the drawn ones
    m = n if cells is None else len(ids)
    out = Projected(
        records=np.zeros((m, RECORD), np.float32),
        radii=np.zeros(m, np.int32),
        tile_rects=np.zeros((m, 4), np.int32),
        ids=None if cells is None else ids,
    )
    _project_kernel(
        gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, gaussians.sh,
        camera.camera_from_world, camera.fx, camera.fy, camera.cx, camera.cy, camera.center,
        camera.width, camera.height, config.tile_size, config.eps2d, config.near_plane, config.far_plane,
        config.radius_sigmas, config.alpha_min, out.records, out.radii, out.tile_rects,
        float(np.linalg.norm(camera.camera_from_world[:3, :3], 2)) ** 2 * (1.0 + 1e-6), drawn,
        ids.astype(np.int64, copy=False), cells is not None,
    )  # fmt: skip
    return out
