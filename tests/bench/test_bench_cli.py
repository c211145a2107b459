"""The aggregation, query and compression benchmarks run end to end on the tiny scene and print
their figures (the figures themselves are not asserted: the machines are shared and noisy)."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from olsplat_nodes.cli import main


def test_aggregation_query_and_compression_benchmarks_print_their_figures(tiny, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    assert main(["bench", "aggregate", "--scene", str(scene), "--views", "4"]) == 0
    out = capsys.readouterr().out
    for stage in ("rasterize", "observe", "append"):
        assert re.search(rf"{stage}\s+\d+\.\d+ s/view", out), out
    assert re.search(r"peak RSS\s+\d+ MB", out) and re.search(r"store \d+ MB", out)

    assert main(["aggregate", "--scene", str(scene), "--out", str(tmp_path / "m")]) == 0
    capsys.readouterr()
    assert (
        main(
            [
                "bench",
                "query",
                "--map",
                str(tmp_path / "m" / "language_map.npz"),
                "--scene",
                str(scene),
                "--repeats",
                "5",
                "--heatmap-repeats",
                "2",
                "--preview-views",
                "2",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert re.search(r"relevance\s+p50\s+\d+\.\d ms\s+p95\s+\d+\.\d ms\s+\(5 queries\)", out), out
    assert re.search(r"heatmap\s+p50\s+\d+\.\d ms", out)
    assert re.search(r"preview, decimated\s+p50\s+\d+\.\d ms\s+p95\s+\d+\.\d ms\s+\(2 queries\)", out), out
    # the tiny map is under the preview's decimation: the same Gaussians, the same masks
    assert "preview masks, decimated vs all: IoU 1.00, 1.00 over 2 views" in out

    assert (
        main(["bench", "compression", "--scene", str(scene), "--aggregated", str(tmp_path / "m"), "--codebooks", "16"])
        == 0
    )
    out = capsys.readouterr().out
    for form in ("float32", "float16", "codebook 16"):
        assert re.search(rf"{form}\s+\d+\.\d B/Gaussian\s+mIoU\s+\d+\.\d", out), out
    assert main(["bench", "compression", "--scene", str(scene), "--aggregated", str(tmp_path / "empty")]) == 1
    assert "no aggregated views" in capsys.readouterr().err


def test_structure_benchmark_runs(tiny, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    assert main(["bench", "structure", "--scene", str(scene), "--views", "3", "--minkunet"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"geometric descriptors \d+\.\d s \(75 dims\)", out) and re.search(
        r"MinkUNet \(shipped, \d\.\d\d M parameters\) \d+\.\d s \(24 dims, [\d,]+ points\)", out
    ), out
    assert re.search(r"per view: \d+\.\d+ s", out)


def test_frame_benchmark_prints_every_stage(tiny, tmp_path, capsys):
    import json

    assert main(["bench", "frame", "--scene", str(tiny[0]), "--views", "2", "--json", str(tmp_path / "f.json")]) == 0
    out = capsys.readouterr().out
    for stage in ("regions", "features", "rasterize", "observe", "store", "photo", "total"):
        assert re.search(rf"{stage}\s+\d+\.\d+ s", out), out
    figures = json.loads((tmp_path / "f.json").read_text())
    assert figures["total"] == pytest.approx(sum(v for k, v in figures.items() if k != "total"), abs=1e-3)


def test_raster_benchmark_writes_one_row_per_case(tmp_path, capsys):
    out = tmp_path / "raster.json"
    args = ["bench", "raster", "--gaussians", "2000", "--sizes", "64x48", "96x64", "--repeat", "1", "--skip-reference"]
    assert main([*args, "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert [(r["width"], r["height"]) for r in rows] == [(64, 48), (96, 64)]
    for row in rows:
        assert row["gaussians"] > 1000 and row["s_per_view_topk"] > 0 and row["s_per_view"] > 0
        assert row["evals_per_s_per_core"] == pytest.approx(
            row["evaluations"] / (row["s_per_view_topk"] * row["threads"])
        )
    assert "Mevals/s" in capsys.readouterr().out


def test_tuning_runs_on_training_seeds_only(tiny, tmp_path, capsys):
    """Every setting of a method's grid is run and scored, the best mIoU chosen; a scene of a
    held-out seed (< 1000) is refused before any work."""
    from olsplat_nodes.bench.tune import GRIDS, choose

    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    assert main(["bench", "tune", "--scene", str(scene), "--methods", "projection"]) == 1
    assert "training scenes only" in capsys.readouterr().err
    record = json.loads((scene / "scene.json").read_text())
    (scene / "scene.json").write_text(json.dumps({**record, "seed": 1000}))  # the same scene, as a training seed
    out, table = tmp_path / "tune.json", tmp_path / "tune.md"
    argv = ["bench", "tune", "--scene", str(scene), "--methods", "projection", "--json", str(out), "--md", str(table)]
    assert main(argv) == 0
    result = json.loads(out.read_text())["methods"]["projection"]
    assert [row["setting"] for row in result["rows"]] == GRIDS["projection"]
    best = result["rows"][choose(result["rows"])]
    assert result["chosen"] == best["setting"] and best["per_scene"]["scene"]["mIoU"] == best["mIoU"]
    assert f"chosen: {json.dumps(result['chosen'])}" in capsys.readouterr().out
    rows = [line for line in table.read_text().splitlines() if line.startswith("| projection |")]
    assert len(rows) == len(GRIDS["projection"]) and sum("**" in row for row in rows) == 1


def test_a_default_is_kept_on_a_tie():
    from olsplat_nodes.bench.tune import choose

    assert choose([{"mIoU": 72.41}, {"mIoU": 72.42}, {"mIoU": 72.38}]) == 0  # 0.01 is noise
    assert choose([{"mIoU": 68.4}, {"mIoU": 71.2}, {"mIoU": 71.25}, {"mIoU": 70.0}]) == 1  # 0.05 more is not a win
    assert choose([{"mIoU": 68.4}, {"mIoU": 71.2}, {"mIoU": 71.4}]) == 2


def test_bench_live_replays_a_store_folded_and_exact(tiny, tmp_path, capsys):
    """``bench live`` over the tiny flight's eval store: a pass every 4 views, both live maps
    scored; with a refresh as large as the map every fold is exact, so the two maps agree."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    assert main(["aggregate", "--scene", str(scene), "--out", str(scene / "eval" / "outlangsplat")]) == 0
    capsys.readouterr()
    args = ["bench", "live", "--scene", str(scene), "--methods", "outlangsplat", "--every", "4"]
    assert main([*args, "--refresh", "1e9", "--json", str(tmp_path / "live.json")]) == 0
    figures = json.loads((tmp_path / "live.json").read_text())["scene/outlangsplat"]
    assert figures["views"] == [4, 8, 12] and len(figures["fold_s"]) == len(figures["exact_s"]) == 3
    assert figures["cosine"] == pytest.approx([1.0, 1.0, 1.0], abs=1e-4)
    assert figures["fold_mIoU"] == figures["exact_mIoU"] > 0
    assert "before the final pass: fold" in capsys.readouterr().out
    # the refresh study: every priority's share of the folds' error within the budget; the oracle's the most
    assert main([*args, "--study", "--json", str(tmp_path / "study.json")]) == 0
    study = json.loads((tmp_path / "study.json").read_text())["scene/outlangsplat"]
    captured = study["captured"]
    assert study["views"] == 12 and study["mean_error"] > 0 and len(captured) == 6
    assert all(0 <= c <= 1 for c in captured.values()) and captured["oracle: error / seen"] == max(captured.values())
    assert "spread x share / seen (the refiner's)" in capsys.readouterr().out
    assert main([*args, "--methods", "vala"]) == 1
    assert "no store; run `olsplat eval" in capsys.readouterr().err
