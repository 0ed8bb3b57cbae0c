"""``govnesf status | save | load | query``: one-shot requests to a node's query endpoint.

Exit codes: 0 success, 1 the node did not answer (or an ``--out`` file could not be written),
2 invalid arguments, 3 the node answered with an error.

Each command first asks the node for its status, waiting at most ``--ping-timeout`` seconds
(default 2) with no retry: with no node at ``--query`` it fails then (exit 1, "no node answers at
tcp://...; is `govnesf serve` running?") rather than after ``--timeout`` x (1 + ``--retries``).
Once the node has answered, the request itself gets ``--timeout``. ``--ping-timeout 0`` skips the
check. ``govnesf status`` prints the ping's answer.

``govnesf query "find the chair" --out chair.ply --json chair.json`` prints the object candidates
(text, centroid, score, points), writes the matching points as a binary PLY (float32 xyz, a float32
``score`` property, coloured by score with the viridis colormap, dark = low, yellow = high; an empty
answer gives a valid PLY with 0 points; ``clients/ply.py``) and the objects as JSON; ``--rerun F.rrd``
logs both for the Rerun viewer (``clients/rerun_log.py``, docs/how-to/rerun.md).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from clients.cli.args import add_ping_argument, late_reply_message, ping_first
from clients.client import (
    DEFAULT_QUERY,
    MapperClient,
    NodeUnreachableError,
    add_curve_arguments,
    curve_from_args,
)
from protocol.errors import ProtocolError, RemoteError
from protocol.messages import Message, Ok, Points, Status


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
    add_ping_argument(parser)
    add_curve_arguments(parser)
    return parser


def _run(args: argparse.Namespace, call: Callable[[MapperClient, Status | None], Message], prog: str) -> int:
    """Ping the node (``--ping-timeout``), then ``call(client, the ping's status or None)``."""
    pinged: Status | None = None
    try:
        curve = curve_from_args(args)
        with MapperClient(
            query=args.query, timeout_s=args.timeout, retries=args.retries, curve=curve
        ) as client:
            pinged = ping_first(client, args)
            reply = call(client, pinged)
    except NodeUnreachableError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    except TimeoutError as exc:
        print(f"{prog}: {late_reply_message(exc, args, pinged is not None)}", file=sys.stderr)
        return 1
    except RemoteError as exc:
        print(f"{prog}: the node refused: {exc.code}: {exc.message}", file=sys.stderr)
        return 3
    except ProtocolError as exc:  # invalid request built locally (e.g. a bad map name)
        print(f"{prog}: {exc.message}", file=sys.stderr)
        return 2
    if isinstance(reply, Points):
        return _report_points(reply, args)
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
    return _run(args, lambda c, pinged: pinged or c.status(), "govnesf status")


def save_main(argv: list[str] | None = None) -> int:
    """``govnesf save NAME [--query EP]``."""
    args = _parser("govnesf save", "Save the node's map in its map directory.", with_name=True).parse_args(
        argv
    )
    return _run(args, lambda c, _: c.save(args.name), "govnesf save")


def load_main(argv: list[str] | None = None) -> int:
    """``govnesf load NAME [--query EP]``."""
    args = _parser("govnesf load", "Load a saved map into the node.", with_name=True).parse_args(argv)
    return _run(args, lambda c, _: c.load(args.name), "govnesf load")


# ---------------------------------------------------------------------------------------------
# govnesf query

def write_points_ply(path: str | Path, xyz: np.ndarray, score: np.ndarray) -> Path:
    """Write points (N, 3) with their scores (N,) as a binary PLY: float32 x, y, z, a float32
    ``score`` property and a viridis colour by score (``clients/ply.py``); N = 0 writes a valid
    empty PLY. Returns the path."""
    from clients.ply import write_points_ply as write_ply

    return write_ply(path, np.asarray(xyz).reshape(-1, 3), np.asarray(score).reshape(-1))


def objects_as_json(points: Points) -> dict[str, Any]:
    """The reply's objects (and a summary) as a JSON-able dict."""
    return {
        "map_version": points.map_version,
        "n_points": int(points.xyz.shape[0]),
        "timing_ms": {k: round(float(v), 3) for k, v in points.timing_ms.items()},
        "objects": [
            {
                "text": o.text,
                "centroid": [round(float(v), 4) for v in o.centroid],
                "aabb_min": [round(float(v), 4) for v in o.aabb_min],
                "aabb_max": [round(float(v), 4) for v in o.aabb_max],
                "score": round(float(o.score), 5),
                "n_points": int(o.n_points),
            }
            for o in points.objects
        ],
    }


def format_objects(points: Points, limit: int = 10) -> str:
    """Object candidates as aligned lines: rank, text, centroid (m), score, points."""
    if not points.objects:
        return f"no object candidates ({points.xyz.shape[0]} matching points)"
    lines = [f"{'#':>3}  {'text':<24} {'centroid x, y, z (m)':<24} {'score':>6} {'points':>7}"]
    for i, o in enumerate(points.objects[:limit]):
        c = ", ".join(f"{v:.2f}" for v in o.centroid)
        lines.append(f"{i + 1:>3}  {o.text[:24]:<24} {c:<24} {o.score:>6.3f} {o.n_points:>7d}")
    if len(points.objects) > limit:
        lines.append(f"     ... and {len(points.objects) - limit} more")
    return "\n".join(lines)


def _report_points(points: Points, args: argparse.Namespace) -> int:
    print(format_objects(points, limit=args.top))
    total = points.timing_ms.get("total")
    print(f"{points.xyz.shape[0]} points matched, map version {points.map_version}"
          + (f", {total:.1f} ms on the node" if total is not None else "")
          + (" (the node's background work was still pending)" if points.settled is False else ""))
    if args.out:
        try:
            written = write_points_ply(args.out, points.xyz, points.score)
        except (OSError, ValueError) as exc:
            print(f"govnesf query: cannot write --out {args.out}: {exc}", file=sys.stderr)
            return 1
        empty = " (no points matched: a valid PLY with 0 points)" if points.xyz.shape[0] == 0 else ""
        print(f"wrote {written}{empty}")
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(objects_as_json(points), indent=1) + "\n")
        print(f"wrote {path}")
    if args.rerun or args.rerun_connect:
        from clients.rerun_log import RerunLog, RerunLogError

        try:
            with RerunLog(args.rerun, connect=args.rerun_connect,
                          recording_name="govnesf query " + " ".join(args.texts)) as rlog:
                rlog.log_query(points, list(args.texts))
        except RerunLogError as exc:
            print(f"govnesf query: {exc}", file=sys.stderr)
            return 1
        if args.rerun:
            print(f"wrote {args.rerun} (view it with: rerun {args.rerun})")
        if args.rerun_connect:
            print(f"sent to the Rerun viewer at {rlog.url}")
    return 0


def query_main(argv: list[str] | None = None) -> int:
    """``govnesf query TEXT [TEXT...] [--negatives N...] [--min-score S] [--out F.ply] [--json F.json]
    [--rerun F.rrd] [--rerun-connect ADDR]``."""
    parser = _parser("govnesf query", "Find map points and objects matching texts (\"find the chair\").",
                     with_name=False)
    parser.add_argument("texts", nargs="+", metavar="TEXT",
                        help='what to find, e.g. "chair" or "find the chair"')
    parser.add_argument("--negatives", nargs="*", metavar="NEG", default=None,
                        help="background prompts (default: the node's set; give none for no negatives)")
    parser.add_argument("--min-score", type=float, default=None, metavar="S",
                        help="drop points whose cosine is below S")
    parser.add_argument("--max-points", type=int, default=None, metavar="N", help="return at most N points")
    parser.add_argument("--no-objects", action="store_true", help="skip the object clustering")
    parser.add_argument("--out", metavar="FILE.ply", help="write the matching points coloured by score")
    parser.add_argument("--json", metavar="FILE.json", help="write the object candidates as JSON")
    parser.add_argument("--top", type=int, default=10, metavar="K", help="objects to print (default 10)")
    parser.add_argument("--region", metavar="X0,Y0,Z0,X1,Y1,Z1", default=None,
                        help="only map points inside this axis-aligned box (world metres: the minimum and "
                             "maximum corners)")
    parser.add_argument("--settle", type=float, default=None, metavar="S",
                        help="answer from the settled map: the node first waits up to S seconds for its "
                             "background work on the frames acked so far (the request timeout grows by S)")
    parser.add_argument("--rerun", metavar="FILE.rrd",
                        help="also log the points (by score) and objects (boxes) for the Rerun viewer")
    from clients.rerun_log import CONNECT_HELP  # no rerun import: only the help text

    parser.add_argument("--rerun-connect", metavar="ADDR", help=CONNECT_HELP)
    parser.set_defaults(timeout=30.0)
    args = parser.parse_args(argv)
    if args.top < 0:
        parser.error(f"--top {args.top} must be >= 0")
    region = None
    if args.region is not None:
        try:
            box = [float(x) for x in args.region.split(",")]
        except ValueError:
            parser.error(f"--region {args.region!r}: expected six numbers X0,Y0,Z0,X1,Y1,Z1")
        if len(box) != 6 or not all(math.isfinite(x) for x in box):
            parser.error(f"--region {args.region!r}: expected six finite numbers X0,Y0,Z0,X1,Y1,Z1")
        if any(lo > hi for lo, hi in zip(box[:3], box[3:], strict=True)):
            parser.error(f"--region {args.region!r}: the minimum corner exceeds the maximum on an axis")
        region = (np.array(box[:3]), np.array(box[3:]))
    if args.settle is not None:
        if args.settle < 0:
            parser.error(f"--settle {args.settle} must be >= 0")
        args.timeout += args.settle
    if args.rerun or args.rerun_connect:  # a bad path / no viewer is an error before the query is sent
        from clients.rerun_log import RerunLogError, check_rerun_outputs

        try:
            check_rerun_outputs(args.rerun, args.rerun_connect)
        except RerunLogError as exc:
            parser.error(str(exc))
    return _run(
        args,
        lambda c, _: c.query_points(
            list(args.texts), negatives=args.negatives, min_score=args.min_score, max_points=args.max_points,
            objects=not args.no_objects, settle_timeout_s=args.settle, region=region,
        ),
        "govnesf query",
    )
