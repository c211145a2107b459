"""From a node's launch-file entry to the exact params dict it is started with.

Three rewrites, in this order, over the node's effective params (its class's ``Params`` defaults
updated with the launch file's ``params``):

1. Placeholders: ``{run_dir}`` (absolute), ``{namespace}`` and ``{name}`` in strings (also inside
   lists and mappings). In launch-file values an unknown ``{word}`` is an error (a typo such as
   ``{rundir}`` would otherwise become a socket path) and ``{{``/``}}`` stand for literal braces;
   in class defaults only the three known placeholders are touched.
2. Topics: every param whose key starts with ``topic`` and whose value is a string or a list of
   strings holds topic names. Each name is remapped (``remap: {frames: uav1/frames}`` replaces the
   name ``frames``), then put in the node's namespace (``ns/name``) unless it starts with ``/``
   (absolute: the ``/`` is dropped and no namespace added). The empty name (zmq's "every
   topic") is left alone. A remap that matches none of the node's topic names is an error.
3. Composed launches only: ``ipc://PATH`` endpoints become ``inproc://PATH`` (zmq's in-process
   transport needs every socket on one context, which a composed launch shares).

Only the params the launch file set or these rewrites changed are passed to the node; the rest
keep the node's own defaults.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ..errors import OlsplatInputError
from ..nodes.base import node_class
from ._config import LaunchConfig, LaunchFileError, NodeConfig

_PLACEHOLDER = re.compile(r"\{\{|\}\}|\{(\w*)\}")


def resolve_launch(config: LaunchConfig, run_dir: Path) -> dict[str, dict[str, Any]]:
    """The params of every node (name -> params), checked against each node class's typed
    ``Params`` (names, types, ranges). Imports every node class; raises ``LaunchFileError`` naming file and key."""
    resolved = {}
    for i, node in enumerate(config.nodes):
        key = f"nodes[{i}] ({node.name})"
        try:
            cls = node_class(node.exec)
        except OlsplatInputError as exc:
            raise LaunchFileError(f"{config.source}: {key}.exec: {exc}") from exc
        where = f"{config.source}: {key}"
        params = resolve_params(node, cls.defaults(), run_dir=run_dir, namespace=config.namespace_of(node),
                                composed=config.compose, where=where)  # fmt: skip
        try:
            cls.check_params(params, f"{where}.params")  # names, types and ranges, before any node starts
        except OlsplatInputError as exc:
            raise LaunchFileError(str(exc)) from exc
        resolved[node.name] = params
    return resolved


def resolve_params(
    node: NodeConfig,
    defaults: Mapping[str, Any],
    run_dir: Path,
    namespace: str,
    composed: bool,
    where: str = "<launch>",
) -> dict[str, Any]:
    """The params ``node`` is started with (see the module docstring for the rules).
    ``where`` prefixes error messages (``replay.yaml: nodes[0] (ingest)``)."""
    unknown = sorted(set(node.params) - set(defaults))
    if unknown:
        close = difflib.get_close_matches(unknown[0], list(defaults), n=3, cutoff=0.6)
        hint = f"did you mean {' or '.join(close)}? " if close else ""
        known = ", ".join(sorted(defaults)) or "(none)"
        raise LaunchFileError(f"{where}.params.{unknown[0]}: unknown parameter of {node.exec}; {hint}known: {known}")
    values = {"run_dir": str(Path(run_dir).resolve()), "namespace": namespace, "name": node.name}
    params: dict[str, Any] = {}
    for key, default in defaults.items():
        if key in node.params:
            params[key] = _substitute(node.params[key], values, strict=True, where=f"{where}.params.{key}")
        else:
            params[key] = _substitute(default, values, strict=False, where="")
    unused = set(node.remap)
    for key, value in params.items():
        if _is_topic_param(key, value):
            params[key] = _map_names(value, lambda name: _topic(name, node.remap, namespace, unused))
    if unused:
        topics = sorted(
            {t for k, v in params.items() if _is_topic_param(k, v) for t in ([v] if isinstance(v, str) else v)}
        )
        raise LaunchFileError(
            f"{where}.remap.{sorted(unused)[0]}: matches none of the node's topic names (topic* params); they are: "
            f"{', '.join(topics) or '(none)'}"
        )
    if composed:
        params = {key: _map_strings(value, _to_inproc) for key, value in params.items()}
    # `is` first: a default that is not JSON-like (an array, say) must not be compared with ==.
    return {
        key: value
        for key, value in params.items()
        if key in node.params or (value is not defaults[key] and value != defaults[key])
    }


def _substitute(value: Any, values: dict[str, str], strict: bool, where: str) -> Any:
    def one(text: str) -> str:
        def replace(match: re.Match) -> str:
            whole, word = match.group(0), match.group(1)
            if word is None:
                return whole[0] if strict else whole  # "{{" -> "{" only where escapes apply
            if word in values:
                return values[word]
            if strict:
                raise LaunchFileError(
                    f"{where}: unknown placeholder {whole} in {text!r}; known: {{run_dir}}, {{namespace}}, {{name}} "
                    "(write {{ and }} for literal braces)"
                )
            return whole

        return _PLACEHOLDER.sub(replace, text)

    return _map_strings(value, one)


def _is_topic_param(key: str, value: Any) -> bool:
    return key.startswith("topic") and (
        isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value))
    )


def _topic(name: str, remap: Mapping[str, str], namespace: str, unused: set[str]) -> str:
    if name in remap:
        unused.discard(name)
        name = remap[name]
    if not name:
        return name
    if name.startswith("/"):
        return name[1:]
    return f"{namespace}/{name}" if namespace else name


def _to_inproc(text: str) -> str:
    return "inproc://" + text[len("ipc://") :] if text.startswith("ipc://") else text


def _map_names(value: str | list[str], fn: Callable[[str], str]) -> str | list[str]:
    return fn(value) if isinstance(value, str) else [fn(v) for v in value]


def _map_strings(value: Any, fn: Callable[[str], str]) -> Any:
    """``fn`` applied to every string in a JSON-like value (strings, lists, mappings)."""
    if isinstance(value, str):
        return fn(value)
    if isinstance(value, list):
        return [_map_strings(v, fn) for v in value]
    if isinstance(value, tuple):
        return tuple(_map_strings(v, fn) for v in value)
    if isinstance(value, dict):
        return {k: _map_strings(v, fn) for k, v in value.items()}
    return value
