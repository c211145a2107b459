"""Launch files: YAML in, validated dataclasses out. Pure functions, no processes, no zmq.

Every error is a ``LaunchFileError`` whose message starts with the file and the key
(``replay.yaml: nodes[1] (encoder).restart: ...``) so a typo is found without reading code.
``--set`` overrides are applied to the raw mapping *before* validation, so an override is held
to exactly the same rules as the file.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, get_args

import yaml

from ..errors import OlsplatInputError
from ..nodes import NODES
from ..params import load_yaml

RestartPolicy = Literal["never", "on-failure", "always"]
RESTART_POLICIES: tuple[str, ...] = get_args(RestartPolicy)

# Node names become log file names and --set targets: keep them to safe characters.
_NAME = (re.compile(r"[A-Za-z_][A-Za-z0-9_-]*\Z"), "letters, digits, '_' and '-', starting with a letter or '_'")
# A namespace is a topic prefix such as "uav1" or "fleet/uav1".
_NAMESPACE = (
    re.compile(r"([A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*)?\Z"),
    "empty, or words of letters, digits, '_', '-' joined by '/' (no leading or trailing '/')",
)
_PATH = (re.compile(r".*\S"), "must not be empty")
_TOP_KEYS = ("name", "run_dir", "namespace", "compose", "exit_when", "stop_timeout_s", "memory_budget_mb", "nodes")
_NODE_KEYS = ("name", "exec", "params", "remap", "namespace", "restart", "max_restarts", "restart_delay_s")
# `--set launch.KEY=...` sets a top-level key; a node may therefore not be called "launch".
LAUNCH_TARGET = "launch"


class LaunchFileError(OlsplatInputError):
    """A launch file (or a ``--set`` override) that cannot be used. The message names the file
    and the key."""


@dataclass(frozen=True)
class NodeConfig:
    """One node of a launch file, as written there (placeholders not yet substituted)."""

    name: str  # unique in the launch; the log is run_dir/logs/NAME.log
    exec: str  # a NODES name ("ingest") or "module:Class"
    params: dict[str, Any] = field(default_factory=dict)
    remap: dict[str, str] = field(default_factory=dict)  # node's own topic name -> name on the wire
    namespace: str | None = None  # None: the launch's namespace
    restart: RestartPolicy = "on-failure"
    max_restarts: int = 5  # restarts over the whole launch; then the node is given up
    restart_delay_s: float = 0.5  # seconds between an exit and the restart


@dataclass(frozen=True)
class LaunchConfig:
    """A whole launch file. ``source`` is the file name used in error messages."""

    name: str
    nodes: tuple[NodeConfig, ...]
    run_dir: Path = Path("out/run")  # relative paths are taken from the current directory
    namespace: str = ""
    compose: bool = False  # True: one process, nodes as threads sharing a zmq.Context, ipc:// -> inproc://
    exit_when: tuple[str, ...] = ()  # empty: run until Ctrl-C (or until every node has ended)
    stop_timeout_s: float = 5.0  # grace period between SIGTERM and SIGKILL when stopping
    # the launch refuses to start when its memory estimate (``_memory``) exceeds this;
    # 0: what the machine has available at launch (MemAvailable)
    memory_budget_mb: float = 0.0
    source: str = "<launch>"

    def node(self, name: str) -> NodeConfig:
        """The node called ``name``; ``KeyError`` if there is none."""
        for node in self.nodes:
            if node.name == name:
                return node
        raise KeyError(name)

    def namespace_of(self, node: NodeConfig) -> str:
        """The namespace the node runs in: its own if it sets one, else the launch's."""
        return self.namespace if node.namespace is None else node.namespace


# The launch files shipped inside the package (package data), launched by name: ``olsplat launch replay``.
SHIPPED_DIR = Path(__file__).resolve().parent / "files"


def shipped_launch_files() -> dict[str, Path]:
    """The launch files that ship with olsplat: name (``replay``) -> file, sorted by name."""
    return {path.stem: path for path in sorted(SHIPPED_DIR.glob("*.yaml"))}


def find_launch_file(name_or_path: str | Path) -> Path:
    """The launch file a user means: an existing file or a path with a folder as given, else a
    shipped launch file by its name (``replay`` or ``replay.yaml``). An unknown bare name is one
    ``LaunchFileError`` that lists the shipped names."""
    path = Path(name_or_path)
    if path.exists() or len(path.parts) > 1:  # a path: read as given (its errors name it)
        return path
    shipped = shipped_launch_files()
    bare = path.name[: -len(".yaml")] if path.name.endswith(".yaml") else path.name
    if bare in shipped:
        return shipped[bare]
    raise LaunchFileError(
        f"{name_or_path}: no such launch file, nor a shipped launch file of that name "
        f"(shipped: {', '.join(shipped) or 'none'}; olsplat launch --list)"
    )


def load_launch(path: str | Path, overrides: Sequence[str] = (), run_dir: str | Path | None = None) -> LaunchConfig:
    """Read, override (``["ingest.rate_hz=2", "launch.compose=true"]``) and validate a launch
    file, given as a path or as the name of a shipped one (``find_launch_file``). ``run_dir``
    replaces the file's ``run_dir`` (the CLI's ``--run-dir``)."""
    path = find_launch_file(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise LaunchFileError(f"{path}: cannot read the launch file ({exc.strerror or exc})") from exc
    try:
        data = load_yaml(text)
    except yaml.YAMLError as exc:
        raise LaunchFileError(f"{path}: not valid YAML: {exc}") from exc
    config = parse_launch(data, source=str(path), overrides=overrides, default_name=path.stem)
    if run_dir is not None:
        config = _replace_run_dir(config, Path(run_dir))
    return config


def parse_launch(
    data: Any, source: str = "<launch>", overrides: Sequence[str] = (), default_name: str = "launch"
) -> LaunchConfig:
    """Validate a launch mapping (as ``yaml.safe_load`` returns it) into a ``LaunchConfig``."""
    where = _Where(source)
    if not isinstance(data, dict):
        raise LaunchFileError(
            f"{source}: the launch file must be a mapping with a 'nodes' list, got {type(data).__name__}"
        )
    data = apply_overrides(data, overrides, source)
    _check_keys(data, _TOP_KEYS, "", where)
    if "nodes" not in data:
        where.fail("nodes", "missing (a list of nodes)")
    raw_nodes = data["nodes"]
    if not isinstance(raw_nodes, list) or not raw_nodes:
        where.fail("nodes", f"must be a non-empty list of nodes, got {raw_nodes!r}")
    nodes = tuple(_parse_node(raw, f"nodes[{i}]", where) for i, raw in enumerate(raw_nodes))
    names = [node.name for node in nodes]
    for i, name in enumerate(names):
        if name in names[:i]:
            where.fail(f"nodes[{i}].name", f"duplicate node name {name!r}")
    exit_when = _exit_when(data.get("exit_when", []), names, nodes, where)
    return LaunchConfig(
        name=_string(data.get("name", default_name), "name", where, pattern=_NAME),
        nodes=nodes,
        run_dir=Path(
            _string(data.get("run_dir", f"out/{data.get('name', default_name)}"), "run_dir", where, pattern=_PATH)
        ),
        namespace=_string(data.get("namespace", ""), "namespace", where, pattern=_NAMESPACE),
        compose=_boolean(data.get("compose", False), "compose", where),
        exit_when=exit_when,
        stop_timeout_s=_number(data.get("stop_timeout_s", 5.0), "stop_timeout_s", where, minimum=0.0),
        memory_budget_mb=_number(data.get("memory_budget_mb", 0.0), "memory_budget_mb", where, minimum=0.0),
        source=source,
    )


def apply_overrides(data: dict, overrides: Sequence[str], source: str = "<launch>") -> dict:
    """A copy of the raw launch mapping with ``TARGET.KEY=VALUE`` overrides applied.

    TARGET is a node name (KEY is one of its params) or ``launch`` (KEY is a top-level key).
    VALUE is parsed as a YAML scalar or flow collection (``2`` -> int, ``true`` -> bool,
    ``[a, b]`` -> list); an empty VALUE is the empty string.
    """
    where = _Where(source)
    data = dict(data)
    nodes = data.get("nodes")
    nodes = [dict(n) if isinstance(n, dict) else n for n in nodes] if isinstance(nodes, list) else nodes
    if isinstance(nodes, list):
        data["nodes"] = nodes
    for item in overrides:
        target_key, eq, text = item.partition("=")
        target, dot, key = target_key.partition(".")
        if not eq or not dot or not target or not key:
            raise LaunchFileError(f"{where.source}: --set {item!r}: expected NODE.PARAM=VALUE or launch.KEY=VALUE")
        try:
            value = load_yaml(text) if text.strip() else ""
        except yaml.YAMLError as exc:
            raise LaunchFileError(f"{where.source}: --set {item!r}: value is not valid YAML ({exc})") from exc
        if target == LAUNCH_TARGET:
            if key not in _TOP_KEYS or key == "nodes":
                raise LaunchFileError(
                    f"{where.source}: --set {item!r}: unknown top-level key {key!r}; known: "
                    f"{', '.join(k for k in _TOP_KEYS if k != 'nodes')}"
                )
            data[key] = value
            continue
        matches = [n for n in nodes or [] if isinstance(n, dict) and n.get("name") == target]
        if not matches:
            known = [str(n.get("name")) for n in nodes or [] if isinstance(n, dict)]
            raise LaunchFileError(
                f"{where.source}: --set {item!r}: no node named {target!r}; nodes: {', '.join(known)} (or 'launch' "
                "for a top-level key)"
            )
        node = matches[0]
        params = node.get("params") or {}
        if not isinstance(params, dict):
            where.fail(f"nodes ({target}).params", f"must be a mapping, got {params!r}")
        node["params"] = {**params, key: value}
    return data


class _Where:
    """Formats errors as ``FILE: KEY: problem``."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, key: str, problem: str):
        raise LaunchFileError(f"{self.source}: {key}: {problem}" if key else f"{self.source}: {problem}")


def _parse_node(raw: Any, key: str, where: _Where) -> NodeConfig:
    if not isinstance(raw, dict):
        where.fail(key, f"each node must be a mapping with at least 'name' and 'exec', got {raw!r}")
    if "name" not in raw:
        where.fail(f"{key}.name", "missing")
    name = _string(raw["name"], f"{key}.name", where, pattern=_NAME)
    if name == LAUNCH_TARGET:
        where.fail(f"{key}.name", f"{LAUNCH_TARGET!r} is reserved (--set {LAUNCH_TARGET}.KEY sets a top-level key)")
    key = f"{key} ({name})"
    _check_keys(raw, _NODE_KEYS, key, where)
    if "exec" not in raw:
        where.fail(f"{key}.exec", f"missing (one of {', '.join(NODES)}, or module:Class)")
    exec_name = _string(raw["exec"], f"{key}.exec", where)
    if exec_name not in NODES and ":" not in exec_name:
        where.fail(f"{key}.exec", f"unknown executable {exec_name!r}; known: {', '.join(NODES)} (or module:Class)")
    params = raw.get("params") or {}
    if not isinstance(params, dict):
        where.fail(f"{key}.params", f"must be a mapping of parameter names to values, got {params!r}")
    for pname, value in params.items():
        if not isinstance(pname, str):
            where.fail(f"{key}.params", f"parameter names must be strings, got {pname!r}")
        _check_param_value(value, f"{key}.params.{pname}", where)
    remap = raw.get("remap") or {}
    if not isinstance(remap, dict) or not all(
        isinstance(k, str) and isinstance(v, str) and k and v for k, v in remap.items()
    ):
        where.fail(f"{key}.remap", f"must map topic names to topic names (non-empty strings), got {remap!r}")
    restart = raw.get("restart", "on-failure")
    if restart not in RESTART_POLICIES:
        where.fail(f"{key}.restart", f"must be one of {', '.join(RESTART_POLICIES)}, got {restart!r}")
    namespace = raw.get("namespace")
    return NodeConfig(
        name=name,
        exec=exec_name,
        params=dict(params),
        remap=dict(remap),
        namespace=None if namespace is None else _string(namespace, f"{key}.namespace", where, pattern=_NAMESPACE),
        restart=restart,
        max_restarts=int(_number(raw.get("max_restarts", 5), f"{key}.max_restarts", where, minimum=0, integer=True)),
        restart_delay_s=_number(raw.get("restart_delay_s", 0.5), f"{key}.restart_delay_s", where, minimum=0.0),
    )


def _exit_when(raw: Any, names: list[str], nodes: tuple[NodeConfig, ...], where: _Where) -> tuple[str, ...]:
    if raw is None:
        raw = []
    if not isinstance(raw, list) or not all(isinstance(n, str) for n in raw):
        where.fail("exit_when", f"must be a list of node names, got {raw!r}")
    for name in raw:
        if name not in names:
            where.fail("exit_when", f"no node named {name!r}; nodes: {', '.join(names)}")
        if next(n for n in nodes if n.name == name).restart == "always":
            # "always" restarts a node that finished, so the launch could never end on it.
            where.fail("exit_when", f"node {name!r} has restart: always, so it never finishes; use on-failure")
    return tuple(dict.fromkeys(raw))


def _check_keys(raw: dict, known: tuple[str, ...], key: str, where: _Where) -> None:
    for k in raw:
        if k not in known:
            where.fail(f"{key}.{k}" if key else str(k), f"unknown key; known: {', '.join(known)}")


def _check_param_value(value: Any, key: str, where: _Where) -> None:
    """Params travel as JSON to the node process: only JSON-like values, finite numbers."""
    if value is None or isinstance(value, (str, bool, int)):
        return
    if isinstance(value, float):
        if not math.isfinite(value):
            where.fail(key, f"numbers must be finite, got {value!r}")
        return
    if isinstance(value, list):
        for i, item in enumerate(value):
            _check_param_value(item, f"{key}[{i}]", where)
        return
    if isinstance(value, dict):
        for k, item in value.items():
            if not isinstance(k, str):
                where.fail(key, f"mapping keys must be strings, got {k!r}")
            _check_param_value(item, f"{key}.{k}", where)
        return
    where.fail(
        key,
        f"unsupported value {value!r} ({type(value).__name__}); use a string, number, bool, list or mapping (quote "
        "dates and the like)",
    )


def _string(value: Any, key: str, where: _Where, pattern: tuple[re.Pattern, str] | None = None) -> str:
    if not isinstance(value, str):
        where.fail(key, f"must be a string, got {value!r}")
    if pattern is not None and not pattern[0].match(value):
        where.fail(key, f"invalid value {value!r}: {pattern[1]}")
    return value


def _boolean(value: Any, key: str, where: _Where) -> bool:
    if not isinstance(value, bool):
        where.fail(key, f"must be true or false, got {value!r}")
    return value


def _number(value: Any, key: str, where: _Where, minimum: float, integer: bool = False) -> float:
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok or not math.isfinite(value) or value < minimum:
        kind = "an integer" if integer else "a number"
        where.fail(key, f"must be {kind} >= {minimum:g}, got {value!r}")
    return value if integer else float(value)


def _replace_run_dir(config: LaunchConfig, run_dir: Path) -> LaunchConfig:
    return replace(config, run_dir=run_dir)
