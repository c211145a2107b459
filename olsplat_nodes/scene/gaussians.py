"""The prior Gaussian-splatting map as plain arrays.

Conventions (the INRIA 3DGS ones, so that files from other trainers load unchanged):
- ``means``      [N, 3] float32, world coordinates (metres for our simulator scenes).
- ``quats``      [N, 4] float32, rotation as (w, x, y, z); need not be normalised.
- ``log_scales`` [N, 3] float32, natural log of the per-axis standard deviations.
- ``opacity_logits`` [N] float32, opacity = sigmoid(logit).
- ``sh``         [N, (deg+1)^2, 3] float32, real spherical-harmonics coefficients per RGB
  channel; coefficient 0 is the DC term. Colour = SH(dir) + 0.5, clamped at 0 (gsplat/INRIA).
- ``extras``     name -> [N] array for per-Gaussian fields we do not interpret (normals,
  trainer-specific values). They are kept so that a round trip loses nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SH_C0 = 0.28209479177387814  # Y_0^0: colour_dc = SH_C0 * f_dc + 0.5


def sh_degree_from_count(n_coeffs: int) -> int:
    """Degree d such that (d + 1)^2 == n_coeffs; raises ValueError otherwise."""
    for degree in range(5):
        if (degree + 1) ** 2 == n_coeffs:
            return degree
    raise ValueError(f"{n_coeffs} SH coefficients per channel is not (d+1)^2 for a degree d <= 4")


@dataclass
class Gaussians:
    means: np.ndarray  # [N, 3] float32
    quats: np.ndarray  # [N, 4] float32, wxyz
    log_scales: np.ndarray  # [N, 3] float32
    opacity_logits: np.ndarray  # [N] float32
    sh: np.ndarray  # [N, (deg+1)^2, 3] float32
    extras: dict[str, np.ndarray] = field(default_factory=dict)  # name -> [N]

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float32)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=np.float32)
        self.sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        n = self.means.shape[0]
        expected = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "log_scales": (self.log_scales, (n, 3)),
            "opacity_logits": (self.opacity_logits, (n,)),
        }
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"means must be [N, 3], got shape {self.means.shape}")
        for name, (array, shape) in expected.items():
            if array.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh must be [N, (deg+1)^2, 3] with N={n}, got {self.sh.shape}")
        sh_degree_from_count(self.sh.shape[1])
        for name, values in self.extras.items():
            if len(values) != n:
                raise ValueError(f"extra field {name!r} has {len(values)} values for {n} Gaussians")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_count(self.sh.shape[1])

    @property
    def opacities(self) -> np.ndarray:
        """[N] float32 in (0, 1)."""
        return (1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))).astype(np.float32)

    @property
    def scales(self) -> np.ndarray:
        """[N, 3] float32 standard deviations."""
        return np.exp(self.log_scales)

    def nonfinite_mask(self) -> np.ndarray:
        """[N] bool: True where any parameter is NaN or infinite."""
        bad = ~np.isfinite(self.means).all(axis=1)
        bad |= ~np.isfinite(self.quats).all(axis=1)
        bad |= ~np.isfinite(self.log_scales).all(axis=1)
        bad |= ~np.isfinite(self.opacity_logits)
        bad |= ~np.isfinite(self.sh).all(axis=(1, 2))
        return bad

    def subset(self, index: np.ndarray) -> Gaussians:
        """A new map holding the Gaussians selected by ``index`` (bool mask or int indices)."""
        return Gaussians(
            means=self.means[index],
            quats=self.quats[index],
            log_scales=self.log_scales[index],
            opacity_logits=self.opacity_logits[index],
            sh=self.sh[index],
            extras={k: v[index] for k, v in self.extras.items()},
        )

    @staticmethod
    def from_colors(
        means: np.ndarray,  # [N, 3]
        colors: np.ndarray,  # [N, 3] linear RGB in 0..1
        scales: np.ndarray,  # [N, 3] standard deviations
        opacities: np.ndarray,  # [N] in (0, 1)
        quats: np.ndarray | None = None,  # [N, 4] wxyz, identity when None
    ) -> Gaussians:
        """Build a degree-0 map from plain colours, scales and opacities."""
        n = len(means)
        if quats is None:
            quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1))
        opacities = np.clip(np.asarray(opacities, np.float64), 1e-6, 1 - 1e-6)
        return Gaussians(
            means=means,
            quats=quats,
            log_scales=np.log(np.maximum(np.asarray(scales, np.float64), 1e-12)),
            opacity_logits=np.log(opacities / (1.0 - opacities)),
            sh=((np.asarray(colors, np.float64) - 0.5) / SH_C0)[:, None, :],
        )
