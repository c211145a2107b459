"""``olsplat launch NAME|FILE``: run a graph of nodes from a YAML launch file under a supervisor.

A launch file is a path, or the name of one that ships inside the package (``replay``, ``drone``,
``field_drone``, ``ground``, ``field_ground``; ``--list`` shows them with their first line), so
that a pip-installed flight computer has them without the source checkout.
"""

from __future__ import annotations

import argparse

from .launch_options import add_launch_options, add_override_options


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "launch", help="run the nodes of a launch file (restarts, per-node logs, Ctrl-C stops all)",
        description="Exit code: 0 when the exit_when nodes have finished, 1 on failure, 65 / 78 when a node "
        "failed on its input / configuration (not restarted), 130 on Ctrl-C (143 on SIGTERM).",
    )  # fmt: skip
    parser.add_argument("file", nargs="?", metavar="NAME|FILE",
                        help="a shipped launch file by name (replay, drone, field_drone, ground, field_ground) "
                             "or the path of a launch file")  # fmt: skip
    parser.add_argument("--list", action="store_true", help="list the shipped launch files and exit")
    add_override_options(parser)
    parser.add_argument("--check", action="store_true",
                        help="check the launch (file, params, inputs, keys, disk, ports, camera) and start nothing; "
                             "exit 1 on a blocker")  # fmt: skip
    add_launch_options(parser, launch_flag=False)  # --minutes, --rate: the disk row of --check
    parser.set_defaults(run=run, parser=parser)


def run(args: argparse.Namespace) -> int:
    if args.list:
        return list_shipped()
    if args.file is None:
        args.parser.error("give a launch file (a name from --list, or a path)")
    if args.check:
        return check(args)
    from ..launcher import Supervisor, load_launch

    config = load_launch(args.file, overrides=args.overrides, run_dir=args.run_dir)
    return Supervisor(config).run()


def check(args: argparse.Namespace) -> int:
    """``--check``: the launch's pre-flight rows as a table; 1 when one is a blocker."""
    from ..errors import OlsplatInputError
    from ..launcher.preflight import blocked, format_table, launch_rows

    if args.minutes <= 0 or (args.rate is not None and args.rate <= 0):
        raise OlsplatInputError(f"--minutes and --rate must be > 0, got --minutes {args.minutes} --rate {args.rate}")
    rows, _ = launch_rows(args.file, args.overrides, args.run_dir, args.minutes, args.rate)
    print(format_table(rows))
    return 1 if blocked(rows) else 0


def list_shipped() -> int:
    """One line per shipped launch file: its name, its first comment line, and where it is."""
    from ..launcher import shipped_launch_files
    from ..launcher._config import SHIPPED_DIR

    shipped = shipped_launch_files()
    for name, path in shipped.items():
        print(f"{name:<14} {summary(path.read_text())}")
    print(f"(the files are in {SHIPPED_DIR}; copy one to change it)")
    return 0


def summary(text: str) -> str:
    """A launch file's header comment up to its first sentence's end, '(' or ';', at most ~90
    characters (its one-line purpose)."""
    header = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        header.append(line.lstrip("#").strip())
    words = " ".join(header)
    cut = min((i for i in (words.find(". "), words.find("; "), words.find(" (")) if i >= 0), default=len(words))
    words = words[:cut].strip()
    return words if len(words) <= 90 else words[:90].rsplit(" ", 1)[0] + " ..."
