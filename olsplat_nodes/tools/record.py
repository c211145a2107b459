"""``olsplat record --source-kind KIND [--source PATH] [--set KEY=VALUE ...] --out LOG.mcap``.

Saves the frames of any camera source (the ingest node's parameters, olsplat_nodes/sources/
README.md) to an MCAP replay log, so that a field session can be replayed later, identically,
with ``source_kind: replay``; with ``--format rosbag2``, to a ROS 2 bag folder for ROS tools
(``sources/rosbag_write.py``). Stops at the end of a finite source, after ``--frames`` or
``--seconds``, or on Ctrl-C (what was written so far is kept).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "record",
        help="save the frames of a camera source (replay, exif_folder, depthai) to an MCAP replay log or a ROS 2 bag",
        description="Exit code: 0 when frames were written, 1 when none were (the source's status is printed).",
    )
    parser.add_argument("--source-kind", default="replay", help="replay | exif_folder | depthai (default replay)")
    parser.add_argument("--source", default="", help="replay log or folder (replay, exif_folder)")
    parser.add_argument("--set", dest="params", action="append", default=[], metavar="PARAM=VALUE",
                        help="a source parameter as in the ingest node (depthai_fps=15, "
                             "telemetry_url=/dev/ttyACM0, ...); value parsed as YAML; repeatable. Finite sources "
                             "are read with fast=true unless set")  # fmt: skip
    parser.add_argument("--out", required=True, type=Path, help="the MCAP replay log to write (rosbag2: a new folder)")
    parser.add_argument(
        "--format",
        dest="out_format",
        choices=("mcap", "rosbag2"),
        default="mcap",
        help="mcap: the replay log (default; a cut recording keeps its whole frames); rosbag2: a ROS 2 bag "
        "folder (metadata version 8) for ros2 bag and other ROS tools, whole only once closed",
    )
    parser.add_argument(
        "--storage", choices=("mcap", "sqlite3"), help="the rosbag2 storage (default mcap; with --format rosbag2)"
    )
    parser.add_argument("--frames", type=int, help="stop after this many frames")
    parser.add_argument("--seconds", type=float, help="stop after this many seconds")
    parser.add_argument(
        "--jpeg-quality", type=int, default=95, help="for frames without original JPEG bytes (default 95)"
    )
    parser.set_defaults(run=run)


def parse_params(items: list[str]) -> dict:
    import yaml

    from ..errors import OlsplatInputError

    params = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise OlsplatInputError(f"--set needs PARAM=VALUE, got {item!r}")
        params[key.strip()] = yaml.safe_load(value) if value.strip() else ""
    return params


def run(args: argparse.Namespace) -> int:
    import signal
    import sys
    import threading

    from ..errors import OlsplatInputError
    from ..outputs import output_file, output_folder
    from ..sources import open_source
    from ..sources.record import record

    if args.source_kind in ("replay", "exif_folder") and not args.source:
        raise OlsplatInputError(f"--source-kind {args.source_kind} needs --source (a replay log or a folder)")
    if args.storage is not None and args.out_format != "rosbag2":
        raise OlsplatInputError(f"--storage {args.storage} is for --format rosbag2 (the replay log is one MCAP file)")
    if args.out_format == "rosbag2":
        if args.out.exists():
            raise OlsplatInputError(f"--out {args.out}: already exists; a rosbag2 bag is written to a new folder")
        if args.out.suffix in (".mcap", ".db3"):
            raise OlsplatInputError(
                f"--out {args.out}: a rosbag2 bag is a folder; give a name without {args.out.suffix}"
            )
        output_folder(args.out.parent, given=args.out)  # the bag's partial folder goes next to it
    else:
        args.out = output_file(args.out, ".mcap")  # its folder exists: the log's temporary file goes next to it
    params = {
        "source_kind": args.source_kind,
        **({"source": args.source} if args.source else {}),
        **parse_params(args.params),
    }
    if params["source_kind"] in ("replay", "exif_folder") and "fast" not in params and "rate_hz" not in params:
        params["fast"] = True
    if (args.frames is not None and args.frames <= 0) or (args.seconds is not None and args.seconds <= 0):
        raise OlsplatInputError(f"--frames and --seconds must be positive, got {args.frames}, {args.seconds}")
    try:
        source = open_source(params)
    except ValueError as exc:
        raise OlsplatInputError(str(exc)) from None
    stop = threading.Event()
    previous = (
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        if threading.current_thread() is threading.main_thread()
        else None
    )
    try:
        with source:
            count = record(
                source,
                args.out,
                frames=args.frames,
                seconds=args.seconds,
                stop=stop,
                jpeg_quality=args.jpeg_quality,
                out_format=args.out_format,
                storage=args.storage or "mcap",
                report=lambda line: print(f"olsplat record: {line}", flush=True),
            )
            level, message = source.status()
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    if count == 0:
        print(f"olsplat record: error: no frame recorded (source level {level}: {message})", file=sys.stderr)
        return 1
    print(f"olsplat record: {count} frames -> {args.out}")
    return 0
