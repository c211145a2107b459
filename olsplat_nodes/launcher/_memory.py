"""Will the graph fit? The memory a launch will need, estimated before any node starts.

A flight that does not fit should be refused at launch with the numbers, not killed by the
kernel at view 250. The estimate is per node, from what the node holds (see each node's
module): the prior map's Gaussians (count and row size from the PLY header, never its body),
the per-view buffers of the largest image the run's cameras will give (when the launch does not
say, 1280 x 960), and the language map's features (float32 rows in the query server up to the
refiner's ``codebook_above``, float16 rows in the refiner). The coefficients were fitted on
``olsplat bench graph --lossless`` runs (then named ``bench scale``) of the small, medium and
large presets (docs/benchmarks.md, "Scale") and err on the high side: each node's estimate is
above its measured peak there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..scene.ply import ply_header

MB = 2**20
FEATURE_DIM = 128  # the widest shipped spec (both encoders fused; the default olsplat-cnn64 is 64):
# the estimate does not load an encoder, and errs high


@dataclass(frozen=True)
class NodeEstimate:
    node: str
    mb: float
    why: str  # the terms, for the error message


def estimate_graph(nodes: list[tuple[str, str, dict[str, Any]]], pixels: int = 1280 * 960) -> list[NodeEstimate]:
    """[(name, exec, resolved params)] -> per node MB it is expected to hold at its peak."""
    estimates = []
    refiner = next((p for _, kind, p in nodes if kind == "refiner"), {})
    for name, kind, params in nodes:
        gaussians, row_bytes = _map_size(params.get("map", ""))
        if kind == "accumulator":  # the map, its projection (64 B records + sort keys), Top-K buffers
            mb = 300 + gaussians * (row_bytes + 96) / MB + pixels * 400 / MB
            why = f"{gaussians:,} Gaussians x {row_bytes + 96} B + {pixels:,} px x 400 B + 300 MB"
        elif kind == "query_server":
            codebook = int(refiner.get("codebook", 0)) > 0 or gaussians > int(refiner.get("codebook_above", 2_000_000))
            feature_bytes = 0 if codebook else FEATURE_DIM * 4 * 2 + FEATURE_DIM * 2  # old + new rows while loading
            cache = float(params.get("heatmap_cache_mb", 320))
            mb = 300 + gaussians * (row_bytes + 96 + feature_bytes) / MB + pixels * 400 / MB + cache
            why = (
                f"{gaussians:,} Gaussians x {row_bytes + 96 + feature_bytes} B + {pixels:,} px x 400 B "
                f"+ heatmap cache {cache:g} MB + 300 MB"
            )
        elif kind == "refiner":  # float16 unit rows + per-Gaussian bookkeeping; a range's work; codebook
            codebook = int(params.get("codebook", 0)) > 0 or gaussians > int(params.get("codebook_above", 2_000_000))
            per = FEATURE_DIM * 2 + 44
            mb = 1000 + gaussians * per / MB + (500 if codebook else 0)
            why = f"{gaussians:,} Gaussians x {per} B + 1000 MB" + (" + codebook 500 MB" if codebook else "")
        elif kind == "region_encoder":
            mb, why = 700.0, "encoders and regions, 700 MB"
        else:
            mb, why = 150.0, "150 MB"
        estimates.append(NodeEstimate(name, mb, why))
    return estimates


def available_mb() -> float:
    """MemAvailable from /proc/meminfo (what can be allocated without swapping); inf elsewhere."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return float("inf")


def _map_size(path: str) -> tuple[int, int]:
    """(Gaussians, bytes per Gaussian in memory) from a PLY header; (0, 0) without a readable one."""
    if not path:
        return 0, 0
    header = ply_header(path)
    return (header[0], header[1]) if header else (0, 0)


def check_memory(config, params: dict[str, dict[str, Any]], available: float | None = None) -> list[NodeEstimate]:
    """Raise ``LaunchFileError`` when the launch's estimate exceeds ``config.memory_budget_mb``
    (0: ``available``, default MemAvailable); the per-node estimates otherwise."""
    from ._config import LaunchFileError

    estimates = estimate_graph([(node.name, node.exec, params[node.name]) for node in config.nodes])
    total = sum(e.mb for e in estimates)
    budget = config.memory_budget_mb or (available_mb() if available is None else available)
    if total > budget:
        maps = sorted({str(params[n.name]["map"]) for n in config.nodes if params[n.name].get("map")})
        worst = sorted(estimates, key=lambda e: -e.mb)[:3]
        where = "launch.memory_budget_mb" if config.memory_budget_mb else "available now (MemAvailable)"
        raise LaunchFileError(
            f"{config.source}: this graph needs about {total:,.0f} MB with the map {', '.join(maps) or '(none)'} "
            f"but {budget:,.0f} MB are {where}; largest: "
            + "; ".join(f"{e.node} ~{e.mb:,.0f} MB ({e.why})" for e in worst)
            + ". Use a machine with more memory or a smaller map, or set launch.memory_budget_mb to "
            "launch anyway"
        )
    return estimates
