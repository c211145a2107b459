"""The prior map as a browser draws it: a decimated set of splats, and their colours.

A browser draws a few hundred thousand splats smoothly; a survey map has millions. We keep the
``limit`` Gaussians that cover the most of a view: opacity times the area of the two largest
axes (a large opaque roof splat before a faint speck), ties by index, so the choice is the
same every time and does not depend on the camera. Coordinates stay the map's (world metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..raster.sh import C0
from ..scene import Gaussians
from ..scene.rotations import quat_to_rotmat


@dataclass
class BrowserSplats:
    """Splats for viser's ``add_gaussian_splats``, rows aligned with ``ids``."""

    ids: np.ndarray  # [M] int64 indices into the prior map, ascending
    centers: np.ndarray  # [M, 3] float32 world metres
    covariances: np.ndarray  # [M, 3, 3] float32, R S S^T R^T (world metres squared)
    rgbs: np.ndarray  # [M, 3] float32 in [0, 1]: the view-independent colour (SH degree 0)
    opacities: np.ndarray  # [M, 1] float32 in (0, 1)
    total: int  # Gaussians in the prior map

    @property
    def caption(self) -> str:
        """What the page says about the decimation."""
        if len(self.ids) == self.total:
            return f"all {self.total:,} Gaussians of the prior map drawn"
        return (
            f"{len(self.ids):,} of {self.total:,} Gaussians drawn "
            f"({100 * len(self.ids) / max(self.total, 1):.0f} %: the most opaque and largest)"
        )


def decimate(gaussians: Gaussians, limit: int) -> np.ndarray:
    """[min(N, limit)] ascending indices of the Gaussians a browser draws (see the module)."""
    n = len(gaussians)
    if limit >= n:
        return np.arange(n, dtype=np.int64)
    if limit <= 0:
        return np.zeros(0, np.int64)
    opacity = 1.0 / (1.0 + np.exp(-gaussians.opacity_logits.astype(np.float64)))
    scales = np.sort(gaussians.log_scales.astype(np.float64), axis=1)
    importance = opacity * np.exp(scales[:, 1] + scales[:, 2])  # opacity x area of the two largest axes
    # stable sort on -importance: equal importance keeps the lower index first
    keep = np.argsort(-importance, kind="stable")[:limit]
    return np.sort(keep).astype(np.int64)


def browser_splats(gaussians: Gaussians, limit: int) -> BrowserSplats:
    """The decimated prior map with covariances, SH-degree-0 colours and opacities."""
    ids = decimate(gaussians, limit)
    rotation = quat_to_rotmat(gaussians.quats[ids])  # [M, 3, 3] float64
    scale = np.exp(gaussians.log_scales[ids].astype(np.float64))  # [M, 3]
    rs = rotation * scale[:, None, :]  # R S
    covariances = rs @ np.swapaxes(rs, 1, 2)
    rgbs = np.clip(gaussians.sh[ids, 0, :] * C0 + 0.5, 0.0, 1.0)
    opacities = 1.0 / (1.0 + np.exp(-gaussians.opacity_logits[ids].astype(np.float64)))
    return BrowserSplats(
        ids,
        gaussians.means[ids].astype(np.float32),
        covariances.astype(np.float32),
        rgbs.astype(np.float32),
        opacities[:, None].astype(np.float32),
        len(gaussians),
    )


# A perceptual ramp for relevance (low: dark blue, high: yellow), sampled at 5 stops.
RAMP = np.array(
    [[0.05, 0.03, 0.35], [0.23, 0.32, 0.55], [0.13, 0.57, 0.55], [0.37, 0.79, 0.38], [0.99, 0.91, 0.14]], np.float32
)
UNOBSERVED = np.array([0.35, 0.35, 0.35], np.float32)


def ramp(values: np.ndarray) -> np.ndarray:
    """[M] values in [0, 1] -> [M, 3] colours on ``RAMP`` (linear between stops)."""
    t = np.clip(np.asarray(values, np.float32), 0.0, 1.0) * (len(RAMP) - 1)
    low = np.minimum(t.astype(np.int64), len(RAMP) - 2)
    frac = (t - low)[:, None]
    return RAMP[low] * (1.0 - frac) + RAMP[low + 1] * frac


def relevance_colours(margin: np.ndarray, observed: np.ndarray, span: float = 0.2) -> np.ndarray:
    """[M, 3] colours of splats by their relevance margin [M] (the query's cosine minus the best
    negative's): -span and below at the bottom of the ramp, +span and above at the top, 0 (a tie
    with the best negative) in the middle. Gaussians no view observed are grey."""
    colours = ramp((np.asarray(margin, np.float32) + span) / (2 * span))
    colours[~np.asarray(observed, bool)] = UNOBSERVED
    return colours.astype(np.float32)


def colour_bar_html(span: float = 0.2) -> str:
    """The page's colour bar for ``relevance_colours``, as HTML."""
    stops = ", ".join(f"rgb({int(r * 255)},{int(g * 255)},{int(b * 255)})" for r, g, b in RAMP)
    return (
        f'<div style="font-size:0.8em">relevance: query minus best negative (cosine)</div>'
        f'<div style="height:12px;background:linear-gradient(to right, {stops})"></div>'
        f'<div style="display:flex;justify-content:space-between;font-size:0.8em">'
        f"<span>-{span:g}</span><span>0 (tie)</span><span>+{span:g}</span></div>"
        f'<div style="font-size:0.8em">grey: never observed</div>'
    )
