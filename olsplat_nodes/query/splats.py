"""The prior map as a browser draws it: a decimated set of splats, their packing on the wire
(``SplatsReply``) and a query's relevance per splat (``QueryReply.splat_margin``).

A browser draws a few hundred thousand splats smoothly; a survey map has millions. We keep the
``limit`` Gaussians that cover the most of a view: opacity times the area of the two largest
axes (a large opaque roof splat before a faint speck), ties by index, so the choice is the
same every time and does not depend on the camera. Coordinates stay the map's (world metres).

Here, below the transport and the ground station, so that the query server (which decimates
and scores) and the page (which unpacks and colours, ``ground/colours.py``) share one
definition.
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


# (row, column) of the upper triangle of a 3x3 covariance, in the wire's order (xx, xy, xz, yy, yz, zz)
UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
MAX_SPLATS = 500_000  # what a browser draws smoothly; a SplatsReply is then at most 20 MB


def pack_splats(splats: BrowserSplats) -> dict[str, np.ndarray]:
    """The splats as the wire carries them (``SplatsReply``): centres float32 [M, 3], the
    covariances' upper triangles float32 [M, 6], colours uint8 [M, 3] and opacities uint8 [M]
    (40 bytes a splat; a colour's or an opacity's 1/255 steps are below what a screen shows)."""
    return {
        "centers": np.ascontiguousarray(splats.centers, np.float32),
        "covariances": np.ascontiguousarray(splats.covariances[:, UPPER[0], UPPER[1]], np.float32),
        "rgbs": np.round(np.clip(splats.rgbs, 0.0, 1.0) * 255.0).astype(np.uint8),
        "opacities": np.round(np.clip(splats.opacities[:, 0], 0.0, 1.0) * 255.0).astype(np.uint8),
    }


def unpack_splats(centers, covariances, rgbs, opacities, total: int) -> BrowserSplats:
    """``pack_splats``'s arrays back as ``BrowserSplats`` (``ids``: 0..M-1, the wire's order)."""
    m = len(centers)
    for name, array, shape in [
        ("covariances", covariances, (m, 6)),
        ("rgbs", rgbs, (m, 3)),
        ("opacities", opacities, (m,)),
    ]:
        if array is None or np.shape(array) != shape:
            raise ValueError(f"{name}: shape {np.shape(array)}, expected {shape} for {m} centres")
    full = np.zeros((m, 3, 3), np.float32)
    full[:, UPPER[0], UPPER[1]] = covariances
    full[:, UPPER[1], UPPER[0]] = covariances  # symmetric
    return BrowserSplats(
        np.arange(m, dtype=np.int64),
        np.array(centers, np.float32),
        full,
        np.asarray(rgbs, np.float32) / 255.0,
        (np.asarray(opacities, np.float32) / 255.0)[:, None],
        int(total),
    )


def relevance_margin(features, observed: np.ndarray, ids: np.ndarray, embeddings: np.ndarray) -> np.ndarray:
    """[M] float32 cos(query) - max cos(negatives) of the splats ``ids`` of the prior map, from a
    map's ``query.QueryFeatures``, its ``observed`` [N] bool and the L2-normalised text
    embeddings [1 + n, D] (the query first); NaN where no view observed the Gaussian."""
    embeddings = np.asarray(embeddings, np.float32).T
    if features.rows is None:  # a dense map: one row per Gaussian, zeros where unobserved
        # the splats' rows in blocks (float16 rows are widened to float32 block by block, and a
        # gather of all the D-wide rows at once would copy 150 MB for 300k splats at D = 128)
        cos = np.empty((len(ids), embeddings.shape[1]), np.float32)
        for start in range(0, len(ids), 16_384):
            block = ids[start : start + 16_384]
            cos[start : start + len(block)] = features.table[block].astype(np.float32) @ embeddings
    else:  # a codebook map: the K centres scored, then gathered through the splats' codes
        cos = features.table.astype(np.float32) @ embeddings
        cos = np.append(cos, np.zeros((1, cos.shape[1]), np.float32), 0)[features.rows[ids]]
    margin = (cos[:, 0] - cos[:, 1:].max(1)).astype(np.float32)
    margin[~np.asarray(observed, bool)[ids]] = np.nan
    return margin
