"""``olsplat bench scale --json`` on the tiny flight: the real graph over ZeroMQ, every frame
aggregated, and every key the issue names in the JSON with values that must hold whatever the
load (the figures themselves are benchmarks, not asserted against targets)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from olsplat_nodes.cli import main

from ..helpers import free_port

REPO = Path(__file__).resolve().parents[2]
NODES = {"query_server", "ingest", "region_encoder", "accumulator", "refiner"}


@pytest.mark.timeout(600)
def test_bench_scale_writes_the_documented_figures(tiny, tmp_path, capsys):
    scene, _ = tiny
    out = tmp_path / "scale.json"
    args = ["bench", "scale", "--scene", str(scene), "--queries", "3", "--heatmap-queries", "2"]
    args += ["--heatmap-views", "1", "--sample-s", "0.2", "--work", str(tmp_path / "run")]
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--port", str(free_port()), "--json", str(out)]
    assert main(args) == 0
    figures = json.loads(out.read_text())
    assert figures["views"] == 12  # lossless: every frame of the tiny flight
    assert figures["gaussians"] > 1000 and figures["width"] > 0 and figures["height"] > 0
    assert figures["views_per_s"] == pytest.approx(12 / figures["wall_s"], rel=0.02)
    assert set(figures["node_ready_s"]) == NODES  # every node's own "ready" line, read from its log
    assert figures["startup_s"] == max(figures["node_ready_s"].values())
    assert all(0 < s < figures["wall_s"] for s in figures["node_ready_s"].values())
    assert 0 < figures["all_reporting_s"] < figures["wall_s"]
    assert set(figures["peak_rss_mb"]) == NODES and all(mb > 10 for mb in figures["peak_rss_mb"].values())
    assert figures["peak_rss_mb_sum"] == pytest.approx(sum(figures["peak_rss_mb"].values()), abs=len(NODES))
    assert set(figures["rss_growth_mb"]) == NODES and set(figures["private_mb_max"]) == NODES
    store = tmp_path / "run" / "store" / "views"
    stored = sum(f.stat().st_size for f in store.rglob("*") if f.is_file())
    assert figures["store_bytes_per_view"] == pytest.approx(stored / 12, abs=1)
    final = json.loads((tmp_path / "run" / "map" / "latest.json").read_text())
    assert figures["snapshot_bytes"] == final["bytes"] == (tmp_path / "run" / "map" / final["file"]).stat().st_size
    passes = figures["refine_pass_s"]
    assert passes and all(s > 0 for s in passes) and len(passes) == len(figures["refine_pass_views"])
    added = [b - a for a, b in zip([0, *figures["refine_pass_views"]], figures["refine_pass_views"], strict=False)]
    per_view = [s / max(a, 1) for s, a in zip(passes, added, strict=True)]
    assert figures["refine_s_per_added_view"] == pytest.approx(per_view, abs=1e-3)
    exact = figures["refine_pass_exact"]  # the refiner folds its live passes; its first and final are exact
    assert len(exact) == len(passes) and exact[0] and exact[-1] and final["final"] and final["exact"]
    assert figures["refine_pass_views"][-1] == 12 and figures["refine_pass_views"] == sorted(
        figures["refine_pass_views"]
    )
    for key in ("query_relevance_p95_ms", "query_heatmap_p95_ms", "query_heatmap_first_p95_ms"):
        assert figures[key] > 0
    # the server's own time is part of the round trip
    assert 0 < figures["query_relevance_server_p95_ms"] <= figures["query_relevance_p95_ms"]
    assert 0 < figures["query_heatmap_first_server_p95_ms"] <= figures["query_heatmap_first_p95_ms"]
    assert "12 views of" in capsys.readouterr().out

    # the same run's queries again without the flight: only its query server, on its final map
    again = tmp_path / "queries.json"
    args = ["bench", "scale", "--scene", str(scene), "--queries", "3", "--heatmap-queries", "2", "--queries-only"]
    args += ["--heatmap-views", "2", "--heatmap-spread", "--work", str(tmp_path / "run"), "--json", str(again)]
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--port", str(free_port())]
    assert main(args) == 0
    requeried = json.loads(again.read_text())
    assert requeried["queries_only"] and requeried["views"] == 12 and requeried["gaussians"] == figures["gaussians"]
    assert set(requeried["peak_rss_mb"]) == {"query_server"} and requeried["startup_s"] > 0
    names = [json.loads(f.read_text())["name"] for f in sorted((tmp_path / "run" / "views").glob("*.json"))]
    assert figures["heatmap_views"] == names[:1] and requeried["heatmap_views"] == [names[0], names[-1]]  # spread
    for key in ("query_relevance_p95_ms", "query_relevance_server_p95_ms", "query_heatmap_p95_ms"):
        assert requeried[key] > 0
    assert json.loads((tmp_path / "run" / "map" / "latest.json").read_text()) == final  # the run is only read
    logs = (tmp_path / "run" / "logs" / "query_server.log").read_text()
    assert logs.count(" ready: ") == 2  # the run's query server, then this one's


@pytest.mark.timeout(60)
def test_queries_only_needs_a_kept_run(tiny, tmp_path, capsys):
    """``--queries-only`` on a folder with no final map is one error naming it, before any node starts."""
    scene, _ = tiny
    args = ["bench", "scale", "--scene", str(scene), "--queries-only", "--work", str(tmp_path / "nothing")]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "nothing: no final map" in err and "bench scale --work DIR" in err
    assert not (tmp_path / "nothing" / "logs").exists()


@pytest.mark.timeout(60)
def test_a_bad_override_is_refused_before_anything_starts(tiny, tmp_path, capsys):
    """``--set`` reaches the nodes' parameters: a value a node refuses is the command's one error
    (naming the node and parameter) before any node starts, not a hang in the graph's thread."""
    scene, _ = tiny
    args = ["bench", "scale", "--scene", str(scene), "--work", str(tmp_path / "run"), "--port", str(free_port())]
    args += ["--launch", str(REPO / "launch" / "replay.yaml")]
    for setting, error in [
        ("query_server.heatmap_max_side=-1", "(query_server).params: heatmap_max_side must be >= 0"),
        ("refiner.passes=sometimes", "(refiner).params: passes must be fold or exact and refresh >= 0"),
        ("refiner.refresh=-1", "(refiner).params: passes must be fold or exact and refresh >= 0"),
    ]:
        assert main([*args, "--set", setting]) == 1
        assert error in capsys.readouterr().err
        assert not (tmp_path / "run" / "logs").exists()  # no node was started


def test_heatmap_views_are_the_first_ones_or_spread_over_the_flight():
    from olsplat_nodes.bench.ground_link import pick_views

    names = [f"v{i}" for i in range(10)]
    assert pick_views(names, 4, spread=False) == ["v0", "v1", "v2", "v3"]
    assert pick_views(names, 4, spread=True) == ["v0", "v3", "v6", "v9"]  # first to last, evenly
    assert pick_views(names, 1, spread=True) == ["v0"]
    assert pick_views(names, 20, spread=True) == names  # more than the flight has: every view once
