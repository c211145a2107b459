"""The configuration reference, ``docs/configuration.md``, generated from the typed parameters.

Every node declares its parameters as a dataclass, ``Params``, with a default and a comment per
field (``threads: int = 1  # numba threads``). This module renders them as Markdown tables: one
per node of ``nodes.NODES`` and one for a launch file's top-level keys, each row the name, the
type as the parameter checker names it (``olsplat_nodes.params.describe``: ``one of 'a', 'b'``
for choices), the default as YAML writes it, and the field's comment. ``tests/test_docs.py``
fails when the file and the code differ; rewrite it with

    python -m olsplat_nodes.tools.params_doc --update docs/configuration.md
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import io
import json
import sys
import textwrap
import tokenize
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..params import describe

# Fields without a comment of their own take it from the record they are copied into
# (``telemetry_baudrate`` is ``TelemetryConfig.baudrate``).
_HELP_FROM = {"telemetry_": "olsplat_nodes.telemetry.config:TelemetryConfig"}
# LaunchConfig fields that are not keys a user writes (or that the node list documents).
_LAUNCH_SKIP = {"name", "nodes", "source"}

HEADER = """# Configuration reference

Generated from the nodes' typed parameters (the `Params` dataclass of each node, and the
launch file's `LaunchConfig`) by `python -m olsplat_nodes.tools.params_doc --update
docs/configuration.md`; `tests/test_docs.py` fails when this file and the code differ. Do not
edit by hand.

Set a parameter in a launch file's `params`, or on the command line with
`olsplat launch FILE_OR_NAME --set NODE.PARAM=VALUE` (values are YAML: `2`, `true`, `[1, 2]`);
`--set launch.KEY=VALUE` sets a top-level key. Types are checked as YAML gives them: an integer
is accepted for a number and a list for a tuple, nothing else is converted. Ranges across fields
are checked when the launch is validated (`olsplat launch --check`), with the error naming the
value. `{run_dir}`, `{namespace}` and `{name}` in a string are placeholders
([launch/README.md](../launch/README.md)).

A method parameter of the accumulator left `null` keeps the named method's own value. Endpoints
(`*_in`, `*_out`, `*_bind`, `*_endpoint`, `diagnostics`, `connect`) are ZeroMQ addresses,
`topic_*` are topic names (see "remap" in launch/README.md), `hwm` is a socket's high-water mark
in messages, and `threads` 0 means one per core.
"""


def render() -> str:
    """The whole of ``docs/configuration.md``."""
    from ..launcher._config import LaunchConfig
    from ..nodes import NODES
    from ..nodes.base import node_class

    parts = [HEADER]
    launch_rows = [row for row in parameter_rows(LaunchConfig) if row[0] not in _LAUNCH_SKIP]
    parts.append(_section("launch", "A launch file's top-level keys (`--set launch.KEY=VALUE`).", launch_rows))
    for exec_name in NODES:
        cls = node_class(exec_name)
        summary = _first_sentence(sys.modules[cls.__module__].__doc__ or "")  # "ingest: frames from ..."
        parts.append(_section(exec_name, summary, parameter_rows(cls.Params)))
    return "\n".join(parts)


def parameter_rows(cls: type) -> list[tuple[str, str, str, str]]:
    """(name, type, default, help) per field of the dataclass ``cls``, in declaration order."""
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            default = _yaml(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            default = _yaml(f.default_factory())
        else:
            default = "(required)"
        type_ = "a string (a path)" if hints[f.name] is Path else describe(hints[f.name])
        rows.append((f.name, type_, default, field_help(cls, f.name)))
    return rows


def field_help(cls: type, name: str) -> str:
    """The comment of field ``name`` in the source of the class (or base class) that declares it:
    the comments on its own lines, else the comment lines right above it."""
    for owner in cls.__mro__:
        if name in inspect.get_annotations(owner):
            text = _comments(owner).get(name, "")
            if text:
                return text
            break
    for prefix, target in _HELP_FROM.items():
        if name.startswith(prefix):
            module_name, _, class_name = target.partition(":")
            other = getattr(importlib.import_module(module_name), class_name)
            return field_help(other, name[len(prefix) :])
    return ""


def _comments(owner: type) -> dict[str, str]:
    """Field name -> its comment text, from the class's source."""
    source = textwrap.dedent(inspect.getsource(owner))
    comments: dict[int, str] = {}
    code_lines: set[int] = set()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            comments[token.start[0]] = token.string.lstrip("#").strip()
        elif token.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT):
            code_lines.update(range(token.start[0], token.end[0] + 1))
    out: dict[str, str] = {}
    for node in _class_body(ast.parse(source)):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        end = node.end_lineno or node.lineno
        own = [comments[line] for line in range(node.lineno, end + 1) if line in comments]
        if not own:  # the comment-only lines right above the field
            line = node.lineno - 1
            while line in comments and line not in code_lines:
                own.insert(0, comments[line])
                line -= 1
        out[node.target.id] = " ".join(own)
    return out


def _class_body(tree: ast.Module) -> Iterator[ast.stmt]:
    for node in tree.body:
        if isinstance(node, ast.ClassDef):
            yield from node.body
            return


def _section(title: str, summary: str, rows: list[tuple[str, str, str, str]]) -> str:
    lines = [f"## `{title}`", ""]
    if summary:
        lines += [summary, ""]
    if not rows:
        return "\n".join([*lines, "No parameters.", ""])
    lines += ["| parameter | type | default | meaning |", "|---|---|---|---|"]
    for name, type_, default, help_ in rows:
        cells = [f"`{name}`", type_, f"`{default}`" if default else "", help_]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join([*lines, ""])


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _yaml(value: Any) -> str:
    """``value`` as a launch file would write it (flow style)."""
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, tuple):
        value = list(value)
    if isinstance(value, str):
        return json.dumps(value)
    return json.dumps(value, ensure_ascii=False)


def _first_sentence(doc: str) -> str:
    text = " ".join(doc.split())
    end = text.find(". ")
    return (text if end < 0 else text[: end + 1]).replace("``", "`")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m olsplat_nodes.tools.params_doc",
        description="print the configuration reference generated from the nodes' typed parameters",
    )
    parser.add_argument("--update", type=Path, metavar="FILE", help="write it to FILE instead of printing it")
    args = parser.parse_args(argv)
    text = render()
    if args.update is None:
        sys.stdout.write(text)
    else:
        args.update.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
