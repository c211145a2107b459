"""`olsplat aggregate` and `olsplat eval` end to end on the tiny simulator scene."""

from __future__ import annotations

import json
import shutil

from olsplat_nodes.cli import main


def test_eval_writes_the_documented_json(tiny, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    args = [
        "eval",
        "--scene",
        str(scene),
        "--methods",
        "outlangsplat,projection",
        "--json",
        str(tmp_path / "r.json"),
        "--md",
        str(tmp_path / "r.md"),
    ]
    assert main([*args, "--figures", str(tmp_path / "fig"), "--figure-views", "1"]) == 0
    printed = capsys.readouterr().out
    assert "(paper Table 2)" in printed and "| scene | " in printed  # the tables, one row for the scene
    figures = sorted((tmp_path / "fig").glob("*.png"))
    assert len(figures) == 10 and figures[0].name.startswith("frame_0000_")  # one per query of the first annotated view
    results = json.loads((tmp_path / "r.json").read_text())["methods"]
    assert set(results) == {"outlangsplat", "projection"}
    for r in results.values():
        assert {"mIoU", "mAcc", "loc40", "loc50", "loc60", "per_query", "seconds", "peak_rss_mb"} <= set(r)
        assert 0 < r["mIoU"] <= 100 and "red roof buildings" in r["per_query"]
        assert set(r["per_query"]["road"]) == {"IoU", "acc"}
    assert "| outlangsplat |" in (tmp_path / "r.md").read_text()  # the category table
    assert main(["aggregate", "--scene", str(scene), "--out", str(tmp_path / "m"), "--codebook", "64"]) == 0
    assert (tmp_path / "m" / "language_map.npz").exists()  # the codebook form: queried below like any map
    assert (
        main(["aggregate", "--scene", str(scene), "--out", str(tmp_path / "m")]) == 1
    )  # a used store is not mixed into
    assert "already holds" in capsys.readouterr().err
    query = [
        "query",
        "--map",
        str(tmp_path / "m" / "language_map.npz"),
        "--scene",
        str(scene),
        "--view",
        "3",
        "--out",
        str(tmp_path / "q"),
    ]
    assert main([*query, "red roof buildings"]) == 0
    printed = capsys.readouterr().out
    assert '"red roof buildings":' in printed and "view frame_0003.jpg" in printed
    assert (tmp_path / "q" / "frame_0003_red_roof_buildings_mask.png").exists()
    assert main([*query, "   "]) == 1
    assert "the query text is empty" in capsys.readouterr().err
    assert main(["eval", "--scene", str(tmp_path), "--methods", "outlangsplat"]) == 1
    assert "not a scene folder" in capsys.readouterr().err
    assert main(["eval", "--scene", str(scene), "--methods", "magic"]) == 1
    assert "unknown method 'magic'" in capsys.readouterr().err


def test_eval_over_several_scenes_reports_each_and_the_mean(tiny, tmp_path):
    for name in ("a", "b"):
        shutil.copytree(tiny[0], tmp_path / name)
    args = [
        "eval",
        "--scene",
        str(tmp_path / "a"),
        "--scene",
        str(tmp_path / "b"),
        "--methods",
        "outlangsplat,topk",
        "--json",
        str(tmp_path / "r.json"),
        "--md",
        str(tmp_path / "r.md"),
    ]
    assert main(args) == 0
    document = json.loads((tmp_path / "r.json").read_text())
    assert set(document["scenes"]) == {"a", "b"}
    a, b = (document["scenes"][s]["methods"]["topk"]["mIoU"] for s in "ab")
    assert abs(document["methods"]["topk"]["mIoU"] - (a + b) / 2) < 1e-9
    table = (tmp_path / "r.md").read_text()
    assert "| a | " in table and "| b | " in table and "| Overall | " in table
    # spread over the two scenes, and the paired difference ours minus topk
    topk = document["methods"]["topk"]
    low, high = topk["mIoU_ci95"]
    assert low <= topk["mIoU"] <= high and len(topk["loc50_ci95"]) == 2
    pair = document["paired"]["topk"]
    ours = [document["scenes"][s]["methods"]["outlangsplat"]["mIoU"] for s in "ab"]
    assert abs(pair["dmIoU"] - (ours[0] - a + ours[1] - b) / 2) < 1e-9
    assert set(pair) >= {"dmIoU", "dmIoU_ci95", "dloc50", "dloc50_ci95"} and "Over 2 scenes" in table


def test_eval_feature_ablation_runs_the_3d_branch(tiny, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    args = [
        "eval",
        "--scene",
        str(scene),
        "--methods",
        "outlangsplat",
        "--features",
        "2d3d",
        "--feature-ablation",
        "--json",
        str(tmp_path / "r.json"),
    ]
    assert main(args) == 0
    document = json.loads((tmp_path / "r.json").read_text())
    assert document["methods"]["outlangsplat"]["run"]["features"] == "2d3d"
    features = document["features"]
    assert list(features) == [
        "olsplat-cnn64",
        "olsplat-vit48",
        "w/o 3D fusion",
        "2D-3D fusion (descriptors)",
        "2D-3D fusion (MinkUNet)",
    ]
    fused = features["2D-3D fusion (descriptors)"]
    assert fused["mIoU"] == document["methods"]["outlangsplat"]["mIoU"]  # the same run, aggregated once
    assert features["w/o 3D fusion"]["mIoU"] != fused["mIoU"]  # the 3D branch changed the features
    minkunet = features["2D-3D fusion (MinkUNet)"]["run"]
    assert minkunet["minkunet"].endswith("segcontrast-olsplat.pt") and fused["run"]["minkunet"] is None
    assert "paper Table 6)" in capsys.readouterr().out
    assert main(["eval", "--scene", str(scene), "--lambda-f", "1.5"]) == 1
    assert "--lambda-f must be in [0, 1]" in capsys.readouterr().err
