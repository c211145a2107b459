"""``python -m olsplat_nodes.nodes EXEC --name NAME --params-json JSON``: one node, one process.

SIGTERM and SIGINT ask the node to stop (it finishes the message in hand); the exit code is
what ``run`` returned, 1 for a start-up error (unknown parameter, missing file)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading

from ..errors import OlsplatInputError
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
    try:
        params = json.loads(args.params_json)
        if not isinstance(params, dict):
            raise OlsplatInputError("--params-json must be a JSON object")
        node = node_class(args.exec)(name, params)
    except (OlsplatInputError, json.JSONDecodeError, FileNotFoundError) as exc:
        print(f"node {name}: error: {exc}", file=sys.stderr)
        return 1
    return int(node.run(stop) or 0)


if __name__ == "__main__":
    sys.exit(main())
