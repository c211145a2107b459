"""``olsplat doctor``: is this computer ready to fly? One table, a row per thing a flight needs.

Each row is ``ok``, ``warn`` (a flight runs, worse than it could) or ``blocker`` (fix it
first), with its figure and the fix in one line. The machine's rows: Python >= 3.11, cores, the
CPU's vector features, the C kernels loaded (or why not: missing, built for AVX2 on a CPU
without it, OLSPLAT_NATIVE=0), numba's cache warm for this CPU (``olsplat warm-up`` fills it;
a cold cache costs a flight's first minute of frames), onnxruntime's providers, the shipped
models against their SHA256SUMS, the clock source and whether the clock is synchronised. With
``--launch``, the launch's rows too (see ``olsplat launch --check``). Exit 1 when any row is a
blocker, else 0. The checks are ``olsplat_nodes.launcher.preflight``.
"""

from __future__ import annotations

import argparse

from .launch_options import add_launch_options

EPILOG = """examples:
  olsplat doctor
  olsplat doctor --launch field_drone --run-dir /var/lib/olsplat/run --minutes 25
  olsplat doctor --launch replay --set ingest.source=flight/replay.mcap --json doctor.json

exit codes: 0 no blocker (warnings allowed); 1 a blocker (the table says which and the fix)."""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "doctor",
        help="pre-flight check of this computer (and of a launch): ok / warn / blocker per row",
        description=__doc__.split("\n\n", 1)[1],
        epilog=EPILOG,
    )
    add_launch_options(parser, launch_flag=True)
    parser.add_argument("--json", metavar="FILE", help="also write the rows (name, status, figure, fix) to FILE")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..launcher.preflight import blocked, format_table, launch_rows, machine_rows, write_json

    if args.minutes <= 0 or (args.rate is not None and args.rate <= 0):
        raise OlsplatInputError(f"--minutes and --rate must be > 0, got --minutes {args.minutes} --rate {args.rate}")
    if args.launch is None and (args.overrides or args.run_dir):
        raise OlsplatInputError("--set and --run-dir apply to a launch: give --launch NAME|FILE too")
    launch: list = []
    plan = None
    if args.launch is not None:
        launch, plan = launch_rows(args.launch, args.overrides, args.run_dir, args.minutes, args.rate)
    rows = [*machine_rows(plan), *launch]
    print(format_table(rows))
    if args.json:
        write_json(rows, args.json)
    return 1 if blocked(rows) else 0
