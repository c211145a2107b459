"""The paper-layout tables of `olsplat eval`."""

from __future__ import annotations

from olsplat_nodes.evaluate.tables import overall, paper_tables


def _scores(miou, loc50, road):
    return {"mIoU": miou, "mAcc": miou + 5, "loc40": loc50 + 3, "loc50": loc50, "loc60": loc50 - 3,
            "per_query": {"road": {"IoU": road, "acc": road + 1}}, "seconds": 10.0, "peak_rss_mb": 100.0}  # fmt: skip


def test_overall_is_the_mean_over_scenes():
    results = {"a": {"m": _scores(60, 50, 70)}, "b": {"m": _scores(70, 40, 80)}}
    merged = overall(results)["m"]
    assert merged["mIoU"] == 65 and merged["loc50"] == 45 and merged["per_query"]["road"]["IoU"] == 75


def test_tables_bold_the_best_and_list_every_scene():
    results = {
        "a": {
            "outlangsplat": _scores(60, 50, 70),
            "projection": _scores(55, 52, 70),
            "outlangsplat-noquality": _scores(58, 49, 60),
        },
        "b": {
            "outlangsplat": _scores(70, 40, 80),
            "projection": _scores(65, 41, 79),
            "outlangsplat-noquality": _scores(66, 39, 75),
        },
    }
    text = paper_tables(results)
    assert "| a | **53.0**/50.0/**47.0** | 55.0/**52.0**/49.0 |" not in text  # loc40 = loc50 + 3: 53 vs 55
    assert "| a | 53.0/50.0/47.0 | **55.0**/**52.0**/**49.0** |" in text
    assert "| Overall | **65.0** | **70.0** | 60.0 | 65.0 |" in text
    assert "| road | " not in text and "| Methods | road |" in text
    assert "| outlangsplat | **75.0** |" in text and "| projection | 74.5 |" in text
    assert "Component ablation" in text and "outlangsplat-noquality" in text.split("Component ablation")[1]
    assert "outlangsplat-noquality" not in text.split("Component ablation")[0]  # ablations stay out of the comparison


def test_feature_and_sweep_tables():
    runs = {}
    for l2d in (0.5, 0.6):
        for lf in (0.6, 0.7):
            scores = _scores(50 + 10 * l2d + 10 * lf, 40, 60)
            scores["run"] = {"kind": "sweep", "weights": [l2d, 1 - l2d], "lambda_f": lf}
            runs[f"lambda_2D={l2d} lambda_f={lf}"] = scores
    runs["olsplat-cnn64"] = {**_scores(50, 40, 60), "run": {"kind": "feature"}}
    runs["2D-3D fusion (MinkUNet)"] = {**_scores(58, 45, 60), "run": {"kind": "feature"}}
    runs["outlangsplat"] = {**_scores(58, 45, 60), "run": {"kind": "method"}}
    text = paper_tables({"s": runs})
    assert "| 0.5 | 0.6/0.7 | 61.0/62.0 | " in text and "| 0.6 | 0.6/0.7 | 62.0/**63.0** | " in text
    feature_table = text.split("paper Table 6")[1]
    assert (
        "| Metrics | olsplat-cnn64 | 2D-3D fusion (MinkUNet) |" in feature_table
        and "| mIoU ↑ | 50.0 | **58.0** |" in feature_table
    )
    assert "lambda_2D" not in text.split("paper Table 6")[0]  # sweep runs stay out of the method tables


def test_sweep_includes_the_first_encoder_alone_and_renders_it():
    from olsplat_nodes.evaluate.runs import LAMBDA_2D, LAMBDA_F, plan_runs

    sweep = [r for r in plan_runs(["outlangsplat"], fusion_sweep=True) if r.kind == "sweep"]
    assert len(sweep) == len(LAMBDA_2D) * len(LAMBDA_F) and 1.0 in LAMBDA_2D
    alone = [r for r in sweep if r.weights[0] == 1.0]
    assert len(alone) == len(LAMBDA_F) and all(r.weights == (1.0, 0.0) and r.structure is not None for r in alone)
    runs = {}
    for l2d, lf, miou in ((0.6, 0.7, 66.0), (0.6, 0.8, 66.5), (1.0, 0.7, 67.0), (1.0, 0.8, 67.5)):
        scores = _scores(miou, 40, 60)
        scores["run"] = {"kind": "sweep", "weights": [l2d, round(1 - l2d, 6)], "lambda_f": lf}
        runs[f"lambda_2D={l2d} lambda_f={lf}"] = scores
    text = paper_tables({"s": runs}).split("paper Table 7")[1]
    assert "| 0.6 | 0.7/0.8 | 66.0/66.5 | " in text and "| 1 | 0.7/0.8 | 67.0/**67.5** | " in text
    assert text.index("| 0.6 |") < text.index("| 1 |")  # rows in lambda_2D order


def test_table_6_over_several_scenes_pairs_each_configuration_with_the_2d_only_run():
    from olsplat_nodes.evaluate.tables import spread
    from olsplat_nodes.tools.evaluate import _document

    results = {}
    for i, (base, fused) in enumerate(((60, 58), (70, 67), (65, 63.5))):  # fused always 1.5-3 below
        results[f"s{i}"] = {
            "outlangsplat": {**_scores(base, 50, 70), "run": {"kind": "method"}},
            "w/o 3D fusion": {**_scores(base, 50, 70), "run": {"kind": "feature"}},
            "2D-3D fusion (MinkUNet)": {**_scores(fused, 50 + i, 70), "run": {"kind": "feature"}},
        }
    text = paper_tables(results)
    table = text.split("Feature configurations, paper Table 6. Over 3 scenes")[1]
    assert "paired: w/o 3D fusion minus the row" in table
    row = next(line for line in table.splitlines() if line.startswith("| 2D-3D fusion (MinkUNet) |"))
    assert "2.2 ± " in row and "(win)" in row  # 2, 3, 1.5: the interval excludes zero
    document = _document(results, overall, spread)
    pair = document["features_paired"]["2D-3D fusion (MinkUNet)"]
    assert abs(pair["dmIoU"] - 6.5 / 3) < 1e-9 and pair["dmIoU_ci95"][0] > 0 and abs(pair["dloc50"] + 1) < 1e-9
    assert document["paired"] == {}  # feature runs are paired with the 2D-only run, not with the methods
