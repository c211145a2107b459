"""``olsplat launch NAME|FILE``: run a graph of nodes from a YAML launch file under a supervisor.

A launch file is a path, or the name of one that ships inside the package (``replay``, ``drone``,
``field_drone``, ``ground``, ``field_ground``; ``--list`` shows them with their first line), so
that a pip-installed flight computer has them without the source checkout.
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "launch", help="run the nodes of a launch file (restarts, per-node logs, Ctrl-C stops all)",
        description="Exit code: 0 when the exit_when nodes have finished, 1 on failure, "
        "130 on Ctrl-C (143 on SIGTERM).",
    )  # fmt: skip
    parser.add_argument("file", nargs="?", metavar="NAME|FILE",
                        help="a shipped launch file by name (replay, drone, field_drone, ground, field_ground) "
                             "or the path of a launch file")  # fmt: skip
    parser.add_argument("--list", action="store_true", help="list the shipped launch files and exit")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="override a node parameter (value parsed as YAML: 2, true, [a, b]); "
                             "launch.KEY=VALUE sets a top-level key, e.g. launch.compose=true; repeatable")  # fmt: skip
    parser.add_argument("--run-dir", help="where the run writes (logs, sockets, outputs); overrides the file's run_dir")
    parser.set_defaults(run=run, parser=parser)


def run(args: argparse.Namespace) -> int:
    if args.list:
        return list_shipped()
    if args.file is None:
        args.parser.error("give a launch file (a name from --list, or a path)")
    from ..launcher import Supervisor, load_launch

    config = load_launch(args.file, overrides=args.overrides, run_dir=args.run_dir)
    return Supervisor(config).run()


def list_shipped() -> int:
    """One line per shipped launch file: its name, its first comment line, and where it is."""
    from ..launcher import shipped_launch_files

    for name, path in shipped_launch_files().items():
        first = next((line.lstrip("# ").strip() for line in path.read_text().splitlines() if line.strip()), "")
        print(f"{name:<14} {first}")
    print(f"(files in {next(iter(shipped_launch_files().values())).parent}; copy one to change it)")
    return 0
