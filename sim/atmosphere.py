"""Light between the sun, the town and the camera (world v2): drifting cloud shadows and haze.

Both act on a rendered frame (linear rgb 0..1) before the camera's sensor model, per pixel, from
the render's depth: the shadow multiplies the surface's light, then haze mixes in the airlight.
"""

from __future__ import annotations

from statistics import NormalDist

import numpy as np

from olsplat_nodes.scene import Camera

from .world import CloudWorld, HazeWorld


class CloudField:
    """A smooth random field on the ground plane moving with the wind; ``light`` is the multiplier
    of the sunlight (``darkness`` in full shadow, 1 in the sun).

    field(q, t) = sqrt(2 / M) * sum_j cos(k_j . (q - wind * t) + phase_j), unit variance, with
    wave vectors of random directions and lengths 2 pi / scale_m * U(0.7, 1.4)."""

    def __init__(self, spec: CloudWorld, rng: np.random.Generator):
        self.spec = spec
        angle = rng.uniform(0.0, 2.0 * np.pi, spec.modes)
        length = 2.0 * np.pi / spec.scale_m * rng.uniform(0.7, 1.4, spec.modes)
        self.waves = np.c_[np.cos(angle), np.sin(angle)] * length[:, None]  # [M, 2] rad / m
        self.phases = rng.uniform(0.0, 2.0 * np.pi, spec.modes)
        # the field is about normal: this quantile leaves ``coverage`` of the ground in shadow
        self.threshold = NormalDist().inv_cdf(1.0 - spec.coverage) if 0.0 < spec.coverage < 1.0 else 0.0

    def field(self, xy: np.ndarray, t_s: float) -> np.ndarray:
        """[P, 2] ground points (metres) at ``t_s`` seconds -> [P] field values."""
        moved = xy - np.asarray(self.spec.wind_mps) * t_s
        return np.sqrt(2.0 / self.spec.modes) * np.cos(moved @ self.waves.T + self.phases).sum(1)

    def light(self, xy: np.ndarray, t_s: float) -> np.ndarray:
        """[P, 2] ground points (metres) at ``t_s`` seconds -> [P] light multiplier in [darkness, 1]."""
        if self.spec.coverage <= 0.0:
            return np.ones(len(xy))
        if self.spec.coverage >= 1.0:
            return np.full(len(xy), self.spec.darkness)
        edge = max(self.spec.softness, 1e-6)
        s = np.clip((self.field(xy, t_s) - self.threshold) / edge + 0.5, 0.0, 1.0)
        shade = s * s * (3.0 - 2.0 * s)  # smoothstep across the edge
        return 1.0 - (1.0 - self.spec.darkness) * shade


def surface_points(camera: Camera, depth: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points [H, W, 3] world metres, depth [H, W] metres along the optical axis) where each
    pixel's ray meets what it sees: at the render's depth where something was rendered, the
    z = 0 ground plane (the bare land beyond the town) where nothing was, alpha-blended between."""
    h, w = depth.shape
    K = camera.K
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)  # pixel centres at +0.5
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # z = 1
    rotation, centre = camera.world_from_camera[:3, :3], camera.world_from_camera[:3, 3]
    rays = rays_cam @ rotation.T  # [H, W, 3] world, one metre of optical-axis depth each
    plane = np.where(rays[..., 2] < -1e-6, -centre[2] / np.minimum(rays[..., 2], -1e-6), 1e4)
    a = np.clip(alpha, 0.0, 1.0)
    blended = a * depth + (1.0 - a) * plane
    return centre + rays * blended[..., None], blended


def shadow_light(clouds: CloudField, points: np.ndarray, sun: np.ndarray, t_s: float) -> np.ndarray:
    """[H, W, 3] surface points -> [H, W] light multiplier: the field where the sun's ray through
    each point meets z = 0 (``sun`` [3] unit, towards the sun)."""
    ground = points[..., :2] - points[..., 2:3] * (sun[:2] / sun[2])
    return clouds.light(ground.reshape(-1, 2), t_s).reshape(points.shape[:2])


def apply_haze(rgb: np.ndarray, depth: np.ndarray, spec: HazeWorld) -> np.ndarray:
    """[H, W, 3] linear rgb, [H, W] depth (metres) -> rgb * t + airlight * (1 - t), t = exp(-beta depth)."""
    t = np.exp(-spec.beta * np.maximum(depth, 0.0))[..., None]
    return rgb * t + np.asarray(spec.airlight) * (1.0 - t)
