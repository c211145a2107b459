"""The run ledger (``evaluate.ledger``): a finished run is found again by what made it and by
nothing else, the first reuse is checked by computing it again, and a stale entry is refused
in one line. The ledger through ``bench paper`` is tested in tests/bench/test_bench_paper.py."""

from __future__ import annotations

import json
import shutil

import pytest

from olsplat_nodes.evaluate.ledger import ALIASES_FILE, LedgerMismatch, RunLedger, run_key, scene_digest
from olsplat_nodes.method import MethodParams
from olsplat_nodes.params import parse_params
from olsplat_nodes.structure.branch import StructureConfig


def _method(**values):
    return parse_params(MethodParams, {"method": "outlangsplat", **values}, "test").resolve()


def _scores(miou: float) -> dict:
    return {"mIoU": miou, "loc50": 50.0, "instances": 12, "per_query": {"road": {"IoU": miou}}}


def test_a_scene_is_known_by_its_content_not_its_place(tiny, tmp_path):
    scene = tmp_path / "elsewhere"
    shutil.copytree(tiny[0], scene)
    assert scene_digest(scene) == scene_digest(tiny[0])
    for written in ("eval", "cache"):  # what runs write there (results, encodings) is not the scene
        (scene / written).mkdir(exist_ok=True)
        (scene / written / "results.json").write_text("{}")
    assert scene_digest(scene) == scene_digest(tiny[0])
    annotation = next((scene / "annotations").glob("*.json"))
    annotation.write_bytes(annotation.read_bytes() + b" ")
    assert scene_digest(scene) != scene_digest(tiny[0])


def test_every_part_of_a_run_is_in_its_key():
    base = run_key("scene", _method(), "a,b", (0.6, 0.4), "files", None)
    others = [
        run_key("other scene", _method(), "a,b", (0.6, 0.4), "files", None),
        run_key("scene", _method(tau_d=0.5), "a,b", (0.6, 0.4), "files", None),
        run_key("scene", _method(topk_scale=0.5), "a,b", (0.6, 0.4), "files", None),
        run_key("scene", _method(), "a", (0.6, 0.4), "files", None),
        run_key("scene", _method(), "a,b", (0.7, 0.3), "files", None),
        run_key("scene", _method(), "a,b", (0.6, 0.4), "other files", None),
        run_key("scene", _method(), "a,b", (0.6, 0.4), "files", StructureConfig()),
        run_key("scene", _method(), "a,b", (0.6, 0.4), "files", StructureConfig(lambda_f=0.6)),
    ]
    keys = [json.dumps(k, sort_keys=True) for k in [base, *others]]
    assert len(set(keys)) == len(keys)
    assert json.loads(json.dumps(base)) == base  # as saved and read back
    # a run at the default render size keeps the key it had before topk_scale existed
    assert "topk_scale" not in base and "topk_scale" not in base["method"]


def test_a_saved_run_is_reused_after_one_check_and_a_stale_one_is_refused(tmp_path, capsys):
    calls: list[str] = []

    def compute(name: str, miou: float):
        def run() -> dict:
            calls.append(name)
            return _scores(miou)

        return run

    first, second = (run_key(f"scene {i}", _method(), "a", None, "files", None) for i in (1, 2))
    ledger = RunLedger(tmp_path / "ledger")
    assert ledger.run(first, compute("first", 60.0), "first") == (_scores(60.0), False)
    assert ledger.run(second, compute("second", 70.0), "second") == (_scores(70.0), False)
    assert len(list((tmp_path / "ledger").glob("*.json"))) == 2 and calls == ["first", "second"]

    again = RunLedger(tmp_path / "ledger")  # another process: the first reuse is computed again ...
    assert again.run(first, compute("first", 60.01), "first") == (_scores(60.0), True)
    assert "computed again matches its entry" in capsys.readouterr().out
    assert again.run(second, compute("second", 99.0), "second") == (_scores(70.0), True)  # ... the others not
    assert calls == ["first", "second", "first"] and (again.reused, again.computed) == (1, 1)

    stale = RunLedger(tmp_path / "ledger")  # the code changed a result: refused, naming the entry
    with pytest.raises(LedgerMismatch, match=r"saved mIoU 60.00 / Loc@50 50.00, computed again 61.00") as error:
        stale.run(first, compute("first", 61.0), "first")
    assert str(stale.path(first)) in str(error.value) and "\n" not in str(error.value)

    (tmp_path / "ledger" / stale.path(second).name).write_text("{")  # torn: computed as if absent
    assert RunLedger(tmp_path / "ledger").run(second, compute("second", 70.0), "second") == (_scores(70.0), False)
    assert RunLedger(None).run(first, compute("first", 1.0)) == (_scores(1.0), False)  # no ledger: always run


def test_a_scene_made_again_on_another_machine_is_found_by_one_run(tmp_path, capsys):
    """Scene "here" is "there" made by the same command elsewhere (other last bits of its poses):
    one run computed here that scores within the tolerance of its entry there makes "there" the
    alias of "here", and the other runs of "there" are reused (after the usual first check)."""
    calls: list[str] = []

    def compute(name: str, miou: float):
        def run() -> dict:
            calls.append(name)
            return _scores(miou)

        return run

    def key(scene: str, tau_d: float = 0.1):
        return run_key(scene, _method(tau_d=tau_d), "a", None, "files", None)

    folder = tmp_path / "ledger"
    made = RunLedger(folder, check=False)
    for scene, miou in (("there", 60.0), ("world 2", 64.0)):  # one seed's scene of two worlds
        made.run(key(scene), compute(scene, miou), "small7 outlangsplat {}")
        made.run(key(scene, 0.3), compute(scene, miou + 1), "small7 outlangsplat {tau_d: 0.3}")
    assert RunLedger(folder).scene_counts() == {"there": 2, "world 2": 2}

    here = RunLedger(folder)
    assert here.run(key("here"), compute("here", 60.02), "small7 outlangsplat {}") == (_scores(60.02), False)
    assert "the same scene made on another machine" in capsys.readouterr().out
    alias = json.loads((folder / ALIASES_FILE).read_text())["here"]
    assert alias["scene"] == "there" and alias["scores"]["mIoU"] == [60.02, 60.0]
    reused = here.run(key("here", 0.3), compute("here", 61.01), "small7 outlangsplat {tau_d: 0.3}")
    assert reused == (_scores(61.0), True)
    assert calls[-2:] == ["here", "here"]  # the alias's first reuse is checked by a run ...
    assert RunLedger(folder).scene_counts()["here"] == 2  # ... and "here" holds both runs
    again = RunLedger(folder, check=False)
    assert again.run(key("here", 0.3), compute("here", 0.0), "x") == (_scores(61.0), True) and again.computed == 0


def test_no_alias_without_exactly_one_entry_within_the_tolerance(tmp_path, capsys):
    def key(scene: str):
        return run_key(scene, _method(), "a", None, "files", None)

    folder = tmp_path / "ledger"
    made = RunLedger(folder)
    for scene, miou in (("one", 60.0), ("two", 60.03), ("far", 70.0)):  # as if made on three machines
        made._write(key(scene), _scores(miou), "small7 outlangsplat {}")
    made._write(key("other label"), _scores(80.0), "small8 outlangsplat {}")
    other_annotations = {**_scores(65.0), "instances": 13}  # a scene of another world: other instances
    made._write(key("other world"), other_annotations, "small7 outlangsplat {}")

    both = RunLedger(folder)  # two scenes within the tolerance: ambiguous, no alias
    both.run(key("new"), lambda: _scores(60.01), "small7 outlangsplat {}")
    assert "no alias for this scene (2 entries" in capsys.readouterr().out
    assert not (folder / ALIASES_FILE).exists()
    # none near: "other world" scores 65.0 too, over other annotations
    RunLedger(folder).run(key("newer"), lambda: _scores(65.0), "small7 outlangsplat {}")
    assert "(0 entries of other scenes within 0.05 mIoU, 5 further)" in capsys.readouterr().out
    RunLedger(folder).run(key("newest"), lambda: _scores(80.0), "small9 outlangsplat {}")  # another label
    assert not (folder / ALIASES_FILE).exists() and RunLedger(folder).aliases() == {}
    assert RunLedger(folder).scene_counts()["newest"] == 1
