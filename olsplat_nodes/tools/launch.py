"""``olsplat launch FILE``: run a graph of nodes from a YAML launch file under a supervisor."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "launch", help="run the nodes of a launch file (restarts, per-node logs, Ctrl-C stops all)",
        description="Exit code: 0 when the exit_when nodes have finished, 1 on failure, "
        "130 on Ctrl-C (143 on SIGTERM).",
    )  # fmt: skip
    parser.add_argument("file", type=Path, help="launch file, e.g. launch/replay.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="override a node parameter (value parsed as YAML: 2, true, [a, b]); "
                             "launch.KEY=VALUE sets a top-level key, e.g. launch.compose=true; repeatable")  # fmt: skip
    parser.add_argument(
        "--run-dir", type=Path, help="where the run writes (logs, sockets, outputs); overrides the file's run_dir"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..launcher import Supervisor, load_launch

    config = load_launch(args.file, overrides=args.overrides, run_dir=args.run_dir)
    return Supervisor(config).run()
