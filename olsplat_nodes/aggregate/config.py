"""Parameters of the aggregation (paper: "Consistency-aware Gaussian feature aggregation")."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class AggregationConfig:
    q_min: float = 0.1  # q_sum = clip(sum of a pixel's Top-K weights, q_min, 1); not given by the paper
    tau_e: float = 12.0  # effective-number threshold of q_eff (paper)
    kappa: float = 8.0  # decay of q_eff (paper)
    tau_d: float = 0.05  # a Gaussian's view observation is kept when d_iv > tau_d; not given by the paper
    level_weights: tuple[float, ...] | None = None  # weight of each region level (coarse to fine); None = finest only
    iterations: int = 3  # T, consistency iterations; not given by the paper
    beta: tuple[float, ...] = (2.0, 4.0, 8.0)  # beta_t per iteration (the last repeats); not given by the paper
    eps: float = 1e-8
    use_quality: bool = True  # multiply by q_sum * q_eff (off: the "noquality" ablation and the baselines)
    # How a Gaussian's weight and feature in a view are formed: "pixels" (the paper's: every
    # pixel's Top-K contribution) or "centre" (VALA's: alpha*T and the feature at the pixel of
    # its projected centre, then VALA's visibility gate with gate_mass and gate_floor).
    view_feature: Literal["pixels", "centre"] = "pixels"
    gate_mass: float = 0.75  # VALA tau_mass: keep the strongest Gaussians holding this share of the view's weight ...
    gate_floor: float = 0.13  # ... whose weight is at least tau_abs (VALA's LERF values) ...
    gate_cut: float = 0.15  # ... and above min(gate_cut, the view's 0.85 quantile) (VALA's released code)
    combine: Literal["consistency", "streaming_median"] = "consistency"  # how views are combined
    # Keep F0 for a Gaussian whose consistency weights retain less than this share of its
    # effective number of views, (sum rho)^2 / sum rho^2 over (sum d)^2 / sum d^2: its views
    # disagree as a whole (e.g. a floater seen against different backgrounds), they do not hold
    # a few outliers. None: off (the paper's update everywhere).
    min_retained_views: float | None = 0.5

    def __post_init__(self) -> None:
        if not 0.0 < self.q_min <= 1.0:
            raise ValueError(f"q_min must be in (0, 1], got q_min={self.q_min}")
        if self.min_retained_views is not None and not 0.0 < self.min_retained_views <= 1.0:
            raise ValueError(f"min_retained_views must be in (0, 1], got {self.min_retained_views}")
        if not 0.0 < self.gate_mass <= 1.0 or self.gate_floor < 0.0 or self.gate_cut < 0.0:
            raise ValueError(f"need 0 < gate_mass <= 1, gate_floor >= 0 and gate_cut >= 0, got {self}")
        if self.kappa <= 0 or self.tau_d < 0 or self.iterations < 0 or not self.beta:
            raise ValueError(f"need kappa > 0, tau_d >= 0, iterations >= 0 and a beta schedule, got {self}")

    def beta_at(self, t: int) -> float:
        """beta_t for iteration t = 1..T."""
        return self.beta[min(t, len(self.beta)) - 1]
