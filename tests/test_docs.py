"""The user documents say what the code does: every ``olsplat`` command of README.md's code blocks
exists with the options it is given, every ``make`` target exists, every table of figures in
docs/ names the command that made it, README.md stays short and free of project history, and
docs/configuration.md is what ``olsplat_nodes.tools.params_doc`` generates from the code."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from olsplat_nodes.cli import build_parser
from olsplat_nodes.tools import params_doc

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
CONFIGURATION = DOCS / "configuration.md"
# Generated from code, not measured: its tables of defaults are not figures.
GENERATED = {CONFIGURATION.name}
HISTORY = re.compile(r"\b(issue|round)s?\s+#?\d+", re.IGNORECASE)
SEPARATORS = {"|", "||", "&&", ";"}
NEAR = 6  # lines around a table where its command must be named


def code_blocks(text: str) -> list[str]:
    """The content of every fenced code block of a Markdown text."""
    return re.findall(r"^```[^\n]*\n(.*?)^```", text, flags=re.MULTILINE | re.DOTALL)


def command_lines(block: str) -> list[list[str]]:
    """Each shell command of a code block as tokens: continuation lines joined, comments and the
    ``$ `` prompt dropped, pipelines and lists cut into their commands."""
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        line = line.strip().removeprefix("$ ")
        if not line or line.startswith("#"):
            continue
        tokens = shlex.split(line, comments=True)
        current: list[str] = []
        for token in [*tokens, ";"]:
            if token in SEPARATORS:
                if current:
                    commands.append(current)
                current = []
            else:
                current.append(token)
    return commands


def readme_commands(program: str) -> list[list[str]]:
    """Every command of README.md's code blocks that runs ``program`` (``.venv/bin/`` allowed)."""
    out = []
    for block in code_blocks(README.read_text(encoding="utf-8")):
        for tokens in command_lines(block):
            if tokens and tokens[0].removeprefix(".venv/bin/") == program:
                out.append(tokens)
    return out


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def resolve(tokens: list[str]) -> tuple[list[str], argparse.ArgumentParser]:
    """The subcommand path of ``olsplat ...`` tokens (``["sim", "make"]``) and its parser."""
    parser = build_parser()
    path: list[str] = []
    for token in tokens[1:]:
        children = _subparsers(parser)
        if token not in children:
            break
        path.append(token)
        parser = children[token]
    return path, parser


OLSPLAT = readme_commands("olsplat")
MAKE = readme_commands("make")


def test_readme_has_commands():
    assert len(OLSPLAT) >= 10 and MAKE, "README.md's code blocks should show olsplat and make commands"


@pytest.mark.parametrize("tokens", OLSPLAT, ids=[" ".join(t)[:60] for t in OLSPLAT])
def test_readme_olsplat_command_exists(tokens):
    """``olsplat <path> --help`` exits 0, and every ``--option`` on the line is one of its options."""
    path, parser = resolve(tokens)
    children = _subparsers(parser)
    rest = tokens[1 + len(path) :]
    assert not children, f"README: `{' '.join(tokens)}`: olsplat {' '.join(path)} has no command {rest[:1]}"
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out), pytest.raises(SystemExit) as exit_:
        build_parser().parse_args([*path, "--help"])
    assert exit_.value.code == 0, f"olsplat {' '.join(path)} --help: {out.getvalue()}"
    options = [t.partition("=")[0] for t in rest if t.startswith("--")]
    unknown = [o for o in options if o not in parser._option_string_actions]
    assert not unknown, f"README: `{' '.join(tokens)}`: olsplat {' '.join(path)} has no option {unknown}"


@pytest.mark.parametrize("tokens", MAKE, ids=[" ".join(t) for t in MAKE])
def test_readme_make_target_exists(tokens):
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    targets = [t for t in tokens[1:] if not t.startswith("-") and "=" not in t]
    assert targets, f"README: `{' '.join(tokens)}` names no target"
    for target in targets:
        assert re.search(rf"^{re.escape(target)}\s*:", makefile, flags=re.MULTILINE), f"Makefile has no target {target}"


def tables(lines: list[str]) -> list[tuple[int, int]]:
    """(first, last) line index of every Markdown table (consecutive lines starting with ``|``,
    the second a separator row)."""
    out = []
    i = 0
    while i < len(lines):
        if lines[i].lstrip().startswith("|"):
            j = i
            while j + 1 < len(lines) and lines[j + 1].lstrip().startswith("|"):
                j += 1
            if j > i and re.fullmatch(r"\s*\|[\s:|-]+\|\s*", lines[i + 1]):
                out.append((i, j))
            i = j + 1
        else:
            i += 1
    return out


def figure_tables_without_command(text: str) -> list[int]:
    """Line numbers (1-based) of the tables with a digit in a data row and no line naming an
    ``olsplat `` or ``make `` command within NEAR lines before or after the table (or in it)."""
    lines = text.splitlines()
    missing = []
    for first, last in tables(lines):
        if not any(re.search(r"\d", row) for row in lines[first + 2 : last + 1]):
            continue
        near = lines[max(0, first - NEAR) : last + 1 + NEAR]
        if not any(re.search(r"\b(olsplat|make) ", line) for line in near):
            missing.append(first + 1)
    return missing


DOC_FILES = sorted(DOCS.glob("*.md"))


@pytest.mark.parametrize("path", DOC_FILES, ids=[p.name for p in DOC_FILES])
def test_figure_tables_name_their_command(path):
    if path.name in GENERATED:
        pytest.skip("generated from the code, no measured figures")
    missing = figure_tables_without_command(path.read_text(encoding="utf-8"))
    assert not missing, f"{path.name}: tables of figures at lines {missing} name no `olsplat ...`/`make ...` command"


def test_figure_table_rule_can_fail():
    bare = "text\n\n| a | b |\n|---|---|\n| x | 1.5 |\n"
    assert figure_tables_without_command(bare) == [3]
    assert figure_tables_without_command("`olsplat bench raster`:\n\n" + bare) == []
    assert figure_tables_without_command("| a |\n|---|\n| no digits |\n") == []


def test_readme_is_short():
    count = len(README.read_text(encoding="utf-8").splitlines())
    assert count <= 300, f"README.md has {count} lines; it is for users: move the rest to docs/"


@pytest.mark.parametrize("path", [README, *DOC_FILES], ids=["README.md", *(p.name for p in DOC_FILES)])
def test_no_project_history(path):
    hits = [
        f"{i}: {line.strip()[:80]}"
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if HISTORY.search(line)
    ]
    assert not hits, f"{path.name} refers to issues or rounds (say what was decided and why): {hits}"


def test_configuration_reference_is_current():
    assert CONFIGURATION.read_text(encoding="utf-8") == params_doc.render(), (
        "docs/configuration.md differs from the code: run "
        "python -m olsplat_nodes.tools.params_doc --update docs/configuration.md"
    )


def test_configuration_reference_documents_every_parameter():
    from olsplat_nodes.nodes import NODES
    from olsplat_nodes.nodes.base import node_class

    text = CONFIGURATION.read_text(encoding="utf-8")
    for exec_name in NODES:
        section = text.split(f"## `{exec_name}`", 1)[1].split("\n## ", 1)[0]
        for name, *_ in params_doc.parameter_rows(node_class(exec_name).Params):
            assert f"| `{name}` |" in section, f"{exec_name}.{name} is missing from docs/configuration.md"
