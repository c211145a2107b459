"""Launch files: validation names the file and the key; --set overrides; placeholders, remaps and
namespaces reach the nodes' params as documented."""

from __future__ import annotations

from pathlib import Path

import pytest

from olsplat_nodes.launcher import (
    LaunchConfig,
    LaunchFileError,
    load_launch,
    parse_launch,
    resolve_launch,
    resolve_params,
)

from .conftest import NODES, write_launch

TICKER = {"name": "a", "exec": f"{NODES}:Ticker"}


def test_public_api():
    import olsplat_nodes.launcher as launcher

    assert all(hasattr(launcher, name) for name in launcher.__all__)


def test_a_full_file_parses_with_its_defaults(tmp_path):
    path = write_launch(tmp_path, [dict(TICKER, params={"ticks": 2}, remap={"ticks": "x"}, restart="never"),
                                   {"name": "b", "exec": "ingest"}], exit_when=["a"])  # fmt: skip
    config = load_launch(path)
    assert isinstance(config, LaunchConfig) and config.source == str(path)
    assert config.name == "t" and config.run_dir == tmp_path / "run" and not config.compose
    assert config.exit_when == ("a",) and config.stop_timeout_s == 5.0 and config.namespace == ""
    a, b = config.nodes
    assert (a.params, a.remap, a.restart) == ({"ticks": 2}, {"ticks": "x"}, "never")
    assert (b.exec, b.params, b.restart, b.max_restarts, b.restart_delay_s) == ("ingest", {}, "on-failure", 5, 0.5)


def test_defaults_for_name_and_run_dir(tmp_path):
    path = tmp_path / "graph.yaml"
    path.write_text(f"nodes: [{{name: a, exec: '{NODES}:Ticker'}}]\n")
    config = load_launch(path)
    assert config.name == "graph" and config.run_dir == Path("out/graph")
    assert load_launch(path, run_dir=tmp_path / "elsewhere").run_dir == tmp_path / "elsewhere"


@pytest.mark.parametrize(
    ("top", "nodes", "key", "message"),
    [
        ({}, [], "nodes", "non-empty list"),
        ({"colour": 1}, [TICKER], "colour", "unknown key; known: name, run_dir"),
        ({"compose": "yes"}, [TICKER], "compose", "must be true or false, got 'yes'"),
        ({"exit_when": ["nobody"]}, [TICKER], "exit_when", "no node named 'nobody'"),
        ({"exit_when": "a"}, [TICKER], "exit_when", "must be a list of node names"),
        ({"exit_when": ["a"]}, [dict(TICKER, restart="always")], "exit_when", "restart: always, so it never finishes"),
        ({"namespace": "/uav1/"}, [TICKER], "namespace", "invalid value '/uav1/'"),
        ({"stop_timeout_s": -1}, [TICKER], "stop_timeout_s", "must be a number >= 0, got -1"),
        ({"run_dir": ""}, [TICKER], "run_dir", "invalid value '': must not be empty"),
        ({}, [{"exec": "ingest"}], "nodes[0].name", "missing"),
        ({}, [{"name": "a b", "exec": "ingest"}], "nodes[0].name", "invalid value 'a b'"),
        ({}, [{"name": "launch", "exec": "ingest"}], "nodes[0].name", "'launch' is reserved"),
        ({}, [TICKER, TICKER], "nodes[1].name", "duplicate node name 'a'"),
        ({}, [{"name": "a"}], "nodes[0] (a).exec", "missing"),
        ({}, [{"name": "a", "exec": "injest"}], "nodes[0] (a).exec", "unknown executable 'injest'; known: ingest,"),
        ({}, [dict(TICKER, restart="sometimes")], "nodes[0] (a).restart", "must be one of never, on-failure, always"),
        ({}, [dict(TICKER, max_restarts=1.5)], "nodes[0] (a).max_restarts", "must be an integer >= 0, got 1.5"),
        ({}, [dict(TICKER, restart_delay_s="soon")], "nodes[0] (a).restart_delay_s", "must be a number >= 0"),
        ({}, [dict(TICKER, remap={"ticks": 3})], "nodes[0] (a).remap", "must map topic names to topic names"),
        ({}, [dict(TICKER, params=[1])], "nodes[0] (a).params", "must be a mapping"),
        ({}, [dict(TICKER, parameters={})], "nodes[0] (a).parameters", "unknown key; known: name, exec, params"),
        ({}, [dict(TICKER, params={"note": float("nan")})], "nodes[0] (a).params.note", "must be finite"),
    ],
)
def test_validation_errors_name_the_file_and_the_key(tmp_path, top, nodes, key, message):
    path = write_launch(tmp_path, nodes, **top)
    with pytest.raises(LaunchFileError) as err:
        load_launch(path)
    assert str(err.value).startswith(f"{path}: {key}: "), str(err.value)
    assert message in str(err.value)


def test_unreadable_and_non_mapping_files(tmp_path):
    with pytest.raises(LaunchFileError, match=r"missing.yaml: cannot read the launch file"):
        load_launch(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("nodes: [a\n")
    with pytest.raises(LaunchFileError, match=r"bad.yaml: not valid YAML"):
        load_launch(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("- a\n")
    with pytest.raises(LaunchFileError, match=r"list.yaml: the launch file must be a mapping"):
        load_launch(tmp_path / "list.yaml")
    (tmp_path / "date.yaml").write_text(f"nodes: [{{name: a, exec: '{NODES}:Ticker', params: {{note: 2024-01-02}}}}]\n")
    with pytest.raises(
        LaunchFileError, match=r"date.yaml: nodes\[0\] \(a\).params.note: unsupported value .*quote dates"
    ):
        load_launch(tmp_path / "date.yaml")


def test_set_overrides_params_and_top_level_keys(tmp_path):
    path = write_launch(tmp_path, [dict(TICKER, params={"ticks": 5}), {"name": "b", "exec": f"{NODES}:Waiter"}])
    config = load_launch(path, ["a.ticks=2", "a.note=hello world", "b.ignore_stop=true", "launch.compose=true",
                                "launch.exit_when=[a]", "a.period_s=5e-1", "a.crash_once="])  # fmt: skip
    # 5e-1 a number, as YAML 1.2 reads it (``params.load_yaml``)
    assert config.node("a").params == {"ticks": 2, "note": "hello world", "period_s": 0.5, "crash_once": ""}
    assert config.node("b").params == {"ignore_stop": True}
    assert config.compose is True and config.exit_when == ("a",)
    assert load_launch(path).node("a").params == {"ticks": 5}  # the file itself is untouched


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("nobody.ticks=2", "--set 'nobody.ticks=2': no node named 'nobody'; nodes: a (or 'launch'"),
        ("a.ticks", "expected NODE.PARAM=VALUE or launch.KEY=VALUE"),
        ("ticks=2", "expected NODE.PARAM=VALUE or launch.KEY=VALUE"),
        ("launch.colour=red", "unknown top-level key 'colour'"),
        ("launch.nodes=[]", "unknown top-level key 'nodes'"),
        ("a.ticks=[1", "value is not valid YAML"),
        ("launch.compose=maybe", "compose: must be true or false, got 'maybe'"),
    ],
)
def test_bad_overrides_are_errors(tmp_path, override, message):
    path = write_launch(tmp_path, [TICKER])
    with pytest.raises(LaunchFileError) as err:
        load_launch(path, [override])
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value), str(err.value)


def test_placeholders_are_substituted_in_launch_values_and_defaults(tmp_path):
    config = parse_launch({"namespace": "uav1", "run_dir": "rel/run", "nodes": [
        {"name": "talk", "exec": f"{NODES}:Talker", "params": {"period_s": 0.1}},
        {"name": "tick", "exec": f"{NODES}:Ticker",
         "params": {"note": "{name} in {namespace} at {run_dir}, {{literal}}",
                    "extra": ["{run_dir}/x", {"k": "{name}"}]}},
    ]})  # fmt: skip
    run_dir = (tmp_path / "rel" / "run").resolve()
    params = resolve_launch(config, run_dir)
    # The Talker's default endpoint carries {run_dir}: substituted although the file does not set it.
    assert params["talk"] == {"endpoint": f"ipc://{run_dir}/talk.sock", "topic_out": "uav1/chatter", "period_s": 0.1}
    assert params["tick"]["note"] == f"tick in uav1 at {run_dir}, {{literal}}"
    assert params["tick"]["extra"] == [f"{run_dir}/x", {"k": "tick"}]


def test_unknown_placeholder_and_unknown_param_are_errors(tmp_path):
    config = parse_launch({"nodes": [dict(TICKER, params={"note": "ipc://{rundir}/x.sock"})]}, source="f.yaml")
    with pytest.raises(LaunchFileError, match=r"f.yaml: nodes\[0\] \(a\).params.note: unknown placeholder \{rundir\}"):
        resolve_launch(config, tmp_path)
    config = parse_launch({"nodes": [dict(TICKER, params={"tiks": 2})]}, source="f.yaml")
    with pytest.raises(
        LaunchFileError,
        match=r"f.yaml: nodes\[0\] \(a\).params.tiks: unknown parameter of .*Ticker; "
        r"did you mean ticks\? known: crash_how",
    ):
        resolve_launch(config, tmp_path)
    config = parse_launch({"nodes": [dict(TICKER, exec="tests.launcher.nowhere:Ticker")]}, source="f.yaml")
    with pytest.raises(LaunchFileError, match=r"f.yaml: nodes\[0\] \(a\).exec: .*cannot load"):
        resolve_launch(config, tmp_path)


def test_remap_then_namespace_applies_to_topic_params_only(tmp_path):
    def params_of(node: dict, namespace: str = "", composed: bool = False) -> dict:
        config = parse_launch({"nodes": [node]})
        from tests.launcher.nodes_for_tests import Listener, Talker, Ticker

        defaults = {"Talker": Talker, "Listener": Listener, "Ticker": Ticker}[
            node["exec"].rpartition(":")[2]
        ].defaults()
        return resolve_params(config.nodes[0], defaults, tmp_path, namespace, composed)

    talker = {"name": "t", "exec": f"{NODES}:Talker"}
    assert params_of(dict(talker, remap={"chatter": "uav1/talk"}))["topic_out"] == "uav1/talk"
    assert params_of(dict(talker, remap={"chatter": "talk"}), namespace="fleet")["topic_out"] == "fleet/talk"
    assert params_of(dict(talker, remap={"chatter": "/global"}), namespace="fleet")["topic_out"] == "global"
    assert params_of(dict(talker, params={"topic_out": "other"}), namespace="ns")["topic_out"] == "ns/other"
    # Only topic* params are names: the endpoint is not namespaced, and nothing changed is not passed.
    assert params_of(dict(talker, params={"period_s": 0.02})) == {
        "endpoint": f"ipc://{tmp_path.resolve()}/talk.sock",
        "period_s": 0.02,
    }
    # A remap that matches nothing is a typo.
    with pytest.raises(
        LaunchFileError, match=r"remap.chat: matches none of the node's topic names .*they are: chatter"
    ):
        params_of(dict(talker, remap={"chat": "x"}))
    # Composed: ipc:// endpoints become inproc:// with the same path.
    assert params_of(talker, composed=True)["endpoint"] == f"inproc://{tmp_path.resolve()}/talk.sock"


def test_per_node_namespace_overrides_the_launch_namespace(tmp_path):
    config = parse_launch({"namespace": "fleet", "nodes": [
        {"name": "t", "exec": f"{NODES}:Talker", "namespace": "uav2"},
        {"name": "l", "exec": f"{NODES}:Listener"},
    ]})  # fmt: skip
    params = resolve_launch(config, tmp_path)
    assert params["t"]["topic_out"] == "uav2/chatter" and params["l"]["topic_in"] == "fleet/chatter"
