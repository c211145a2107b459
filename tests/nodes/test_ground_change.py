"""Change queries over the ground link: a real query server over three flights of the tiny town
(training seed 1005) aggregated once with ``--per-flight`` (f0 = A, f1 = B after the default
changes, f2 = N without any; f2 is "now"). ``olsplat ground query --since`` gives the instances
``olsplat query --since`` gives; the unchanged pair gives none; refusals in one line."""

from __future__ import annotations

import json

import pytest

from olsplat_nodes.cli import main

from ..query.test_change_flights import TINY_CUTS
from .test_ground_cli import ground, query_server, wait_until_up

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def flights(change_flights):
    """The session's three flights of seed 1005 (tests/conftest.py)."""
    return change_flights


def offline(root, since: str, *extra: str) -> list[dict]:
    """``olsplat query --since``'s instances, f2 against ``since``."""
    out = root / "out" / "flights"
    args = ["query", "--map", str(out / "f2"), "--since", str(out / since), "--scene", str(root / "N")]
    assert main([*args, *extra, "--json", str(root / "q.json")]) == 0
    return json.loads((root / "q.json").read_text())["instances"]


def test_ground_query_since_is_olsplat_query_since(ctx, sockdir, flights, capsys):
    tiny = (flights / "N", None)
    with query_server(
        ctx, sockdir, tiny, flights / "out" / "map", flights / "N" / "views", flights=str(flights / "out" / "flights"),
        change_cuts=TINY_CUTS,  # the defaults are chosen on 60-view flights: these 12-view ones need looser cuts
    ) as endpoint:  # fmt: skip
        wait_until_up(capsys, endpoint)
        ask = ["query", "--connect", endpoint, "--timeout", 60, "--json"]
        code, out, err = ground(capsys, *ask, "--since", "f1")
        assert code == 0, err
        answer = json.loads(out)
        assert answer["since"] == "f1" and answer["now"] == "f2" and answer["status"] == "ok"
        expected = offline(flights, "f1", "--change-cuts", TINY_CUTS)
        capsys.readouterr()
        assert len(expected) >= 1
        got = [i for i in answer["instances"] if i["kind"] == "3d"]
        assert [i["n_gaussians"] for i in got] == [i["gaussians"] for i in expected]
        assert [i["score"] for i in got] == [i["score"] for i in expected]
        for mine, theirs in zip(got, expected, strict=True):
            assert mine["centroid"] == pytest.approx(theirs["centre"], abs=1e-4)
            assert mine["latitude"] == pytest.approx(theirs["latitude"], abs=1e-9)

        # the unchanged pair: nothing changed, with or without a text
        code, out, err = ground(capsys, *ask, "--since", "f0")
        assert code == 0 and json.loads(out)["instances"] == [], err
        code, out, err = ground(capsys, *ask, "--since", "f0", "cars", "--gone")
        assert code == 0 and json.loads(out)["instances"] == [], err

        # the printed answer, then refusals: a flight that is not an earlier one, --gone alone
        code, out, _ = ground(capsys, "query", "--connect", endpoint, "--timeout", 60, "--since", "f1")
        assert code == 0 and "what changed since flight f1 (now f2)" in out and "median change score" in out
        code, out, _ = ground(capsys, "query", "--connect", endpoint, "--timeout", 60, "--since", "f2")
        assert code == 1 and "not an earlier flight of f0, f1, f2" in out
        code, _, err = ground(capsys, "query", "--connect", endpoint, "--gone", "cars")
        assert code != 0 and "--gone needs --since" in err
        # an ordinary query is unchanged: no since, no change scores
        code, out, err = ground(capsys, *ask, "trees")
        assert code in (0, 1) and "since" not in json.loads(out), err


def test_bad_change_cuts_stop_the_query_server_before_it_binds(tmp_path):
    from olsplat_nodes.nodes.query_server import QueryServerNode
    from olsplat_nodes.params import ParameterError

    for name, cuts in (("change_cuts", "2.5,1.0,10"), ("text_change_cuts", "0.8,1.6")):
        with pytest.raises(ParameterError, match=rf"{name}: {cuts}: expected CANDIDATE,OBJECT,GAUSSIANS\[,AREA_M2\]"):
            QueryServerNode("qs", {"map": str(tmp_path / "m.ply"), "query_endpoint": "ipc:///nowhere", name: cuts})


def test_ground_web_takes_change_cuts_with_a_run_folder_only(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (tmp_path / "m.ply").write_bytes(b"")  # the cuts are checked before the map is read
    assert main(["ground", "web", "--connect", "tcp://127.0.0.1:1", "--change-cuts", "1.4,1.8,10"]) == 1
    assert "--change-cuts goes with --run" in capsys.readouterr().err
    assert main(["ground", "web", "--run", str(run), "--map", str(tmp_path / "m.ply"), "--change-cuts", "x"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--change-cuts x: expected CANDIDATE,OBJECT,GAUSSIANS" in err
