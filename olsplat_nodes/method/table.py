"""The methods by name (the words of the design card, used by every table, script and node).

- ``outlangsplat``: adaptive Top-K, pixel quality q_sum * q_eff, valid mask, tau_d, consistency
  iterations, with the retained-views gate (our default);
- ``outlangsplat-paper``: the paper's equations exactly (no retained-views gate);
- ``outlangsplat-noquality`` (no q_sum * q_eff), ``outlangsplat-noconsistency`` (T = 0);
- ``topk``: our adaptive Top-K contributions, no reliability weighting, no tau_d, plain
  weighted mean (the ablation of everything but the Top-K);
- ``drsplat`` (Dr.Splat, Sec. 3.2 of its paper): a fixed K contributors per pixel (45 in its
  released code; 16 chosen by the same tuning as every method), alpha*T weights, plain
  weighted mean; no product quantization (we
  store float16 or our own codebook);
- ``projection`` (LUDVIG, Marrie et al. 2024, its uplifting: every contributor of every
  pixel of every view, alpha*T-weighted mean, nothing else; no graph diffusion): a
  contribution list of ``ALL_CONTRIBUTORS`` per pixel, more than any pixel of our scenes has
  (the most on the small preset: 186), in full;
- ``vala`` (VALA, Wang et al. 2025, Secs. 4.1-4.2): alpha*T and the feature at each Gaussian's
  centre pixel, VALA's visibility gate, streaming geometric median in cosine space in flight
  order (``aggregate/vala.py``).
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
ALL_CONTRIBUTORS = 256  # a contribution list this long holds every contributor of every pixel we render
_EVERY = RasterConfig(topk_min=ALL_CONTRIBUTORS, topk_max=ALL_CONTRIBUTORS, topk_coverage=1.0)
# Chosen by ``olsplat bench tune`` on training seeds 1001 and 1002 (docs/evaluation.md, "Comparisons"); every
# method had the same four settings of budget. VALA's own values for LERF scenes (tau_mass 0.75,
# tau_abs 0.13, stage-B cut 0.15) are AggregationConfig's defaults and gave 3 mIoU less here.
_VALA = replace(_PLAIN, view_feature="centre", combine="streaming_median", gate_mass=0.9, gate_floor=0.0, gate_cut=0.05)
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("outlangsplat", AggregationConfig(), RasterConfig()),
        Method("outlangsplat-paper", AggregationConfig(min_retained_views=None), RasterConfig()),
        Method("outlangsplat-noquality", AggregationConfig(use_quality=False), RasterConfig()),
        Method("outlangsplat-noconsistency", AggregationConfig(iterations=0), RasterConfig()),
        Method("topk", _PLAIN, RasterConfig()),
        Method("drsplat", _PLAIN, RasterConfig(topk_min=16, topk_max=16, topk_coverage=1.0)),  # tuned; its code: 45
        Method("projection", _PLAIN, _EVERY),
        Method("vala", _VALA, _EVERY),
    )
}


def named_method(name: str) -> Method:
    """The method called ``name``; OlsplatInputError listing the known names otherwise."""
    if name not in METHODS:
        raise OlsplatInputError(f"unknown method {name!r}; known: {', '.join(METHODS)}")
    return METHODS[name]
