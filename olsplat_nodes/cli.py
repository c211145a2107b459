"""The ``olsplat`` command. Each subcommand lives in its own module under ``tools/``/``bench/``.

User mistakes (``OlsplatInputError``, a missing file) print one line and exit 1; anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys

from .errors import EXIT_FAILED, EXIT_INTERRUPTED, OlsplatInputError


def build_parser() -> argparse.ArgumentParser:
    from olsplat_sim import cli as sim

    from .bench import cli as bench
    from .tools import aggregate, demo, encode, evaluate, export_clip, ground, keys, launch, query, record, render

    parser = argparse.ArgumentParser(prog="olsplat", description="open-vocabulary 3D scene understanding for UAVs")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (
        render,
        demo,
        sim,
        encode,
        aggregate,
        evaluate,
        query,
        launch,
        ground,
        keys,
        export_clip,
        bench,
        record,
    ):
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (OlsplatInputError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        print(f"olsplat {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f"olsplat {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
