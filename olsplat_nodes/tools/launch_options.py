"""The command-line options every command that names a launch shares (``olsplat launch``,
``doctor --launch``, ``service --launch``): the same words wherever a launch is named."""

from __future__ import annotations

import argparse


def add_override_options(parser: argparse.ArgumentParser) -> None:
    """``--set`` and ``--run-dir`` as ``olsplat launch`` takes them: the same words wherever a
    command names a launch (``launch``, ``doctor --launch``, ``service --launch``)."""
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="NODE.PARAM=VALUE",
                        help="override a node parameter (value parsed as YAML: 2, true, [a, b]); "
                             "launch.KEY=VALUE sets a top-level key, e.g. launch.compose=true; repeatable")  # fmt: skip
    parser.add_argument("--run-dir", help="where the run writes (logs, sockets, outputs); overrides the file's run_dir")


def add_launch_options(parser: argparse.ArgumentParser, launch_flag: bool) -> None:
    """The launch options doctor and ``launch --check`` share (``--launch`` for doctor only:
    ``launch`` takes the file as its argument)."""
    if launch_flag:
        parser.add_argument("--launch", metavar="NAME|FILE", help="also check this launch (a shipped name or a file)")
        add_override_options(parser)
    parser.add_argument(
        "--minutes", type=float, default=30.0, help="flight time the disk must hold, in minutes (with a launch)"
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=None,
        metavar="HZ",
        help="views stored per second for the disk row (default: the launch's frame rate, else 1)",
    )
