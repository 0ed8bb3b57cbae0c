"""``govnesf status | save | load``: one-shot requests to a node's query endpoint.

Exit codes: 0 success, 1 the node did not answer, 2 invalid arguments, 3 the node answered
with an error.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable

from clients.client import DEFAULT_QUERY, MapperClient
from protocol.errors import ProtocolError, RemoteError
from protocol.messages import Message, Ok, Status


def _parser(prog: str, description: str, with_name: bool) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=description)
    if with_name:
        parser.add_argument("name", help="map name, [A-Za-z0-9_.-]{1,64}, inside the node's map directory")
    parser.add_argument(
        "--query", default=DEFAULT_QUERY, metavar="EP", help=f"node query endpoint ({DEFAULT_QUERY})"
    )
    parser.add_argument(
        "--timeout", type=float, default=5.0, metavar="S", help="seconds to wait for the reply"
    )
    parser.add_argument(
        "--retries", type=int, default=1, metavar="N", help="retries before giving up (default 1)"
    )
    return parser


def _run(args: argparse.Namespace, call: Callable[[MapperClient], Message], prog: str) -> int:
    try:
        with MapperClient(query=args.query, timeout_s=args.timeout, retries=args.retries) as client:
            reply = call(client)
    except TimeoutError as exc:
        print(f"{prog}: node unreachable: {exc}", file=sys.stderr)
        return 1
    except RemoteError as exc:
        print(f"{prog}: the node refused: {exc.code}: {exc.message}", file=sys.stderr)
        return 3
    except ProtocolError as exc:  # invalid request built locally (e.g. a bad map name)
        print(f"{prog}: {exc.message}", file=sys.stderr)
        return 2
    if isinstance(reply, Status):
        print(format_status(reply, as_json=getattr(args, "json", False)))
    elif isinstance(reply, Ok):
        print(reply.message or "ok")
    return 0


def format_status(status: Status, as_json: bool = False) -> str:
    """The status as aligned ``key: value`` lines (or one JSON object)."""
    fields = {
        "map_version": status.map_version,
        "keyframes": status.keyframes,
        "frames_received": status.frames_received,
        "frames_rejected": status.frames_rejected,
        "ov_space": status.ov_space,
        "memory_bytes": status.memory_bytes,
        "uptime_s": round(status.uptime_s, 3),
        **status.extra,
    }
    if as_json:
        return json.dumps(fields, indent=2, sort_keys=False, default=str)
    width = max(len(k) for k in fields)
    return "\n".join(
        f"{k:<{width}}  {json.dumps(v, default=str) if isinstance(v, dict | list) else v}"
        for k, v in fields.items()
    )


def status_main(argv: list[str] | None = None) -> int:
    """``govnesf status [--query EP] [--json]``."""
    parser = _parser("govnesf status", "Print a mapper node's status.", with_name=False)
    parser.add_argument("--json", action="store_true", help="print JSON")
    args = parser.parse_args(argv)
    return _run(args, lambda c: c.status(), "govnesf status")


def save_main(argv: list[str] | None = None) -> int:
    """``govnesf save NAME [--query EP]``."""
    args = _parser("govnesf save", "Save the node's map in its map directory.", with_name=True).parse_args(
        argv
    )
    return _run(args, lambda c: c.save(args.name), "govnesf save")


def load_main(argv: list[str] | None = None) -> int:
    """``govnesf load NAME [--query EP]``."""
    args = _parser("govnesf load", "Load a saved map into the node.", with_name=True).parse_args(argv)
    return _run(args, lambda c: c.load(args.name), "govnesf load")
