"""The ``olsplat`` command. Each subcommand lives in its own module under ``tools/``/``bench/``.

One error path: anticipated failures (``OlsplatInputError``, ``RunFailed`` -- a run of the
graph that did not get there -- and the operating system's ``OSError``: a missing file, a folder
where a file was expected, no permission, a full disk; and a module of an optional extra that is
not installed, ``extras.py``) print one line naming the file, option, logs or extra and exit 1;
anything else is a bug: its traceback is printed with a line saying so, and the exit code is 1 as
well.
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback

from .errors import EXIT_FAILED, EXIT_INTERRUPTED, OlsplatInputError, RunFailed
from .extras import EXTRA_OF_MODULE, missing_extra_message

EPILOG = """examples:
  olsplat demo --out out                           the whole pipeline on a generated flight
  olsplat sim make --preset tiny --seed 0 --out scene
  olsplat aggregate --scene scene --out maps/ols
  olsplat query --map maps/ols/language_map.npz --scene scene "red roof buildings" --view 3 --out q/
  olsplat COMMAND --help                           options and examples of one command

exit codes: 0 done; 1 bad input, a failed run or no answer (one line says which); 2 the
command line itself (argparse); 130 interrupted (Ctrl-C)."""


EXAMPLES = {
    "render": "olsplat render --ply scene/map/point_cloud.ply --cameras scene/sparse/0 --view 3 --out r/v3 "
    "--png r/v3.png",
    "demo": "olsplat demo --out out\nolsplat demo --out out --preset small --seed 1",
    "warm-up": "olsplat warm-up",
    "doctor": "olsplat doctor\nolsplat doctor --launch field_drone --run-dir /var/lib/olsplat/run --minutes 25",
    "service": "olsplat service --launch field_drone --run-dir /var/lib/olsplat/run --user uav "
    "> /etc/systemd/system/olsplat.service",
    "sim train-encoders": "olsplat sim train-encoders --out enc --seeds 10 --epochs 8",
    "sim train-pair": "olsplat sim train-pair --work pair\nolsplat sim train-pair --work pair --scenes val --out enc",
    "sim zeroshot": "olsplat sim zeroshot --seeds 0 1 2 --views 12",
    "sim replay": "olsplat sim replay --log scene/replay.mcap --rate 2 --limit 10",
    "encode": "olsplat encode --scene scene --png\n"
    "olsplat encode --scene scene --encoders enc/remoteclip,enc/georsclip --weights 0.6,0.4",
    "aggregate": "olsplat aggregate --scene scene --out maps/ols\nolsplat aggregate --scene scene --method projection "
    "--out maps/proj --set topk_max=24\n"
    "olsplat aggregate --scene flight1 --scene flight2 --tile-m 100 --cluster auto --out maps/city",
    "eval": "olsplat eval --scene small31 --scene small32 --methods outlangsplat,projection,vala",
    "launch": "olsplat launch --list\n"
    "olsplat launch replay --run-dir out/run --set ingest.source=scene/replay.mcap "
    "--set query_server.map=scene/map/point_cloud.ply --set accumulator.map=scene/map/point_cloud.ply "
    "--set refiner.map=scene/map/point_cloud.ply\n"
    "olsplat launch my_graph.yaml --set launch.compose=true",
    "ground query": 'olsplat ground query "red roof buildings" --view 3 --out pictures/\n'
    "olsplat ground query road --connect tcp://DRONE:5600 --client-key ground.key_secret --server-key drone.key",
    "ground status": "olsplat ground status\nolsplat ground status --connect tcp://DRONE:5600 --json",
    "ground web": "olsplat ground web --run out/run\nolsplat ground web --run out/run --map flight/map/point_cloud.ply "
    "--port 8090",
    "keys generate": "olsplat keys generate --out keys --name drone",
    "export-clip": "olsplat export-clip --checkpoint RemoteCLIP-ViT-B-32.pt --vocab bpe_simple_vocab_16e6.txt.gz "
    "--out enc/remoteclip",
    "bench change": "olsplat bench change --preset tiny --seeds 0,1,2,3,4 --train-seeds 1001,1002,1003 "
    "--work change --json change.json --md change.md",
    "bench raster": "olsplat bench raster --gaussians 1000000 --sizes 960x720 --json raster.json",
    "bench regions": "olsplat bench regions --scene small0",
    "bench encode": "olsplat bench encode --scene small0",
    "bench aggregate": "olsplat bench aggregate --scene small0",
    "bench live": "olsplat eval --scene small1 --methods outlangsplat,vala\n"
    "olsplat bench live --scene small1 --methods outlangsplat,vala --every 10 --json live.json\n"
    "olsplat bench live --scene small1 --methods outlangsplat --study",
    "bench frame": "olsplat bench frame --scene small0 --json frame.json",
    "bench query": "olsplat bench query --scene small0 --map maps/small0/language_map.npz",
    "bench graph": "olsplat bench graph --scene small0 --rate 1 --json graph.json\n"
    "olsplat bench graph --scene medium0 --lossless --work run --json scale-medium.json\n"
    "olsplat bench graph --scene medium0 --work run --queries-only --heatmap-spread",
    "bench compression": "olsplat aggregate --scene small0 --out maps/small0\n"
    "olsplat bench compression --scene small0 --aggregated maps/small0",
    "bench robustness": "olsplat bench robustness --scene small31 --confusion 0,0.15,0.3,0.45 --md robust.md\n"
    "olsplat bench robustness --scene small31 --mode lookalike --correlation 1 --confusion 0.3\n"
    "olsplat bench robustness --scene small31 --mode swap --confusion 0.3",
    "bench tune": "olsplat bench tune --scene small1001 --scene small1002 --json tune.json",
    "bench paper": "olsplat bench paper --world v1 --world v2 --seeds 0,1,2,3,4 --train-seeds 1001,1002 "
    "--preset small --encoders olsplat-nadir32,olsplat-oblique48 --weights 0.6,0.4 --work paper --json paper.json "
    "--md paper.md\nolsplat bench paper --work paper --dry-run",
    "bench structure": "olsplat bench structure --scene small0",
    "bench cluster": "olsplat bench cluster --scene medium0 --tile-m 0,100 --workers 1,2 --work /tmp/bc --json c.json",
    "record": "olsplat record --source scene/replay.mcap --out session.mcap --frames 20\n"
    "olsplat record --source-kind exif_folder --source photos/ --out photos.mcap",
    "bag info": "olsplat bag info flight_bag\n"
    "olsplat bag info flight_bag/flight_bag.mcap --set bag_world_frame=odom --check",
}


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Examples kept as written; each option's default shown unless its help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            action.option_strings
            and "default" not in text.lower()
            and not any(default is skip for skip in (None, False, argparse.SUPPRESS))  # 0 is a default to show
            and default != []
            and not isinstance(action, (argparse._HelpAction, argparse._VersionAction))
        ):
            text += " (default: %(default)s)"
        return text


def _finish(parser: argparse.ArgumentParser, path: list[str]) -> None:
    """Give every command the shared formatter and its examples (``EXAMPLES``; the ones a
    command's module wrote itself are kept)."""
    parser.formatter_class = _HelpFormatter
    key = " ".join(path)
    if key in EXAMPLES and not parser.epilog:
        parser.epilog = "examples:\n" + "\n".join(f"  {line}" for line in EXAMPLES[key].split("\n"))
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                _finish(sub, [*path, name])


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("olsplat")
    except PackageNotFoundError:  # running from a source tree that was not installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    from olsplat_sim import cli as sim

    from .bench import cli as bench
    from .tools import (
        aggregate,
        bag,
        demo,
        doctor,
        encode,
        evaluate,
        export_clip,
        ground,
        keys,
        launch,
        map,
        query,
        record,
        render,
        service,
        warm_up,
    )

    parser = argparse.ArgumentParser(
        prog="olsplat",
        description="open-vocabulary 3D scene understanding for UAVs",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"olsplat {_version()}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (
        render,
        demo,
        sim,
        encode,
        aggregate,
        evaluate,
        query,
        map,
        launch,
        ground,
        keys,
        export_clip,
        bench,
        record,
        bag,
        warm_up,
        doctor,
        service,
    ):
        module.add_parser(subparsers)
    _finish(parser, [])
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except BrokenPipeError:  # the reader of our output went away (`| head`): nothing to say to it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return EXIT_FAILED
    except (OlsplatInputError, RunFailed, OSError) as exc:
        print(f"olsplat {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f"olsplat {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        missing = (exc.name or "") if isinstance(exc, ModuleNotFoundError) else ""
        if missing.split(".")[0] in EXTRA_OF_MODULE:  # an optional extra this install does not have
            print(f"olsplat {args.command}: error: {missing_extra_message(missing, 'this command')}", file=sys.stderr)
            return EXIT_FAILED
        traceback.print_exc()
        print(
            f"olsplat {args.command}: internal error (a bug in olsplat, not in your input): please report it "
            "with the command line and the traceback above",
            file=sys.stderr,
        )
        return EXIT_FAILED


def _one_line(exc: BaseException) -> str:
    """The error as one line; an OSError names its file (``strerror: filename``)."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        target = f"{exc.filename} -> {exc.filename2}" if exc.filename2 is not None else str(exc.filename)
        return f"{target}: {exc.strerror}"
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
