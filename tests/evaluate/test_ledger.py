"""The run ledger (``evaluate.ledger``): a finished run is found again by what made it and by
nothing else, the first reuse is checked by computing it again, and a stale entry is refused
in one line. The ledger through ``bench paper`` is tested in tests/bench/test_bench_paper.py."""

from __future__ import annotations

import json
import shutil

import pytest

from olsplat_nodes.evaluate.ledger import LedgerMismatch, RunLedger, run_key, scene_digest
from olsplat_nodes.method import MethodParams
from olsplat_nodes.params import parse_params
from olsplat_nodes.structure.branch import StructureConfig


def _method(**values):
    return parse_params(MethodParams, {"method": "outlangsplat", **values}, "test").resolve()


def _scores(miou: float) -> dict:
    return {"mIoU": miou, "loc50": 50.0, "per_query": {"road": {"IoU": miou}}}


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
