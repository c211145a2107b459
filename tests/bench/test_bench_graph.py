"""``olsplat bench graph --json`` on the tiny flight, live-paced (``--rate``) and ``--lossless``:
the real graph over ZeroMQ, and every key the module docstrings name in the JSON, with values
that must hold whatever the load (the figures themselves are benchmarks, not asserted against
targets: the machines are shared and noisy)."""

from __future__ import annotations

import ast
import json
import re
import shutil
from pathlib import Path

import pytest

from olsplat_nodes.bench import graph, requery
from olsplat_nodes.cli import main

from ..helpers import free_port

REPO = Path(__file__).resolve().parents[2]
NODES = {"query_server", "ingest", "region_encoder", "accumulator", "refiner"}
# what the two benchmarks this one replaces (the live-paced ``bench graph`` and the lossless
# ``bench scale``) wrote: every key still written, in both modes
OLD_KEYS = {
    "frames_sent", "frames_aggregated", "frames_dropped", "views_per_s", "seconds", "nodes",
    "gaussians", "views", "width", "height", "wall_s", "startup_s", "node_ready_s", "all_reporting_s",
    "peak_rss_mb", "peak_rss_mb_sum", "rss_growth_mb", "private_mb_max", "store_bytes_per_view",
    "snapshot_bytes", "refine_pass_s", "refine_pass_views", "refine_pass_exact", "refine_s_per_added_view",
    "query_relevance_p95_ms", "query_relevance_server_p95_ms", "query_heatmap_p95_ms",
    "query_heatmap_first_p95_ms", "query_heatmap_repeat_p95_ms", "query_heatmap_first_server_p95_ms",
    "heatmap_views", "memory_series",
}  # fmt: skip


def documented_keys(doc: str) -> set[str]:
    """The top-level key names (````name```` or ````name.sub````) of a docstring's ``--json FILE``
    paragraph(s)."""
    section = doc.split("``--json FILE`` writes", 1)[1].split("``--queries-only", 1)[0]
    return set(re.findall(r"``([a-z_0-9]+)(?:\.[^`]+)?``", section))


def test_the_documented_keys_are_the_old_ones_and_more():
    keys = documented_keys(graph.__doc__ or "")
    assert OLD_KEYS <= keys, OLD_KEYS - keys
    assert {"lossless", "rate"} <= keys
    assert "nodes.<name>.{busy_ms, latency_ms, drops, handled}" in (graph.__doc__ or "")
    assert {"gaussians", "views", "width", "height", "startup_s"} <= documented_keys(requery.__doc__ or "")


def check_common(figures: dict, frames: int = 12) -> None:
    """What holds in both modes: every documented key written, the counts and the figures of a
    completed flight."""
    missing = documented_keys(graph.__doc__ or "") - set(figures)
    if not figures["lossless"]:  # written by --lossless only: a live-paced run's views are not the exact map's
        missing -= {"live_drift_miou", "live_drift"}
    assert not missing, missing
    assert sum(figures["core_s_per_view"].values()) == pytest.approx(figures["core_s_per_view_sum"], abs=0.01)
    assert set(figures["core_s_per_view"]) == NODES and all(c > 0 for c in figures["core_s_per_view"].values())
    # the encoder and the accumulator work for every view: more CPU than the ingest, which only reads frames
    assert (
        min(figures["core_s_per_view"][n] for n in ("region_encoder", "accumulator"))
        > figures["core_s_per_view"]["ingest"]
    )
    assert figures["frames_sent"] == frames  # the tiny flight, every frame sent once
    assert 0 < figures["frames_aggregated"] == figures["views"] <= frames
    assert figures["frames_dropped"] == frames - figures["frames_aggregated"]
    assert figures["seconds"] == figures["wall_s"] > 0
    assert figures["gaussians"] > 1000 and figures["width"] > 0 and figures["height"] > 0
    assert set(figures["node_ready_s"]) == NODES  # every node's own "ready" line, read from its log
    assert figures["startup_s"] == max(figures["node_ready_s"].values())
    assert all(0 < s < figures["wall_s"] for s in figures["node_ready_s"].values())
    assert 0 < figures["all_reporting_s"] < figures["wall_s"]
    assert set(figures["peak_rss_mb"]) == NODES and all(mb > 10 for mb in figures["peak_rss_mb"].values())
    assert figures["peak_rss_mb_sum"] == pytest.approx(sum(figures["peak_rss_mb"].values()), abs=len(NODES))
    assert set(figures["rss_growth_mb"]) == NODES and set(figures["private_mb_max"]) == NODES
    assert set(figures["memory_series"]) == NODES
    for node in ("region_encoder", "accumulator"):
        assert set(figures["nodes"][node]) == {"busy_ms", "latency_ms", "drops", "handled"}
        assert figures["nodes"][node]["busy_ms"] > 0
    passes = figures["refine_pass_s"]
    assert passes and all(s > 0 for s in passes) and len(passes) == len(figures["refine_pass_views"])
    added = [b - a for a, b in zip([0, *figures["refine_pass_views"]], figures["refine_pass_views"], strict=False)]
    per_view = [s / max(a, 1) for s, a in zip(passes, added, strict=True)]
    assert figures["refine_s_per_added_view"] == pytest.approx(per_view, abs=1e-3)
    assert figures["refine_pass_views"][-1] == figures["views"]
    assert figures["refine_pass_views"] == sorted(figures["refine_pass_views"])
    for key in ("query_relevance_p95_ms", "query_heatmap_p95_ms", "query_heatmap_first_p95_ms"):
        assert figures[key] > 0
    assert figures["query_heatmap_repeat_p95_ms"] > 0
    assert figures["query_heatmap_preview_p95_ms"] > 0 and figures["query_heatmap_preview_first_p95_ms"] > 0
    growth = figures["refine_pass_s_per_view_added"]
    assert set(growth) == {"first_third", "last_third", "ratio", "first_third_per_m_obs", "last_third_per_m_obs",
                           "ratio_obs"}  # fmt: skip
    observations = figures["refine_pass_observations"]
    assert len(observations) == len(passes) and observations == sorted(observations) and observations[0] > 0
    # the server's own time is part of the round trip
    assert 0 < figures["query_relevance_server_p95_ms"] <= figures["query_relevance_p95_ms"]
    assert 0 < figures["query_heatmap_first_server_p95_ms"] <= figures["query_heatmap_first_p95_ms"]


def check_report(out: str) -> None:
    """The printed lines of both modes: start-up, the per-node table, memory, refinement, queries."""
    for line in (
        r"  start-up: slowest node ready [0-9.]+ s after its process started \(",
        r"  accumulator +handled +\d+  peak rate",
        r"  accumulator +peak RSS +\d+ MB  private max",
        r"  sum of the nodes' peaks [0-9,]+ MB",
        r"  store \d+ MB \([0-9.]+ MB per view\), final snapshot",
        r"  refinement passes \(s, views in the map; \* exact, the others folds\): ",
        r"  query relevance +\(round trip\) +p50 +[0-9.]+ ms +p95",
        r"  query heatmap, first query on its view +\(round trip\)",
    ):
        assert re.search(line, out), (line, out)


@pytest.mark.timeout(600)
def test_live_paced_flight_writes_the_documented_figures(tiny, tmp_path, capsys):
    scene, _ = tiny
    out = tmp_path / "graph.json"
    # 1 frame/s: the 12 s stream outlasts the nodes' start-up gap (the ingest is ready seconds
    # before the region encoder and the accumulator on a loaded machine, and frames sent before
    # they are listening are lost: at 4/s every frame was, under load)
    args = ["bench", "graph", "--scene", str(scene), "--rate", "1", "--queries", "3", "--heatmap-queries", "2"]
    args += ["--heatmap-views", "1", "--sample-s", "0.5"]  # one view: a first query and a repeat
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--port", str(free_port()), "--json", str(out)]
    assert main(args) == 0
    figures = json.loads(out.read_text())
    check_common(figures)
    assert figures["lossless"] is False and figures["rate"] == 1 and figures["frames_resent"] == 0
    assert figures["views_per_s"] == pytest.approx(figures["frames_aggregated"] / 12, abs=1e-3)
    printed = capsys.readouterr().out
    assert f"{figures['frames_sent']} frames sent at 1/s" in printed
    assert "sustained aggregation rate" in printed
    check_report(printed)


@pytest.mark.timeout(900)
def test_lossless_flight_and_its_queries_again(tiny, tmp_path, capsys):
    scene, _ = tiny
    out = tmp_path / "lossless.json"
    args = ["bench", "graph", "--scene", str(scene), "--lossless", "--queries", "3", "--heatmap-queries", "2"]
    args += ["--heatmap-views", "1", "--sample-s", "0.2", "--work", str(tmp_path / "run")]
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--port", str(free_port()), "--json", str(out)]
    # live folds on a short flight (where an exact pass would always be the cheaper: the same map)
    args += ["--set", "refiner.period_s=0.5", "--set", "refiner.max_duty=1", "--set", "refiner.fold_limit=1e9"]
    assert main(args) == 0
    figures = json.loads(out.read_text())
    check_common(figures)
    drift = figures["live_drift"]  # the last fold against an exact pass over the same views, both scored
    assert drift is not None and figures["live_drift_miou"] == drift["drift_miou"]
    assert 0 < drift["views"] <= 12 and 0 < drift["version"] and not figures["refine_pass_exact"][-2]
    assert 0 < drift["live_mIoU"] <= 100 and 0 < drift["exact_mIoU"] <= 100
    assert drift["drift_miou"] == pytest.approx(drift["exact_mIoU"] - drift["live_mIoU"], abs=0.011)
    assert figures["lossless"] is True and figures["rate"] is None
    assert figures["views"] == 12 and figures["frames_dropped"] == 0  # lossless: every frame
    assert figures["views_per_s"] == pytest.approx(12 / figures["wall_s"], rel=0.02)
    store = tmp_path / "run" / "store" / "views"
    stored = sum(f.stat().st_size for f in store.rglob("*") if f.is_file())
    assert figures["store_bytes_per_view"] == pytest.approx(stored / 12, abs=1)
    final = json.loads((tmp_path / "run" / "map" / "latest.json").read_text())
    assert figures["snapshot_bytes"] == final["bytes"] == (tmp_path / "run" / "map" / final["file"]).stat().st_size
    exact = figures["refine_pass_exact"]  # the refiner folds its live passes; its first and final are exact
    assert len(exact) == final["version"]  # every pass, also one written between two polls of latest.json
    assert len(exact) == len(figures["refine_pass_s"]) and exact[0] and exact[-1] and final["final"] and final["exact"]
    reads = figures["refine_pass_reads"]  # each pass's observations: taken in, and what each kind would read
    assert len(reads) == len(exact) and 0 < reads[0]["added"] <= figures["refine_pass_observations"][0]
    for r, total in zip(reads, figures["refine_pass_observations"], strict=True):
        assert r["added"] <= r["fold"] and r["exact"] <= total
    printed = capsys.readouterr().out
    assert "12 frames sent lossless (" in printed and "12 views of" in printed
    assert "sustained aggregation rate" not in printed  # no stream rate to aggregate per second of
    check_report(printed)

    # the same run's queries again without the flight: only its query server, on its final map
    again = tmp_path / "queries.json"
    args = ["bench", "graph", "--scene", str(scene), "--queries", "3", "--heatmap-queries", "2", "--queries-only"]
    args += ["--heatmap-views", "2", "--heatmap-spread", "--work", str(tmp_path / "run"), "--json", str(again)]
    args += ["--launch", str(REPO / "launch" / "replay.yaml"), "--port", str(free_port())]
    assert main(args) == 0
    requeried = json.loads(again.read_text())
    missing = documented_keys(requery.__doc__ or "") - set(requeried)
    assert not missing, missing
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
    args = ["bench", "graph", "--scene", str(scene), "--queries-only", "--work", str(tmp_path / "nothing")]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "nothing: no final map" in err and "bench graph --work DIR" in err
    assert not (tmp_path / "nothing" / "logs").exists()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("feed", [["--rate", "1"], ["--lossless"]])
def test_a_bad_override_is_refused_before_anything_starts(tiny, tmp_path, capsys, feed):
    """``--set`` reaches the nodes' parameters: a value a node refuses is the command's one error
    (naming the node and parameter) before any node starts, not a hang in the graph's thread."""
    scene, _ = tiny
    args = ["bench", "graph", "--scene", str(scene), *feed, "--work", str(tmp_path / "run")]
    args += ["--port", str(free_port()), "--launch", str(REPO / "launch" / "replay.yaml")]
    refiner = "(refiner).params: passes must be fold or exact, refresh >= 0 and fold_limit >= 0"
    for setting, error in [
        ("query_server.heatmap_max_side=-1", "(query_server).params: heatmap_max_side must be >= 0"),
        ("refiner.passes=sometimes", f"{refiner}, got 'sometimes', 2.0, 0.85"),
        ("refiner.refresh=-1", f"{refiner}, got 'fold', -1.0, 0.85"),
        ("refiner.fold_limit=-1e-3", f"{refiner}, got 'fold', 2.0, -0.001"),
    ]:
        assert main([*args, "--set", setting]) == 1
        assert error in capsys.readouterr().err
        assert not (tmp_path / "run" / "logs").exists()  # no node was started


@pytest.mark.timeout(60)
def test_the_feed_and_the_sampling_are_checked_before_anything_starts(tiny, tmp_path, capsys):
    scene, _ = tiny
    args = ["bench", "graph", "--scene", str(scene), "--work", str(tmp_path / "run"), "--port", str(free_port())]
    assert main([*args, "--rate", "0"]) == 1
    assert "--rate 0: must be > 0 frames per second (or --lossless)" in capsys.readouterr().err
    assert main([*args, "--sample-s", "-1"]) == 1
    assert "--sample-s -1: must be >= 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # one feed or the other
        main([*args, "--rate", "2", "--lossless"])
    assert "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "run" / "logs").exists()
    assert graph.feed_overrides(True, 1.0) == [
        "ingest.lossless=true",
        "ingest.fast=true",
        "region_encoder.latest_wins=false",
    ]
    assert "ingest.rate_hz=2.5" in graph.feed_overrides(False, 2.5)


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


def test_pass_growth_compares_the_live_passes_of_the_first_and_last_thirds():
    # passes after 1 (the first, exact), 3, 5, 10, 14 (live) and 15 views (the final exact pass)
    seconds = [9.0, 2.0, 2.0, 10.0, 8.0, 30.0]
    live = [False, True, True, True, True, False]
    growth = graph.pass_growth(seconds, [1, 3, 5, 10, 14, 15], live, 15)
    # first third (<= 5 views): 2/2 and 2/2 s per view added; last third (> 10): 8/4
    nothing = {"first_third_per_m_obs": None, "last_third_per_m_obs": None, "ratio_obs": None}
    assert growth == {"first_third": 1.0, "last_third": 2.0, "ratio": 2.0, **nothing}
    # the later views see more of the map: per million observations added the passes are flat
    observations = [1_000_000, 3_000_000, 5_000_000, 15_000_000, 23_000_000, 25_000_000]
    growth = graph.pass_growth(seconds, [1, 3, 5, 10, 14, 15], live, 15, observations)
    assert (growth["first_third_per_m_obs"], growth["last_third_per_m_obs"], growth["ratio_obs"]) == (1.0, 1.0, 1.0)
    assert graph.pass_growth([9.0, 1.0], [1, 12], [False, False], 12) == {
        "first_third": None, "last_third": None, "ratio": None, **nothing
    }  # fmt: skip


def test_heatmap_views_are_the_first_ones_or_spread_over_the_flight():
    from olsplat_nodes.bench.ground_link import pick_views

    names = [f"v{i}" for i in range(10)]
    assert pick_views(names, 4, spread=False) == ["v0", "v1", "v2", "v3"]
    assert pick_views(names, 4, spread=True) == ["v0", "v3", "v6", "v9"]  # first to last, evenly
    assert pick_views(names, 1, spread=True) == ["v0"]
    assert pick_views(names, 20, spread=True) == names  # more than the flight has: every view once


def test_the_bench_modules_import_no_cycle():
    """The benchmark modules' imports of each other (at any depth of a function) form no cycle."""
    folder = REPO / "olsplat_nodes" / "bench"
    edges: dict[str, set[str]] = {}
    for path in folder.glob("*.py"):
        names = edges.setdefault(path.stem, set())
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                if node.module:
                    names.add(node.module.split(".")[0])
                else:
                    names.update(alias.name for alias in node.names)
    for start in edges:
        seen, todo = set(), list(edges[start])
        while todo:
            name = todo.pop()
            assert name != start, f"bench/{start}.py imports itself through {sorted(seen)}"
            if name not in seen:
                seen.add(name)
                todo.extend(edges.get(name, ()))
