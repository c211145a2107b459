"""``python -m olsplat_msgs [--update msgs/README.md]``: print the README tables generated from
``schema.yaml``, or rewrite the generated blocks of a README in place."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .schema import header_table, message_tables, record_tables, update_readme


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m olsplat_msgs", description="print or update the README tables generated from schema.yaml"
    )
    parser.add_argument(
        "--update", type=Path, metavar="README", help="rewrite the generated blocks of this file in place"
    )
    args = parser.parse_args(argv)
    if args.update is None:
        print(header_table() + "\n" + message_tables() + "\n" + record_tables(), end="")
    else:
        args.update.write_text(update_readme(args.update.read_text(encoding="utf-8")), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
