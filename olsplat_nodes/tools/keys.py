"""``olsplat keys generate --out DIR --name NAME``: a CURVE key pair for the query link.

The query server loads its ``NAME.key_secret`` and a directory of the clients' ``*.key`` files
(its allow-list); a ground station loads its own ``NAME.key_secret`` and the server's ``.key``.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("keys", help="CURVE key pairs for the encrypted, authenticated query link")
    actions = parser.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    generate = actions.add_parser(
        "generate",
        help="write NAME.key (public) and NAME.key_secret (secret, mode 0600) into a folder",
        description="Write a new CURVE key pair. Give NAME.key to the other side (a client's key goes into the "
        "server's allow-list folder); keep NAME.key_secret on this machine only.",
    )
    generate.add_argument("--out", required=True, type=Path, help="folder for the key files (created if missing)")
    generate.add_argument("--name", required=True, help="key name, e.g. query_server or ground1")
    generate.add_argument("--force", action="store_true", help="replace an existing key pair of that name")
    generate.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..outputs import output_folder
    from ..transport import curve

    output_folder(args.out)
    try:
        public, secret = curve.generate(args.out, args.name, overwrite=args.force)
    except (FileExistsError, ValueError) as exc:
        raise OlsplatInputError(str(exc).replace("pass overwrite", "pass --force")) from exc
    print(f"public key: {public}  (share it: clients' public keys go into the server's allow-list folder)")
    print(f"secret key: {secret}  (keep it here, mode 0600)")
    return 0
