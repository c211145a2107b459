"""The slow, obviously-correct rasterizer: the oracle of the fast one. Pure numpy, float64.

Same contract as ``rasterize.rasterize``. It projects every Gaussian with plain matrix
algebra, sorts all of them by depth, and then, for every pixel separately, walks the whole
sorted list: a Gaussian counts at a pixel when the pixel's tile lies in the Gaussian's tile
rectangle (gsplat's rule: the tiles of its 3-sigma square) and its box where alpha >= alpha_min
is possible reaches that tile, and it contributes alpha * T unless alpha < alpha_min; the walk
stops before the transmittance would fall to <= transmittance_min. The pixel's Top-K is a
stable sort of all its contributions by weight. Use it only on tiny scenes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..scene import Camera, Gaussians
from ..scene.rotations import quat_to_rotmat
from .config import RasterConfig
from .sh import C0, C1, C2, C3


def _sh_colors(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """sh [N, n, 3], dirs [N, 3] unit -> [N, 3] colours (max(SH + 0.5, 0))."""
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    n = sh.shape[1]
    out = C0 * sh[:, 0]
    if n >= 4:
        out = out - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3]
    if n >= 9:
        xx, yy, zz = x * x, y * y, z * z
        out = out + C2[0] * x * y * sh[:, 4] + C2[1] * y * z * sh[:, 5]
        out = out + C2[2] * (2 * zz - xx - yy) * sh[:, 6] + C2[3] * x * z * sh[:, 7] + C2[4] * (xx - yy) * sh[:, 8]
    if n >= 16:
        out = out + C3[0] * y * (3 * xx - yy) * sh[:, 9] + C3[1] * x * y * z * sh[:, 10]
        out = out + C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
        out = out + C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + C3[5] * z * (xx - yy) * sh[:, 14]
        out = out + C3[6] * x * (xx - 3 * yy) * sh[:, 15]
    return np.maximum(out + 0.5, 0.0)


def project_reference(gaussians: Gaussians, camera: Camera, config: RasterConfig) -> dict:
    """Per-Gaussian screen quantities; ``valid`` marks the ones that may be rasterized."""
    n = len(gaussians)
    means = gaussians.means.astype(np.float64)
    with np.errstate(all="ignore"):
        finite = np.isfinite(means).all(1) & np.isfinite(gaussians.quats).all(1)
        finite &= np.isfinite(gaussians.log_scales).all(1) & np.isfinite(gaussians.opacity_logits)
        finite &= np.linalg.norm(gaussians.quats.astype(np.float64), axis=1) > 0
        view = camera.camera_from_world
        cam = means @ view[:3, :3].T + view[:3, 3]  # [N, 3]
        opacity = 1.0 / (1.0 + np.exp(-gaussians.opacity_logits.astype(np.float64)))
        rot = quat_to_rotmat(np.where(finite[:, None], gaussians.quats, [1.0, 0, 0, 0]))
        scale = np.exp(gaussians.log_scales.astype(np.float64))
        cov3 = rot @ (scale[:, :, None] ** 2 * np.transpose(rot, (0, 2, 1)))  # R S^2 R^T
        cov_cam = view[:3, :3] @ cov3 @ view[:3, :3].T
        fx, fy, cx, cy, w, h = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
        z = cam[:, 2]
        tx = z * np.clip(cam[:, 0] / z, -(cx / fx + 0.15 * w / fx), (w - cx) / fx + 0.15 * w / fx)
        ty = z * np.clip(cam[:, 1] / z, -(cy / fy + 0.15 * h / fy), (h - cy) / fy + 0.15 * h / fy)
        jac = np.zeros((n, 2, 3))
        jac[:, 0, 0], jac[:, 0, 2] = fx / z, -fx * tx / z**2
        jac[:, 1, 1], jac[:, 1, 2] = fy / z, -fy * ty / z**2
        cov2 = jac @ cov_cam @ np.transpose(jac, (0, 2, 1)) + config.eps2d * np.eye(2)
        det = np.linalg.det(cov2)
        conic = np.linalg.inv(np.where((det > 0)[:, None, None], cov2, np.eye(2)))
        half = 0.5 * (cov2[:, 0, 0] + cov2[:, 1, 1])
        radius = np.ceil(config.radius_sigmas * np.sqrt(half + np.sqrt(np.maximum(0.01, half**2 - det))))
        mean2d = np.stack([fx * cam[:, 0] / z + cx, fy * cam[:, 1] / z + cy], 1)
        dirs = means - camera.center
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        colors = _sh_colors(gaussians.sh.astype(np.float64), dirs)
        t = config.tile_size
        tiles_x, tiles_y = math.ceil(w / t), math.ceil(h / t)
        rect = np.stack(
            [
                np.clip(np.floor((mean2d[:, 0] - radius) / t), 0, tiles_x),
                np.clip(np.floor((mean2d[:, 1] - radius) / t), 0, tiles_y),
                np.clip(np.ceil((mean2d[:, 0] + radius) / t), 0, tiles_x),
                np.clip(np.ceil((mean2d[:, 1] + radius) / t), 0, tiles_y),
            ],
            1,
        )
        valid = finite & (z > config.near_plane) & (z < config.far_plane) & (det > 0)
        valid &= np.isfinite(colors).all(1)
        valid &= (mean2d[:, 0] + radius > 0) & (mean2d[:, 0] - radius < w)
        valid &= (mean2d[:, 1] + radius > 0) & (mean2d[:, 1] - radius < h)
        valid &= (rect[:, 0] < rect[:, 2]) & (rect[:, 1] < rect[:, 3])
        # the tiles a Gaussian is listed in: those of rect that its alpha >= alpha_min box reaches
        # (pixel x is in the box when |x + 0.5 - mx| <= extent * 1.001 + 0.01; one pixel wider)
        sigma_cut = np.log(np.maximum(opacity, 1e-30) / config.alpha_min)
        extent = np.sqrt(2.0 * np.maximum(sigma_cut, 0.0)[:, None] * cov2[:, [0, 1], [0, 1]]) * 1.001 + 0.01
        first = np.ceil(mean2d - extent - 0.5) - 1  # pixel
        last = np.floor(mean2d + extent - 0.5) + 2  # pixel, end exclusive
        low, high = np.maximum(rect[:, :2], np.floor(first / t)), np.minimum(rect[:, 2:], np.ceil(last / t))
        tiles = np.concatenate([low, high], 1)
        tiles[sigma_cut <= 0] = 0
    return dict(valid=valid, mean2d=mean2d, conic=conic, depth=z, opacity=opacity, color=colors, rect=rect, tiles=tiles)


def rasterize_reference(
    gaussians: Gaussians,
    camera: Camera,
    config: RasterConfig | None = None,
    features: np.ndarray | None = None,  # [N, D]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> dict[str, Any]:
    """Returns rgb, alpha, depth, features (if given), topk_ids, topk_weights as in RenderResult,
    and tile_pairs (RenderResult.n_tile_pairs)."""
    config = config or RasterConfig()
    proj = project_reference(gaussians, camera, config)
    order = np.flatnonzero(proj["valid"])
    order = order[np.argsort(proj["depth"][order], kind="stable")]
    h, w, t, kmax = camera.height, camera.width, config.tile_size, config.topk_max
    d = 0 if features is None else features.shape[1]
    rows = np.zeros((len(gaussians), 0)) if features is None else features  # [N, D], D = 0 without features
    out: dict[str, Any] = {
        "rgb": np.zeros((h, w, 3)),
        "alpha": np.zeros((h, w)),
        "depth": np.zeros((h, w)),
        "features": np.zeros((h, w, d)),
        "topk_ids": np.full((h, w, kmax), -1, np.int64),
        "topk_weights": np.zeros((h, w, kmax)),
        "tile_pairs": 0,  # Gaussians tested, summed over pixels (a per-pixel tile-list loop's work)
    }
    for y in range(h):
        for x in range(w):
            trans, contributions = 1.0, []  # (weight, gaussian)
            rgb, depth, feat = np.zeros(3), 0.0, np.zeros(d)
            for g in order:
                x0, y0, x1, y1 = proj["tiles"][g]
                if not (x0 <= x // t < x1 and y0 <= y // t < y1):
                    continue
                # the fast path culls Gaussians that can never reach alpha_min before binning
                out["tile_pairs"] += proj["opacity"][g] >= config.alpha_min
                dx, dy = proj["mean2d"][g] - (x + 0.5, y + 0.5)
                a, b, c = proj["conic"][g][0, 0], proj["conic"][g][0, 1], proj["conic"][g][1, 1]
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                alpha = min(config.alpha_max, proj["opacity"][g] * math.exp(-sigma))
                if sigma < 0 or alpha < config.alpha_min:
                    continue
                if trans * (1.0 - alpha) <= config.transmittance_min:
                    break
                weight = alpha * trans
                rgb += weight * proj["color"][g]
                depth += weight * proj["depth"][g]
                if d:
                    feat += weight * rows[g]
                contributions.append((weight, g))
                trans *= 1.0 - alpha
            total = 1.0 - trans
            out["alpha"][y, x] = total
            out["rgb"][y, x] = rgb + trans * np.asarray(background)
            out["depth"][y, x] = depth / total if total > 1e-10 else 0.0
            out["features"][y, x] = feat / (total + config.feature_eps)
            ranked = sorted(contributions, key=lambda item: -item[0])  # stable: nearer first on ties
            weights = np.array([wt for wt, _ in ranked])
            covered = np.flatnonzero(np.cumsum(weights) >= config.topk_coverage * total)
            keep = covered[0] + 1 if len(covered) else len(ranked)
            keep = min(max(keep, config.topk_min), config.topk_max, len(ranked))
            for k in range(keep):
                out["topk_weights"][y, x, k], out["topk_ids"][y, x, k] = ranked[k]
    if features is None:
        del out["features"]
    return out
