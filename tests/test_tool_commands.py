"""The commands no other test runs, each once on tiny inputs (training with a few steps): the
training commands write what the rest of olsplat loads, the benchmarks print their figures.
Their numbers are not judged here (a few steps train nothing); that they run, write and load is."""

from __future__ import annotations

import json

import numpy as np
import pytest

from olsplat_nodes.cli import main

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def trained_encoders(tmp_path_factory):
    out = tmp_path_factory.mktemp("encoders") / "enc"
    assert main(["sim", "train-encoders", "--out", str(out), "--seeds", "1", "--views", "2", "--epochs", "1"]) == 0
    return out


def test_train_encoders_writes_two_encoders_olsplat_loads(trained_encoders, capsys):
    from olsplat_nodes.encoders.onnx_encoder import OnnxEncoder

    for name in ("olsplat-cnn64", "olsplat-vit48"):
        encoder = OnnxEncoder(trained_encoders / name)
        text = np.asarray(encoder.encode_text(["road", "red roof buildings"]))
        assert text.shape[0] == 2 and np.allclose(np.linalg.norm(text, axis=1), 1.0, atol=1e-4)


def test_zeroshot_scores_the_shipped_encoders_and_a_retrained_one_apart(trained_encoders, capsys):
    """A retrained encoder named as a shipped one is its own row (its folder), not the shipped one's."""
    folder = str(trained_encoders / "olsplat-cnn64")
    assert main(["sim", "zeroshot", "--seeds", "0", "--views", "2", "--encoders", folder]) == 0
    rows = {line.split()[0]: line.split()[1] for line in capsys.readouterr().out.splitlines()[3:]}
    assert {"olsplat-cnn64", "olsplat-vit48", folder} <= set(rows)
    assert float(rows["olsplat-cnn64"]) > 0.5  # the shipped encoder, not the one trained for one epoch


def test_train_structure_refuses_a_map_without_objects_and_trains_on_one_with_them(tmp_path, capsys):
    from olsplat_nodes.structure.minkunet import load_minkunet

    assert main(["sim", "train-structure", "--out", str(tmp_path / "t.pt"), "--seeds", "1", "--preset", "tiny",
                 "--steps", "2"]) == 1  # fmt: skip
    assert "no segment above the ground" in capsys.readouterr().err and not (tmp_path / "t.pt").exists()
    out = tmp_path / "s.pt"
    assert main(["sim", "train-structure", "--out", str(out), "--seeds", "1", "--preset", "small", "--steps", "2"]) == 0
    assert "step 2/2: InfoNCE" in capsys.readouterr().out
    assert load_minkunet(out).out_channels > 0


def test_bench_regions_and_encode_print_their_figures(tiny, capsys):
    scene = str(tiny[0])
    assert main(["bench", "regions", "--scene", scene, "--every", "6"]) == 0
    printed = capsys.readouterr().out
    assert "annotated segments" in printed and "seconds per view" in printed
    assert main(["bench", "encode", "--scene", scene]) == 0
    assert "regions:" in capsys.readouterr().out


def test_bench_cluster_writes_its_json(tiny, tmp_path):
    ray = pytest.importorskip("ray", reason="olsplat[cluster] is not installed")  # tests/cluster guards it in CI
    try:
        argv = ["bench", "cluster", "--scene", str(tiny[0]), "--views", "2", "--tile-m", "0", "--workers", "1"]
        assert main([*argv, "--work", str(tmp_path / "w"), "--json", str(tmp_path / "c.json")]) == 0
    finally:
        ray.shutdown()
    (run,) = json.loads((tmp_path / "c.json").read_text())["runs"]
    assert run["views"] == 2 and run["tiles"] == 1 and run["workers"] == 1 and run["observed_gaussians"] > 0
