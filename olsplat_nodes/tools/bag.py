"""``olsplat bag info BAG [--set bag_PARAM=VALUE ...] [--check]``: a ROS 2 bag as the camera source sees it.

Prints the storage, time span, every topic (type, count, role for the source, and for images
and CameraInfo what the first message says), the tf tree (all of ``/tf_static`` and the first
500 ``/tf`` messages), the frame names it carries, which topics and tf chain the replay source
would read, and the ``--set`` lines that read it. ``--check`` reads every frame as the source
does (decoding, intrinsics, poses) and counts them. Exit 1 with one line naming the bag (and
topic and message) when the source could not read it.
"""

from __future__ import annotations

import argparse
import datetime as dt


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("bag", help="ROS 2 bags as a camera source: what a bag holds and how it replays")
    actions = parser.add_subparsers(dest="bag_command", required=True, metavar="ACTION")
    info = actions.add_parser(
        "info",
        help="topics, tf tree and what the replay source would read from a rosbag2 folder, .mcap or .db3",
        description=__doc__.split("\n\n", 1)[1],
    )
    info.add_argument("bag", help="a rosbag2 folder (metadata.yaml inside), its .mcap or its .db3")
    info.add_argument("--set", dest="params", action="append", default=[], metavar="PARAM=VALUE",
                      help="a bag_* source parameter (bag_image_topic=/camera/image_raw, ...); repeatable")  # fmt: skip
    info.add_argument("--check", action="store_true", help="also read every frame as the source does")
    info.set_defaults(run=run)


def _time(ns: int) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, dt.UTC).isoformat(timespec="milliseconds")


def _print_summary(summary, params: dict) -> None:
    print(f"bag: {summary.path} (storage {summary.storage}, ros_distro {summary.ros_distro or 'not given'})")
    print(f"time: {_time(summary.start_ns)} + {summary.duration_ns / 1e9:.3f} s, {summary.message_count} messages")
    print("topics:")
    width = max((len(t.topic) for t in summary.topics), default=0)
    type_width = max((len(t.msgtype) for t in summary.topics), default=0)
    for t in summary.topics:
        line = f"  {t.topic:<{width}}  {t.msgtype:<{type_width}}  {t.count:>6}  {t.role or '-':<11} {t.first}"
        print(line.rstrip())
    print(f"tf tree (/tf_static and the first {summary.tf_messages_read} /tf messages):")
    for line in summary.tf_tree or ["(no tf)"]:
        print(f"  {line}")
    print(f"frame names: {summary.frame_names or 'none (frame_0000.jpg, ...)'}")
    s = summary.selection
    if s is None:
        return
    pose = f"tf {params.get('bag_world_frame', 'map')} -> {summary.camera_frame or '?'}" if not s.pose else s.pose
    print(f"reads: images {s.image}, intrinsics {s.camera_info}, pose {pose}")
    sets = " ".join(f"--set {k}={v}" for k, v in params.items())
    print(f"record: olsplat record --source-kind replay --source {summary.path} --out flight.mcap {sets}".rstrip())
    launch = " ".join(f"--set ingest.{k}={v}" for k, v in {"source": summary.path, **params}.items())
    print(f"in a launch: {launch}")


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError, SceneFormatError
    from ..params import parse_params
    from ..sources.open import SourceParams
    from ..sources.rosbag import read_bag
    from ..sources.rosbag_info import bag_summary
    from .record import parse_params as parse_sets

    params = parse_sets(args.params)
    unknown = sorted(k for k in params if not k.startswith("bag_"))
    if unknown:
        raise OlsplatInputError(f"--set takes bag_* parameters here, got {', '.join(unknown)}")
    parse_params(SourceParams, params, "bag")  # types and names checked as the ingest node checks them
    summary = bag_summary(args.bag, params)
    _print_summary(summary, params)
    if summary.problem:
        raise SceneFormatError(summary.path, summary.problem)
    if args.check:
        warnings: list[str] = []
        count = sum(1 for _ in read_bag(args.bag, params, warnings.append))
        print(f"check: {count} frames read" + (f"; {warnings[0]}" if warnings else ""))
    return 0
