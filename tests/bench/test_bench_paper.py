"""``olsplat eval --tuned``, ``bench tune --encoders`` and ``olsplat bench paper`` (the evaluation
protocol's one command) on the tiny preset; the claims' verdict rule on hand-made numbers."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from olsplat_nodes.bench.paper import PEAK, claim_verdict, claims
from olsplat_nodes.cli import main


def _tune_file(path, chosen: dict) -> None:
    """A ``bench tune --json`` document with the given choices (its rows are not read by eval)."""
    methods = {
        name: {"rows": [{"setting": setting, "mIoU": 0.0}], "chosen": setting} for name, setting in chosen.items()
    }
    path.write_text(json.dumps({"scenes": [], "encoders": "olsplat-cnn64", "weights": None, "methods": methods}))


def test_eval_tuned_applies_each_methods_setting_under_set(tiny, tiny_map, tmp_path, capsys):
    """outlangsplat runs with its tuned tau_d (the map differs from the default one), --set wins
    over the file (kappa), projection (not in the file) keeps its defaults and says so."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny[0], scene)
    tune = tmp_path / "tune.json"
    _tune_file(tune, {"outlangsplat": {"tau_d": 0.5, "kappa": 2.0}, "vala": {"gate_mass": 0.9}})
    argv = ["eval", "--scene", str(scene), "--methods", "outlangsplat,projection", "--tuned", str(tune)]
    argv += ["--set", "kappa=8.0", "--work", str(tmp_path / "w"), "--json", str(tmp_path / "r.json")]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert f"projection: not in {tune}, its default setting" in printed
    assert 'outlangsplat: tuned setting {"tau_d": 0.5, "kappa": 2.0}' in printed
    document = json.loads((tmp_path / "r.json").read_text())
    ours, projection = (document["methods"][m]["run"] for m in ("outlangsplat", "projection"))
    assert ours["settings"] == {"tau_d": 0.5, "kappa": 8.0} and ours["tuned"] == {"tau_d": 0.5, "kappa": 2.0}
    assert projection["settings"] == {"kappa": 8.0} and projection["tuned"] is None
    assert document["tuned"] == {"file": str(tune), "chosen": {"outlangsplat": ours["tuned"], "projection": None}}
    # kappa 8 is outlangsplat's default, so only the tuned tau_d separates this map from the default one
    tuned, default = np.load(tmp_path / "w" / "outlangsplat" / "language_map.npz"), np.load(tiny_map)
    assert set(tuned.files) == set(default.files)
    assert any(tuned[k].shape != default[k].shape or not np.array_equal(tuned[k], default[k]) for k in tuned.files)


@pytest.mark.parametrize(
    "content",
    ['{"methods": {"outlangsplat": {"mIoU": 70.0}}}', '{"methods": {"outlangsplat": {"chosen": 3}}}', "[1, 2]", "{"],
)
def test_eval_refuses_a_file_that_is_not_a_tuning_result(tiny, tmp_path, capsys, content):
    (tmp_path / "r.json").write_text(content)
    assert (
        main(["eval", "--scene", str(tiny[0]), "--methods", "outlangsplat", "--tuned", str(tmp_path / "r.json")]) == 1
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a tuning result" in err and str(tmp_path / "r.json") in err
    assert main(["eval", "--scene", str(tiny[0]), "--tuned", str(tmp_path / "none.json")]) == 1
    assert "no such file" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "0,1000"], "--seeds: held-out seeds are < 1000"),
        (["--train-seeds", "1001,999"], "--train-seeds: training seeds are >= 1000"),
        (["--seeds", "3"], "need two held-out seeds or more"),
        (["--seeds", "1,1"], "distinct seeds"),
        (["--methods", "outlangsplat,magic"], "no tuning grid for magic"),
    ],
)
def test_bench_paper_refuses_bad_seeds_before_any_work(tmp_path, capsys, argv, message):
    assert main(["bench", "paper", "--work", str(tmp_path / "w"), *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "w").exists()


def test_bench_paper_end_to_end_on_the_tiny_preset(tmp_path, monkeypatch, capsys):
    """Scenes made, then reused; tuned on the training seed (the choice recorded in the held-out
    runs), Tables 5-7 with intervals and the paper's figures, the claims with verdicts. The
    smallest run that exercises every part: two methods with one setting each, 2-view scenes, a
    Table 7 of the paper's best cell only (which is Table 6's descriptors run: no run of its own)."""
    import olsplat_nodes.evaluate.runs as runs

    monkeypatch.setattr(runs, "LAMBDA_2D", (0.6,))
    monkeypatch.setattr(runs, "LAMBDA_F", (0.7,))
    work = tmp_path / "work"
    argv = ["bench", "paper", "--world", "v1", "--preset", "tiny", "--seeds", "0,1", "--train-seeds", "1000"]
    argv += ["--methods", "outlangsplat,projection", "--grid-limit", "1", "--views", "2", "--work", str(work)]
    assert main([*argv, "--json", str(tmp_path / "p.json"), "--md", str(tmp_path / "p.md")]) == 0
    printed = capsys.readouterr().out
    assert "scenes: 3 to make, 0 reused" in printed and "2 tuning runs" in printed
    assert f"[v1] made {work / 'v1' / 'tiny1000'}" in printed
    tune = json.loads((work / "v1" / "tune.json").read_text())
    assert tune["encoders"] == "olsplat-nadir32,olsplat-oblique48" and tune["weights"] == "0.6,0.4"
    assert set(tune["methods"]) == {"outlangsplat", "projection"} and tune["scenes"] == [str(work / "v1" / "tiny1000")]
    evaluated = json.loads((work / "v1" / "eval.json").read_text())
    assert set(evaluated["scenes"]) == {"tiny0", "tiny1"} and evaluated["tuned"]["file"] == str(
        work / "v1" / "tune.json"
    )
    assert evaluated["methods"]["projection"]["run"]["tuned"] == {}  # its chosen (default) setting, from the file
    document = json.loads((tmp_path / "p.json").read_text())
    world = document["worlds"]["v1"]
    assert document["seeds"] == [0, 1] and world["chosen"] == {"outlangsplat": {}, "projection": {}}
    assert {"table5", "table6", "table7", "claims"} <= set(world)
    verdicts = {row["claim"]: row["verdict"] for row in world["claims"]}
    assert verdicts["its aggregation beats VALA"] == verdicts["λ2D 0.6, λf 0.7 beats the grid's best other cell"]
    assert verdicts["its aggregation beats VALA"] == "not run"  # no vala, no other cell of Table 7
    for claim in (
        "its aggregation beats projection",
        "two fused encoders beat the better one alone",
        "2D-3D fusion (descriptors) beats 2D fusion",
        "2D-3D fusion (MinkUNet) beats 2D fusion",
    ):
        assert verdicts[claim] in ("holds", "fails", "tie"), claim
    ours = [evaluated["scenes"][s]["methods"]["outlangsplat"]["mIoU"] for s in ("tiny0", "tiny1")]
    theirs = [evaluated["scenes"][s]["methods"]["projection"]["mIoU"] for s in ("tiny0", "tiny1")]
    projection = next(row for row in world["claims"] if row["claim"] == "its aggregation beats projection")
    assert projection["difference"] == pytest.approx(np.mean(ours) - np.mean(theirs))
    markdown = (tmp_path / "p.md").read_text()
    for title in (
        "## World v1 (2 held-out seeds",
        "paper Table 5. Over 2 scenes",
        "paper Table 6. Over 2 scenes",
        "(mean over the seeds; paper Table 7)",
        "paper Table 7. Over 2 scenes",
        "**Claims**",
    ):
        assert title in markdown, title
    assert "| projection | " in markdown and "| 65.44 |" in markdown  # the paper's projection figure beside ours
    assert "| 0.6 | 0.7 | " in markdown and "66.2/68.3/62.4 |" in markdown  # Table 7 beside the paper's row
    assert "| 58.99 (RS5M) |" in markdown  # Table 6: the second encoder beside the paper's second (RS5M)
    assert "68.31 vs 65.44 (Projection Agg.): +2.87" in markdown

    # the same command again (as after an interruption): the tuning and each held-out scene reused
    assert main([*argv, "--json", str(tmp_path / "again.json")]) == 0
    again = capsys.readouterr().out
    assert "[v1] tuning reused from" in again and again.count("runs reused from") == 2
    assert json.loads((tmp_path / "again.json").read_text())["worlds"] == document["worlds"]
    results = work / "v1" / "eval" / "tiny0" / "results.json"
    saved = json.loads(results.read_text())
    saved["key"]["runs"][0]["settings"] = {"tau_d": 0.123}  # made with another setting: run again
    results.write_text(json.dumps(saved))
    assert main(argv) == 0
    assert capsys.readouterr().out.count("runs reused from") == 1

    assert main([*argv, "--dry-run"]) == 0  # the same scenes again: reused, nothing run
    printed = capsys.readouterr().out
    assert "scenes: 0 to make, 3 reused" in printed
    assert f"ledger {work / 'ledger'}: [v1] 2/2 tuning runs, 12/12 held-out runs (per seed 6, 6 of 6)" in printed

    # the ledger alone, as on another machine: scenes made again, every run from the ledger but
    # the first reuse of the tuning and of the evaluation, each computed again as a check
    ledger = work / "ledger"
    # tuning: 1 seed x 2 methods; held out, per scene: the 2 methods, each encoder alone and
    # 2D-3D with descriptors and with the MinkUNet (2D fusion is outlangsplat's run, Table 7's
    # only cell the descriptors run)
    assert len(list(ledger.glob("*.json"))) == 2 + 2 * 6
    elsewhere = ["--work", str(tmp_path / "elsewhere"), "--ledger", str(ledger), "--json", str(tmp_path / "e.json")]
    assert main([*argv[: argv.index("--work")], *elsewhere]) == 0
    printed = capsys.readouterr().out
    assert "scenes: 3 to make, 0 reused" in printed and printed.count("computed again matches its entry") == 2
    assert printed.count("from the ledger (") == 2 * 6  # every held-out run (the check's too)
    made_here = json.loads((tmp_path / "e.json").read_text())["worlds"]["v1"]
    assert made_here["tune"] == str(tmp_path / "elsewhere" / "v1" / "tune.json")
    assert {k: v for k, v in made_here.items() if k not in ("tune", "eval")} == {
        k: v for k, v in world.items() if k not in ("tune", "eval")
    }
    assert len(list(ledger.glob("*.json"))) == 2 + 2 * 6  # nothing new
    scene = json.loads((work / "v1" / "tiny1" / "scene.json").read_text())
    (work / "v1" / "tiny1" / "scene.json").write_text(json.dumps({**scene, "seed": 7}))
    assert main([*argv, "--dry-run"]) == 1
    assert "tiny1: holds another scene than `olsplat sim make --preset tiny --seed 1 --world v1`" in (
        capsys.readouterr().err
    )


def test_claim_verdicts_follow_the_protocols_rule():
    held = claim_verdict([70.0, 71.0, 72.0, 69.0, 70.5], [68.0, 69.5, 70.0, 67.0, 69.0])  # +1.5..+2, every seed
    assert held["verdict"] == "holds" and held["difference"] == pytest.approx(1.8) and held["ci95"][0] > 0
    failed = claim_verdict([60.0, 61.0, 60.5], [62.0, 63.5, 62.0])
    assert failed["verdict"] == "fails" and failed["ci95"][1] < 0
    tie = claim_verdict([70.0, 68.0, 71.0, 69.0, 70.0], [69.0, 69.5, 70.0, 69.5, 69.0])  # +1, -1.5, +1, -0.5, +1
    assert tie["verdict"] == "tie" and tie["ci95"][0] < 0 < tie["ci95"][1]
    assert claim_verdict([70.0], [60.0])["verdict"] == "n/a (one seed)"


def test_claims_pick_the_better_single_encoder_and_the_best_other_cell():
    """The fused pair is compared with the single encoder of the higher mean, the paper's best
    cell of Table 7 with the best other cell; a claim whose runs are absent is "not run"."""

    def scene(values: dict[str, float]) -> dict[str, dict]:
        kinds = {"A": "feature", "B": "feature", "w/o 3D fusion": "feature", PEAK: "sweep", "cell": "sweep"}
        return {k: {"mIoU": v, "run": {"kind": kinds.get(k, "method")}} for k, v in values.items()}

    shifts = ((0.0, 0.0), (0.5, 3.0), (-0.5, -1.0))
    results = {
        f"s{i}": scene(
            {"outlangsplat": 70 + i, "projection": 68 + i + e, "A": 50, "B": 60 + d, "w/o 3D fusion": 64 + i}
        )
        | scene({PEAK: 66, "cell": 68 + d})
        for i, (d, e) in enumerate(shifts)
    }
    rows = {row["claim"]: row for row in claims(results)}
    assert rows["its aggregation beats projection"]["verdict"] == "tie"  # +2, -2, +3
    fused = rows["two fused encoders beat the better one alone"]
    assert fused["theirs"] == "B" and fused["verdict"] == "holds" and fused["paper"]["difference"] == 4.91
    peak = rows["λ2D 0.6, λf 0.7 beats the grid's best other cell"]
    assert peak["theirs"] == "cell" and peak["verdict"] == "fails"
    assert rows["its aggregation beats VALA"]["verdict"] == "not run"
    assert rows["2D-3D fusion (descriptors) beats 2D fusion"]["verdict"] == "not run"


def test_encoder_fingerprint_follows_the_model_files(tmp_path):
    """A saved tuning or result is reused only with the same encoder files: the fingerprint
    changes with any model file, not with the derived SHA256SUMS."""
    import shutil

    from olsplat_nodes.encoders.shipped import ASSETS
    from olsplat_nodes.encoders.spec import encoder_fingerprint

    copy = tmp_path / "enc"
    shutil.copytree(ASSETS / "olsplat-nadir32", copy)
    first = encoder_fingerprint(str(copy))
    assert first == encoder_fingerprint(str(copy)) and len(first) == 64
    (copy / "SHA256SUMS").write_text("changed\n")
    assert encoder_fingerprint(str(copy)) == first
    (copy / "encoder.json").write_text((copy / "encoder.json").read_text() + " ")
    assert encoder_fingerprint(str(copy)) != first
    assert encoder_fingerprint("olsplat-nadir32") != encoder_fingerprint("olsplat-nadir32,olsplat-oblique48")
