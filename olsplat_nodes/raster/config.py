"""Rasterizer parameters. Defaults follow gsplat's "classic" mode and the paper's Top-K."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class RasterConfig:
    tile_size: int = 16  # pixels per tile side
    eps2d: float = 0.3  # low-pass filter added to the 2D covariance diagonal, pixels^2
    near_plane: float = 0.01  # camera-z below which a Gaussian is culled (world units)
    far_plane: float = 1e10  # camera-z above which a Gaussian is culled
    radius_sigmas: float = 3.0  # screen radius = ceil(radius_sigmas * sqrt(largest eigenvalue))
    alpha_min: float = 1.0 / 255.0  # contributions with smaller alpha are skipped
    alpha_max: float = 0.999  # alpha = min(alpha_max, opacity * exp(-sigma))
    transmittance_min: float = 1e-4  # a pixel stops before its transmittance would fall to <= this
    topk_min: int = 16  # adaptive Top-K keeps at least this many contributors (when present)
    topk_max: int = 32  # ... and at most this many
    topk_coverage: float = 0.9  # ... stopping once this fraction of the pixel's total weight is covered
    feature_eps: float = 1e-6  # epsilon of eq. semantic_rendering: F = sum(w f) / (sum(w) + eps)
    # The observations' Top-K render at this fraction of the view's width and height (1: the
    # view's own pixels, exact; 0.5: a quarter of the pixels, the region label maps sampled at
    # the smaller render's pixel centres, each observation's strength counted in the view's
    # pixels). A speed setting measured in docs/benchmarks.md ("A smaller Top-K render"), not the
    # paper's. Left out of repr (the run ledger's key, evaluate/ledger.py, adds it when not 1).
    topk_scale: float = field(default=1.0, repr=False)

    def __post_init__(self) -> None:
        if self.tile_size <= 0:
            raise ValueError(f"tile_size must be positive, got tile_size={self.tile_size}")
        if not 1 <= self.topk_min <= self.topk_max:
            raise ValueError(f"need 1 <= topk_min <= topk_max, got topk_min={self.topk_min}, topk_max={self.topk_max}")
        if not 0.0 < self.topk_scale <= 1.0:
            raise ValueError(f"topk_scale must be in (0, 1], got topk_scale={self.topk_scale}")
        if not 0.0 < self.topk_coverage <= 1.0:
            raise ValueError(f"topk_coverage must be in (0, 1], got topk_coverage={self.topk_coverage}")
        if not 0.0 < self.alpha_min < self.alpha_max < 1.0:
            raise ValueError(f"need 0 < alpha_min < alpha_max < 1, got {self.alpha_min}, {self.alpha_max}")
        if not 0.0 < self.near_plane < self.far_plane:
            raise ValueError(f"need 0 < near_plane < far_plane, got {self.near_plane}, {self.far_plane}")
