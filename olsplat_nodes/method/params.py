"""The method's tunable parameters, as a launch file, ``--set`` and ``olsplat aggregate|eval``
give them: a method name plus any of the fields below; a field left at None keeps the named
method's own value (so ``method: projection`` keeps its 256-long contribution lists unless told otherwise).

Symbols are the paper's; defaults and the values the sweeps tried are in docs/method.md.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

from ..aggregate import AggregationConfig
from ..errors import OlsplatInputError
from ..params import ParameterError
from ..raster import RasterConfig
from .table import Method, named_method

_AGGREGATION = {f.name for f in fields(AggregationConfig)}
_RASTER = {f.name for f in fields(RasterConfig)}


@dataclass(frozen=True)
class MethodParams:
    method: str = "outlangsplat"  # a name of method.METHODS
    q_min: float | None = None  # q_sum = clip(sum of a pixel's Top-K weights, q_min, 1)
    tau_e: float | None = None  # tau_E, effective-number threshold of q_eff (paper: 12)
    kappa: float | None = None  # decay of q_eff (paper: 8)
    tau_d: float | None = None  # an observation is kept when d_iv > tau_d
    level_weights: tuple[float, ...] | None = None  # weight per region level, coarse to fine ([] = finest only)
    iterations: int | None = None  # T, consistency iterations
    beta: tuple[float, ...] | None = None  # beta_t per iteration (the last repeats)
    min_retained_views: float | None = None  # retained-views gate; 0 = off (the paper's update everywhere)
    gate_mass: float | None = None  # vala: tau_mass of VALA's visibility gate ...
    gate_floor: float | None = None  # ... its tau_abs ...
    gate_cut: float | None = None  # ... and its stage-B cut
    topk_min: int | None = None  # adaptive Top-K: at least this many contributors per pixel (paper: 16) ...
    topk_max: int | None = None  # ... at most this many (paper: 32) ...
    topk_coverage: float | None = None  # ... stopping at this share of the pixel's weight (paper: 0.9)
    topk_scale: float | None = None  # the observations' Top-K render at this fraction of the view's size (1: exact)

    def overrides(self) -> dict[str, Any]:
        """The fields that were set (not None), by name."""
        named = {f.name: getattr(self, f.name) for f in fields(MethodParams) if f.name != "method"}
        return {name: value for name, value in named.items() if value is not None}

    def resolve(self, where: str = "method") -> Method:
        """The named method with the set fields replaced; ParameterError (naming ``where``) when
        the name is unknown or a value is out of its range."""
        try:
            base = named_method(self.method)
        except OlsplatInputError as exc:
            raise ParameterError(f"{where}.method: {exc}") from exc
        overrides = self.overrides()
        if overrides.get("level_weights") == ():
            overrides["level_weights"] = None
        if overrides.get("min_retained_views") == 0.0:
            overrides["min_retained_views"] = None
        try:
            aggregation = replace(base.aggregation, **{k: v for k, v in overrides.items() if k in _AGGREGATION})
            raster = replace(base.raster, **{k: v for k, v in overrides.items() if k in _RASTER})
        except ValueError as exc:  # the configs' own range checks
            raise ParameterError(f"{where}: {exc}") from exc
        if raster.topk_scale != 1.0 and aggregation.view_feature == "centre":  # VALA reads centre pixels
            raise ParameterError(f"{where}: topk_scale applies to pixel-weighted view features, not {base.name}'s")
        return Method(base.name, aggregation, raster)


def method_params_of(params: object) -> MethodParams:
    """The MethodParams part of any params dataclass that extends MethodParams."""
    return MethodParams(**{f.name: getattr(params, f.name) for f in fields(MethodParams)})
