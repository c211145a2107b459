"""``python -m olsplat_nodes.nodes EXEC --name NAME --params-json JSON``: one node, one process.

SIGTERM and SIGINT ask the node to stop (it finishes the message in hand); the abrupt death of
the launcher that started it ends the node at once (``_lifeline``). The exit code is what ``run`` returned; a failure
a restart cannot mend (bad input, bad configuration, an endpoint another process holds) exits
with ``EXIT_BAD_INPUT`` or ``EXIT_CONFIG`` after one line ``node NAME: error: REASON`` on stderr
and no traceback; any other exception is a crash (traceback, exit code 1)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading

from ..errors import EXIT_BAD_INPUT, OlsplatInputError, classify_failure
from ._lifeline import die_with_launcher
from .base import node_class


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m olsplat_nodes.nodes")
    parser.add_argument("exec", help="node executable (ingest, region_encoder, ...) or module:Class")
    parser.add_argument("--name", help="node name (default: the executable)")
    parser.add_argument("--params-json", default="{}", help="parameters as one JSON object")
    args = parser.parse_args(argv)
    name = args.name or args.exec
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {name} %(levelname)s %(message)s")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    die_with_launcher(stop.set)
    try:
        params = json.loads(args.params_json)
        if not isinstance(params, dict):
            raise OlsplatInputError("--params-json must be a JSON object")
        node = node_class(args.exec)(name, params)
        return int(node.run(stop) or 0)
    except json.JSONDecodeError as exc:
        print(f"node {name}: error: --params-json is not JSON ({exc})", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:
        failure = classify_failure(exc)
        if failure is None:
            raise  # a crash: the traceback goes to the log, exit code 1, the launcher restarts
        code, reason = failure
        print(f"node {name}: error: {reason}", file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
