"""``olsplat bench graph --json`` on the tiny flight: the real graph over ZeroMQ, and every key
the issue names in the JSON (the figures are not asserted against targets: the machines are
shared and noisy; only what must hold whatever the load)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from olsplat_nodes.cli import main

from ..helpers import free_port

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(600)
def test_bench_graph_writes_the_documented_figures(tiny, tmp_path, capsys):
    scene, _ = tiny
    out = tmp_path / "graph.json"
    args = ["bench", "graph", "--scene", str(scene), "--rate", "4", "--queries", "3", "--heatmap-queries", "2"]
    args += ["--heatmap-views", "1"]  # one view: a first query and a repeat
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--port", str(free_port()), "--json", str(out)]
    assert main(args) == 0
    figures = json.loads(out.read_text())
    assert figures["frames_sent"] == 12  # the tiny flight, every frame sent once (latest-wins)
    assert 0 < figures["frames_aggregated"] <= 12
    assert figures["frames_dropped"] == 12 - figures["frames_aggregated"]
    assert figures["views_per_s"] == pytest.approx(4 * figures["frames_aggregated"] / 12, abs=1e-3)
    assert figures["query_relevance_p95_ms"] > 0 and figures["query_heatmap_p95_ms"] > 0
    assert figures["query_heatmap_first_p95_ms"] > 0 and figures["query_heatmap_repeat_p95_ms"] > 0
    for node in ("region_encoder", "accumulator"):
        assert set(figures["nodes"][node]) == {"busy_ms", "latency_ms", "drops", "handled"}
        assert figures["nodes"][node]["busy_ms"] > 0
    assert f"{figures['frames_sent']} frames sent at 4/s" in capsys.readouterr().out


@pytest.mark.timeout(60)
def test_a_bad_override_is_refused_before_anything_starts(tiny, tmp_path, capsys):
    """``--set`` reaches the nodes' parameters: a value a node refuses is the command's one error
    (naming the node and parameter) before any node starts, not a hang in the graph's thread."""
    scene, _ = tiny
    args = ["bench", "graph", "--scene", str(scene), "--work", str(tmp_path / "run"), "--port", str(free_port())]
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--set", "query_server.heatmap_max_side=-1"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "(query_server).params: heatmap_max_side must be >= 0" in err
    assert not (tmp_path / "run" / "logs").exists()  # no node was started


@pytest.mark.timeout(120)
def test_a_stream_that_aggregates_no_view_is_one_error_not_a_hang(tiny, tmp_path, capsys):
    """A replay with no frame (as one whose every frame a lossy stream dropped): the refiner
    announces a final map of no view and the ingest exits; the bench says so and points at the
    logs, which it keeps, instead of waiting for a map that will never be written."""
    from olsplat_nodes.sources.replay_log import write_mcap

    scene, _ = tiny
    empty = tmp_path / "empty.mcap"
    assert write_mcap(empty, []) == 0
    args = ["bench", "graph", "--scene", str(scene), "--port", str(free_port())]
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--set", f"ingest.source={empty}"]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no view was aggregated" in err[0], err
    logs = Path(err[0].rsplit("see ", 1)[1])
    assert "all 0 frames delivered" in (logs / "ingest.log").read_text()
    shutil.rmtree(logs.parent)  # the bench's own temporary run folder, kept for the message
