"""Every example command we show a user is accepted as written: the ``examples:`` of every
``olsplat ... --help``, the command lines in the shipped launch files' headers, and the code
blocks of README.md and docs/*.md.

"Accepted" is what can be checked without the user's files: the command line parses (every
subcommand and option exists, every value has the right type), and a launch it names (``olsplat
launch``, ``launch --check``, ``doctor --launch``, ``service --launch``) loads with its ``--set``
overrides and every node's parameters resolve (names, types, ranges). Upper-case words such as
``FLIGHT`` or ``DRONE`` stand for the user's own paths and hosts.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import shutil
from pathlib import Path

import pytest

from olsplat_nodes.cli import build_parser
from olsplat_nodes.launcher import load_launch, resolve_launch, shipped_launch_files
from olsplat_nodes.transport import curve
from tests.test_docs import code_blocks, command_lines

ROOT = Path(__file__).resolve().parents[1]


def _parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, (*path, name))


def help_examples() -> list[tuple[str, list[str]]]:
    """(where, tokens) of every example line in every command's ``--help`` epilog."""
    out = []
    for path, parser in _parsers(build_parser()):
        epilog = parser.epilog or ""
        if "examples:" not in epilog:
            continue
        for line in epilog.split("examples:", 1)[1].splitlines():
            line = re.split(r"\s{3,}", line.strip())[0]  # "olsplat demo --out out    what it does"
            if line.startswith("olsplat ") and "COMMAND" not in line:
                out.append((f"olsplat {' '.join(path)} --help", shlex.split(line, comments=True)))
    return out


def launch_header_examples() -> list[tuple[str, list[str]]]:
    """(where, tokens) of the command lines (``#   olsplat ...``, continued with ``\\``) in the
    header comments of the shipped launch files."""
    out = []
    for name, path in shipped_launch_files().items():
        header = []
        for line in path.read_text().splitlines():
            if not line.startswith("#"):
                break
            header.append(line[1:])
        text = "\n".join(header).replace("\\\n#", " ").replace("\\\n", " ")
        for line in text.splitlines():
            if re.match(r"\s{2,}olsplat ", line):
                out.append((f"launch file {name}", shlex.split(line, comments=True)))
    return out


def markdown_examples() -> list[tuple[str, list[str]]]:
    """(file, tokens) of every ``olsplat`` command in the code blocks of README.md and docs/
    (other lines of a block, such as a folder tree, are not shell)."""
    out = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for block in code_blocks(path.read_text(encoding="utf-8")):
            lines = block.replace("\\\n", " ").splitlines()
            shell = "\n".join(line for line in lines if re.match(r"\s*(\$ )?(\.venv/bin/)?olsplat ", line))
            for tokens in command_lines(shell):
                if tokens and tokens[0].removeprefix(".venv/bin/") == "olsplat":
                    out.append((path.name, tokens))
    return out


EXAMPLES = help_examples() + launch_header_examples() + markdown_examples()


def test_every_source_of_examples_is_read():
    wheres = {where.split(" --help")[0] for where, _ in EXAMPLES}
    assert "olsplat launch" in wheres and "launch file replay" in wheres and "README.md" in wheres, wheres
    assert len(EXAMPLES) >= 60, len(EXAMPLES)


def _launch_of(args: argparse.Namespace) -> tuple[str, list[str], str | None] | None:
    """The launch a parsed command names: (file or name, overrides, run dir), or None."""
    if args.command == "launch" and not getattr(args, "list", False):
        return (args.file, args.overrides, args.run_dir) if args.file else None  # a launch, or --check of it
    if args.command in ("doctor", "service") and getattr(args, "launch", None):
        return args.launch, getattr(args, "overrides", []) or [], getattr(args, "run_dir", None)
    return None


@pytest.mark.parametrize(("where", "tokens"), EXAMPLES, ids=[f"{w}: {' '.join(t)[:70]}" for w, t in EXAMPLES])
def test_example_is_accepted_as_written(where, tokens, tmp_path, monkeypatch):
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            args = build_parser().parse_args(tokens[1:])
    except SystemExit:
        pytest.fail(f"{where}: `{' '.join(tokens)}` is refused: {out.getvalue().strip().splitlines()[-1:]}")
    launch = _launch_of(args)
    if launch is None:
        return
    target, overrides, run_dir = launch
    if not Path(str(target)).exists() and str(target) not in shipped_launch_files():
        pytest.skip(f"{target}: the user's own launch file")
    # in a folder where the key pairs exist as the launch files' headers make them
    monkeypatch.chdir(tmp_path)
    for name in ("drone", "ground"):
        curve.generate(tmp_path / "keys", name)
    (tmp_path / "keys" / "allowed").mkdir()
    shutil.copy(tmp_path / "keys" / "ground.key", tmp_path / "keys" / "allowed")
    config = load_launch(target, overrides=overrides, run_dir=str(tmp_path / "run"))
    resolve_launch(config, Path(run_dir or tmp_path / "run"))
