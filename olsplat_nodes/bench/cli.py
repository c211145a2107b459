"""``olsplat bench TARGET``: one subcommand per benchmark."""

from __future__ import annotations

from . import (
    aggregate,
    change,
    cluster,
    compression,
    diagnose,
    encode,
    frame,
    graph,
    live,
    paper,
    query,
    raster,
    regions,
    robustness,
    structure,
    tune,
)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("bench", help="run a benchmark and print its figures")
    targets = parser.add_subparsers(dest="target", required=True, metavar="TARGET")
    raster.add_parser(targets)
    regions.add_parser(targets)
    encode.add_parser(targets)
    aggregate.add_parser(targets)
    frame.add_parser(targets)
    query.add_parser(targets)
    graph.add_parser(targets)
    cluster.add_parser(targets)
    live.add_parser(targets)
    compression.add_parser(targets)
    robustness.add_parser(targets)
    structure.add_parser(targets)
    tune.add_parser(targets)
    diagnose.add_parser(targets)
    paper.add_parser(targets)
    change.add_parser(targets)
