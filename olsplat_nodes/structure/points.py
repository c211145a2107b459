"""The 3D branch's point set: reliable Gaussians, voxel-downsampled (paper: "3D structural
feature branch", o_i > tau_o, then voxel downsampling).

Each point is the mean of the kept Gaussian centres in its voxel (open3d's voxel
downsampling) and remembers its source Gaussian: the most opaque one of the voxel. Units are
the map's (metres for the simulator and geo-registered maps; arbitrary for a raw COLMAP map,
which is why ``voxel`` is usually given relative to the map, see ``auto_voxel``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import OlsplatInputError
from ..scene import Gaussians


@dataclass
class StructuralPoints:
    positions: np.ndarray  # [P, 3] float64 world positions (voxel means)
    opacity: np.ndarray  # [P] float32 opacity (0..1) of the source Gaussian
    source: np.ndarray  # [P] int64 index of the source Gaussian in the map
    voxel: float  # voxel side, map units

    def __len__(self) -> int:
        return len(self.positions)


def auto_voxel(means: np.ndarray, target_points: int = 150_000) -> float:
    """A voxel side giving about ``target_points`` on a roughly 2.5D (terrain-like) map."""
    lo, hi = np.percentile(means, [1, 99], axis=0)
    extent = np.sort(hi - lo)[::-1]
    area = max(extent[0] * extent[1], 1e-12)  # the two largest extents: the ground footprint
    return float(np.sqrt(area / target_points))


def structural_points(gaussians: Gaussians, tau_o: float = 0.1, voxel: float | None = None) -> StructuralPoints:
    """Gaussians with opacity > tau_o, one point per occupied voxel of side ``voxel`` (auto if None)."""
    import open3d as o3d

    opacity = 1.0 / (1.0 + np.exp(-gaussians.opacity_logits.astype(np.float64)))
    keep = np.flatnonzero((opacity > tau_o) & np.isfinite(gaussians.means).all(1))
    if len(keep) == 0:
        raise OlsplatInputError(
            f"no Gaussian has opacity above tau_o = {tau_o} (of {len(gaussians):,}): the 3D branch has nothing to "
            "work on"
        )
    means = gaussians.means[keep].astype(np.float64)
    voxel = auto_voxel(means) if voxel is None else float(voxel)
    if not voxel > 0:
        raise OlsplatInputError(f"the voxel size must be positive, got {voxel}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(means))
    lo, hi = means.min(0) - voxel, means.max(0) + voxel
    down, _, members = cloud.voxel_down_sample_and_trace(voxel, lo, hi, False)
    source = np.empty(len(members), np.int64)
    for p, traced in enumerate(members):  # the most opaque Gaussian of each voxel
        group = np.asarray(traced)
        source[p] = keep[group[np.argmax(opacity[keep[group]])]]
    return StructuralPoints(np.asarray(down.points), opacity[source].astype(np.float32), source, voxel)
