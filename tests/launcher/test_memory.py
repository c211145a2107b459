"""A flight that will not fit is refused at launch, with the numbers, before any node starts."""

from __future__ import annotations

import pytest

from olsplat_nodes.launcher import LaunchFileError, Supervisor, load_launch
from olsplat_nodes.launcher._memory import check_memory, estimate_graph
from olsplat_nodes.launcher._resolve import resolve_launch
from olsplat_nodes.scene import write_ply
from olsplat_nodes.scene.ply import ply_header

from ..conftest import random_gaussians


def _replay(tmp_path, budget_mb: float):
    ply = tmp_path / "map.ply"
    write_ply(ply, random_gaussians(5000, 1, seed=0))
    overrides = [f"{node}.map={ply}" for node in ("query_server", "accumulator", "refiner")]
    overrides += [f"ingest.source={tmp_path / 'none.mcap'}", f"launch.memory_budget_mb={budget_mb}"]
    return load_launch("launch/replay.yaml", overrides=overrides, run_dir=str(tmp_path / "run")), ply


def test_the_header_gives_the_map_size_without_its_body(tmp_path):
    _, ply = _replay(tmp_path, 0)
    assert ply_header(ply) == (5000, 4 * (3 + 3 + 3 * 3 + 1 + 3 + 4))  # xyz f_dc f_rest(deg 1) opacity scale rot
    assert ply_header(tmp_path / "missing.ply") is None


def test_a_launch_over_its_memory_budget_is_refused_before_any_node_starts(tmp_path):
    config, ply = _replay(tmp_path, 100)
    with pytest.raises(LaunchFileError, match="memory_budget_mb") as error:
        Supervisor(config).run()
    assert str(ply) in str(error.value) and "query_server ~" in str(error.value)
    assert not list((tmp_path / "run" / "logs").glob("*.log"))  # no node was started
    # the same graph within a large enough budget passes the check
    config, _ = _replay(tmp_path, 10**6)
    estimates = check_memory(config, resolve_launch(config, tmp_path / "run"))
    assert {e.node for e in estimates} == {"query_server", "ingest", "region_encoder", "accumulator", "refiner"}


def test_the_estimate_grows_with_the_map_and_a_codebook_map_spares_the_query_server(tmp_path):
    def header_only(name: str, gaussians: int) -> str:  # only the header is read: no body needed
        path = tmp_path / name
        fields = "".join(f"property float {f}\n" for f in ("x", "y", "z", "opacity"))
        path.write_text(f"ply\nformat binary_little_endian 1.0\nelement vertex {gaussians}\n{fields}end_header\n")
        return str(path)

    def estimate(gaussians: int, codebook_above: int) -> dict[str, float]:
        ply = header_only(f"{gaussians}.ply", gaussians)
        nodes = [(kind, kind, {"map": ply}) for kind in ("accumulator", "query_server")]
        nodes.append(("refiner", "refiner", {"map": ply, "codebook_above": codebook_above}))
        return {e.node: e.mb for e in estimate_graph(nodes)}

    million, five = estimate(1_000_000, 2_000_000), estimate(5_000_000, 2_000_000)
    assert five["accumulator"] - million["accumulator"] == pytest.approx(4_000_000 * (16 + 96) / 2**20)
    assert five["refiner"] > million["refiner"]
    # above codebook_above the refiner writes codes: the query server holds no [N, D] float32 rows
    dense = estimate(5_000_000, 10_000_000)
    assert dense["query_server"] - five["query_server"] == pytest.approx(5_000_000 * 1280 / 2**20)
