"""``govnesf keys``: make CurveZMQ key files for a node and its clients (docs/how-to/robot-network.md).

::

    govnesf keys /etc/govnesf/keys                  # server.key, server.key_secret, empty allowed/
    govnesf keys /etc/govnesf/keys --client robot1  # clients/robot1.key(_secret), allowed/robot1.key

Keys are ``zmq.auth`` certificate files (layout: :mod:`protocol.curve`); existing keys are never
overwritten. Exit codes: 0 made, 2 invalid arguments or a key that already exists.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.curve import SERVER_NAME, CurveKeyError, create_client_keys, create_server_keys


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="govnesf keys",
        description="Make CurveZMQ keys: without --client the node's key pair and an empty allowed/ "
        "directory; with --client NAME a client key pair, allowed in by the node.",
    )
    parser.add_argument("dir", metavar="DIR", help="the curve directory (created if missing)")
    parser.add_argument(
        "--client", metavar="NAME", help="make a client key pair NAME ([A-Za-z0-9_.-]{1,64}) and allow it"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.client is None:
            paths = create_server_keys(args.dir)
            note = (
                f"next: `govnesf keys {args.dir} --client NAME` per client, then "
                f"`govnesf serve --curve-dir {args.dir}`"
            )
        elif not (Path(args.dir) / f"{SERVER_NAME}.key").is_file():
            print(
                f"govnesf keys: {args.dir}: no server key (server.key) there; run "
                f"`govnesf keys {args.dir}` first, then add clients",
                file=sys.stderr,
            )
            return 2
        else:
            paths = create_client_keys(args.dir, args.client)
            note = (
                f"give the client {args.dir}/server.key and {paths[1]} (secret: that client only); "
                f"it connects with --curve-dir DIR --client {args.client}"
            )
    except CurveKeyError as exc:
        print(f"govnesf keys: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"govnesf keys: cannot write keys in {args.dir!r}: {exc}", file=sys.stderr)
        return 2
    for path in paths:
        print(f"wrote {path}")
    print(note)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
