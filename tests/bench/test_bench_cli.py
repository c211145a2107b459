"""The aggregation, query and compression benchmarks run end to end on the tiny scene and print
their figures (the figures themselves are not asserted: the machines are shared and noisy)."""

from __future__ import annotations

import re
import shutil

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
    assert main(["bench", "query", "--map", str(tmp_path / "m" / "language_map.npz"), "--scene", str(scene), "--repeats", "5", "--heatmap-repeats", "2"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"relevance\s+p50\s+\d+\.\d ms\s+p95\s+\d+\.\d ms\s+\(5 queries\)", out), out
    assert re.search(r"heatmap\s+p50\s+\d+\.\d ms", out)

    assert main(["bench", "compression", "--scene", str(scene), "--aggregated", str(tmp_path / "m"), "--codebooks", "16"]) == 0
    out = capsys.readouterr().out
    for form in ("float32", "float16", "codebook 16"):
        assert re.search(rf"{form}\s+\d+\.\d B/Gaussian\s+mIoU\s+\d+\.\d", out), out
    assert main(["bench", "compression", "--scene", str(scene), "--aggregated", str(tmp_path / "empty")]) == 1
    assert "no aggregated views" in capsys.readouterr().err
