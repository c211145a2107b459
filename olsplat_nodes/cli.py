"""The ``olsplat`` command. Each subcommand lives in its own module under ``tools/``/``bench/``.

One error path: anticipated failures (``OlsplatInputError``, and the operating system's
``OSError``: a missing file, a folder where a file was expected, no permission, a full disk)
print one line naming the file or option and exit 1; anything else is a bug: its traceback
is printed with a line saying so, and the exit code is 1 as well.
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback

from .errors import EXIT_FAILED, EXIT_INTERRUPTED, OlsplatInputError

EPILOG = """examples:
  olsplat demo --out out                           the whole pipeline on a generated flight
  olsplat sim make --preset tiny --seed 0 --out scene
  olsplat aggregate --scene scene --out maps/ols
  olsplat query --map maps/ols/language_map.npz --scene scene "red roof buildings" --view 3 --out q/
  olsplat COMMAND --help                           options and examples of one command

exit codes: 0 done; 1 bad input, a failed run or no answer (one line says which); 2 the
command line itself (argparse); 130 interrupted (Ctrl-C)."""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("olsplat")
    except PackageNotFoundError:  # running from a source tree that was not installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    from olsplat_sim import cli as sim

    from .bench import cli as bench
    from .tools import aggregate, demo, encode, evaluate, export_clip, ground, keys, launch, query, record, render

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
    except BrokenPipeError:  # the reader of our output went away (`| head`): nothing to say to it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return EXIT_FAILED
    except (OlsplatInputError, OSError) as exc:
        print(f"olsplat {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f"olsplat {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception:
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
