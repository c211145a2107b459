"""The map a user would have: the truth degraded the way a real reconstruction is.

Real Gaussian-splatting maps are not the scene: Gaussians sit a little off the surface, have
the wrong size and opacity, some surfaces are missing, neighbours are merged into one blob,
floaters hang in the air, colours carry view-dependent residue, and the camera poses of
structure-from-motion are slightly wrong. Optimisation also leaves layers of large translucent
Gaussians over and around the surfaces (densification residue): a real trained splat
(``donut_fused.ply``) has 38 % of its Gaussians below opacity 0.5 and a median effective number
of contributors per pixel of ~7 (90th percentile ~13); without these layers our maps had 2 %
and ~5 (~9). With ``layered`` = 0.4 they come to ~30 % and the figures in sim/README.md.
``reconstruct`` applies all of that, keeps each surviving Gaussian's truth labels (floaters get
label -1), and shuffles the map so that nothing can be read from the order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from olsplat_nodes.scene import Camera, Gaussians
from olsplat_nodes.scene.rotations import quat_to_rotmat

from .labels import CATEGORY
from .scene import TruthScene


@dataclass(frozen=True)
class ReconstructionSpec:
    missing: float = 0.03  # fraction of Gaussians dropped
    merged: float = 0.04  # fraction merged into a neighbour
    floaters: float = 0.015  # floaters added, as a fraction of the map ...
    # ... but at most this many per m² of the town (the small preset's is 0.26): a denser map is not
    # a foggier one. A trainer prunes floaters that would show in its own training views; tied to
    # the count alone, the large preset (4.3x the small one's Gaussians per m²) had 1.1 per m²,
    # the top-weight Gaussian on most roof, tree and car pixels, fogging its training views
    # (docs/decisions.md, "Scale and the simulator"). inf: the fraction alone
    floaters_max_per_m2: float = 0.3
    position_jitter: float = 0.25  # std, in units of the mean Gaussian spacing
    log_scale_jitter: float = 0.25  # std of the log-scale error
    opacity_logit_jitter: float = 0.6  # std of the opacity-logit error
    color_jitter: float = 0.03  # std of the colour error
    view_dependence: float = 0.04  # std of the degree-1 SH coefficients
    layered: float = 0.4  # translucent layer Gaussians added, as a fraction of the surviving surface ones
    layer_offset: float = 1.0  # std of their offset from their source Gaussian, in units of the spacing
    layer_growth: tuple[float, float] = (1.5, 3.0)  # their scale, as a factor of their source's (uniform)
    layer_opacity_logit: tuple[float, float] = (-2.0, 0.8)  # mean, std of their opacity logit (~0.12)
    pose_position_m: float = 0.05  # std of the camera position error
    pose_rotation_deg: float = 0.03  # std of the camera rotation error


@dataclass
class ReconstructedMap:
    gaussians: Gaussians
    category: np.ndarray  # [M] int16, CATEGORY["floater"] for floaters
    instance: np.ndarray  # [M] int32, -1 for stuff and floaters
    label: np.ndarray  # [M] int16, -1 for floaters


def _merge_pairs(means: np.ndarray, fraction: float, cell: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """(keep [k] indices, partner [k] indices): disjoint pairs of Gaussians sharing a voxel of side ``cell``."""
    voxel = np.floor(means / cell).astype(np.int64)
    voxel -= voxel.min(0)
    extent = voxel.max(0) + 1
    keys = (voxel[:, 0] * extent[1] + voxel[:, 1]) * extent[2] + voxel[:, 2]  # exact: no two voxels share a key
    order = np.argsort(keys, kind="stable")
    same = keys[order[:-1]] == keys[order[1:]]
    starts = np.flatnonzero(same)
    starts = starts[np.r_[True, np.diff(starts) > 1]] if len(starts) else starts  # disjoint pairs
    chosen = rng.random(len(starts)) < fraction * len(means) / max(len(starts), 1)
    return order[starts[chosen]], order[starts[chosen] + 1]


def reconstruct(truth: TruthScene, spec: ReconstructionSpec, rng: np.random.Generator) -> ReconstructedMap:
    g = truth.gaussians
    n = len(g)
    spacing = float(np.median(np.exp(g.log_scales[:, 0]))) / 0.85
    means = g.means.astype(np.float64).copy()
    log_scales = g.log_scales.astype(np.float64).copy()
    colors = g.sh[:, 0, :].astype(np.float64).copy()
    opacity = g.opacity_logits.astype(np.float64).copy()
    quats = g.quats.astype(np.float64).copy()

    keep, partner = _merge_pairs(means, spec.merged, 2.0 * spacing, rng)
    gap = np.linalg.norm(means[keep] - means[partner], axis=1)
    means[keep] = 0.5 * (means[keep] + means[partner])
    # the merged blob spans both: it grows along its two long axes, its thin axis stays thin
    log_scales[keep] = np.maximum(log_scales[keep], log_scales[partner])
    log_scales[keep, :2] = np.log(np.exp(log_scales[keep, :2]) + 0.5 * gap[:, None])
    colors[keep] = 0.5 * (colors[keep] + colors[partner])
    alive = np.ones(n, bool)
    alive[partner] = False
    alive &= rng.random(n) >= spec.missing
    index = np.flatnonzero(alive)

    m = len(index)
    normals = quat_to_rotmat(quats[index])[:, :, 2]  # a flat Gaussian's thin axis
    out_means = means[index] + rng.normal(0, spec.position_jitter * spacing, (m, 3))
    out_means += normals * rng.normal(0, 0.3 * spec.position_jitter * spacing, (m, 1))
    sh = np.zeros((m, 4, 3))
    sh[:, 0] = colors[index] + rng.normal(0, spec.color_jitter / 0.2820948, (m, 3))
    sh[:, 1:] = rng.normal(0, spec.view_dependence, (m, 3, 3))
    out_log_scales = log_scales[index] + rng.normal(0, spec.log_scale_jitter, (m, 3))
    out_opacity = opacity[index] + rng.normal(0, spec.opacity_logit_jitter, m)
    category, instance, label = truth.category[index], truth.instance[index], truth.label[index]

    # layers: translucent, grown copies of surface Gaussians, off the surface and across edges
    k_layer = int(spec.layered * m)
    source = rng.integers(0, m, k_layer)
    out_means = np.concatenate(
        [out_means, out_means[source] + rng.normal(0, spec.layer_offset * spacing, (k_layer, 3))]
    )
    growth = np.log(rng.uniform(*spec.layer_growth, (k_layer, 1)))
    out_log_scales = np.concatenate([out_log_scales, out_log_scales[source] + growth])
    out_opacity = np.concatenate([out_opacity, rng.normal(*spec.layer_opacity_logit, k_layer)])
    layer_sh = sh[source].copy()
    layer_sh[:, 0] += rng.normal(0, spec.color_jitter / 0.2820948, (k_layer, 3))
    sh = np.concatenate([sh, layer_sh])
    out_quats = np.concatenate([quats[index], quats[index][source]])
    category, instance, label = (np.concatenate([a, a[source]]) for a in (category, instance, label))

    # floaters: loose, translucent blobs in the air between the town and the cameras
    k = int(min(spec.floaters * n, spec.floaters_max_per_m2 * truth.size_m**2))
    half = truth.size_m / 2
    f_means = np.c_[rng.uniform(-half, half, (k, 2)), rng.uniform(2.0, 45.0, k)]
    f_sh = np.zeros((k, 4, 3))
    f_sh[:, 0] = (rng.uniform(0.2, 0.8, (k, 1)) + rng.normal(0, 0.05, (k, 3)) - 0.5) / 0.2820948
    gaussians = Gaussians(
        means=np.concatenate([out_means, f_means]),
        quats=np.concatenate([out_quats, rng.normal(size=(k, 4))]),
        log_scales=np.concatenate([out_log_scales, np.log(rng.uniform(0.1, 1.5, (k, 3)))]),
        opacity_logits=np.concatenate([out_opacity, rng.uniform(-3.0, 0.0, k)]),
        sh=np.concatenate([sh, f_sh]),
    )
    category = np.concatenate([category, np.full(k, CATEGORY["floater"], np.int16)])
    instance = np.concatenate([instance, np.full(k, -1, np.int32)])
    label = np.concatenate([label, np.full(k, -1, np.int16)])
    shuffle = rng.permutation(len(category))
    return ReconstructedMap(gaussians.subset(shuffle), category[shuffle], instance[shuffle], label[shuffle])


def perturb_pose(camera: Camera, spec: ReconstructionSpec, rng: np.random.Generator) -> Camera:
    """The camera with the pose error of structure-from-motion (position and rotation noise)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.normal(0, spec.pose_rotation_deg))
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew  # Rodrigues
    pose = camera.world_from_camera.copy()
    pose[:3, :3] = rotation @ pose[:3, :3]
    pose[:3, 3] += rng.normal(0, spec.pose_position_m, 3)
    return Camera(camera.name, camera.width, camera.height, camera.K, pose, camera.dist, camera.model)
