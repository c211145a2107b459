"""The methods by name (the words of the design card, used by every table, script and node).

- ``outlangsplat``: adaptive Top-K, pixel quality q_sum * q_eff, valid mask, tau_d, consistency
  iterations, with the retained-views gate (our default);
- ``outlangsplat-paper``: the paper's equations exactly (no retained-views gate);
- ``outlangsplat-noquality`` (no q_sum * q_eff), ``outlangsplat-noconsistency`` (T = 0);
- ``topk``: our adaptive Top-K contributions, no reliability weighting, no tau_d, plain
  weighted mean (the ablation of everything but the Top-K);
- ``drsplat`` (Dr.Splat, Sec. 3.2 of its paper): a fixed K = 45 contributors per pixel (its
  released code's value), alpha*T weights, plain weighted mean; no product quantization (we
  store float16 or our own codebook);
- ``projection`` (LUDVIG-style): every contribution of every pixel (Top-K cap 32 and 100 %
  coverage, which holds all but a sliver of the weight), alpha*T-weighted mean, nothing else;
- ``vala`` (VALA-style): the same contributions, a per-view mass gate (the fewest Gaussians
  holding 95 % of the view's contribution; VALA's own threshold is not published here) and a
  streaming update weighted by each observation's cosine agreement, in flight order.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from ..aggregate import AggregationConfig
from ..errors import OlsplatInputError
from ..params import parse_params
from ..raster import RasterConfig


@dataclass(frozen=True)
class Method:
    """Everything that decides a language map's numbers from the same views: how a view is
    rasterized (its Top-K) and how observations are weighted and combined."""

    name: str
    aggregation: AggregationConfig
    raster: RasterConfig

    def record(self) -> dict[str, Any]:
        """JSON-ready form (the store's manifest); ``Method.from_record`` reads it back."""
        return {"name": self.name, "aggregation": asdict(self.aggregation), "raster": asdict(self.raster)}

    @staticmethod
    def from_record(record: dict[str, Any], where: str) -> Method:
        """The method of ``record()``; ParameterError naming ``where`` when it does not fit."""
        if not isinstance(record, dict) or not {"name", "aggregation", "raster"} <= set(record):
            raise OlsplatInputError(f"{where}: not a method record (needs name, aggregation, raster)")
        return Method(
            str(record["name"]),
            parse_params(AggregationConfig, record["aggregation"], f"{where}.aggregation"),
            parse_params(RasterConfig, record["raster"], f"{where}.raster"),
        )


_PLAIN = AggregationConfig(use_quality=False, tau_d=0.0, iterations=0)
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("outlangsplat", AggregationConfig(), RasterConfig()),
        Method("outlangsplat-paper", AggregationConfig(min_retained_views=None), RasterConfig()),
        Method("outlangsplat-noquality", AggregationConfig(use_quality=False), RasterConfig()),
        Method("outlangsplat-noconsistency", AggregationConfig(iterations=0), RasterConfig()),
        Method("topk", _PLAIN, RasterConfig()),
        Method("drsplat", _PLAIN, RasterConfig(topk_min=45, topk_max=45, topk_coverage=1.0)),
        Method("projection", _PLAIN, RasterConfig(topk_min=32, topk_max=32, topk_coverage=1.0)),
        Method("vala", replace(_PLAIN, mass_gate=0.95, combine="streaming_cosine"), RasterConfig()),
    )
}


def named_method(name: str) -> Method:
    """The method called ``name``; OlsplatInputError listing the known names otherwise."""
    if name not in METHODS:
        raise OlsplatInputError(f"unknown method {name!r}; known: {', '.join(METHODS)}")
    return METHODS[name]
