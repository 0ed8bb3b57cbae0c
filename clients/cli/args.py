"""argparse value types and options shared by the ``govnesf`` subcommands."""

from __future__ import annotations

import argparse
import math

from clients.client import MapperClient
from protocol.messages import Status

__all__ = [
    "DEFAULT_PING_TIMEOUT_S",
    "add_ping_argument",
    "late_reply_message",
    "non_negative_float",
    "ping_first",
    "positive_int",
]

DEFAULT_PING_TIMEOUT_S = 2.0
"""How long a CLI command waits for the node's answer to its first ``status`` (the ping)."""


def positive_int(text: str) -> int:
    """An integer >= 1 (``type=`` of an argparse option); anything else is a one-line usage error."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: must be 1 or more")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0 (``type=`` of an argparse option)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number >= 0")
    return value


def add_ping_argument(parser: argparse.ArgumentParser) -> None:
    """``--ping-timeout S`` of the commands that talk to a node (read as ``args.ping_timeout``)."""
    parser.add_argument(
        "--ping-timeout",
        type=non_negative_float,
        default=DEFAULT_PING_TIMEOUT_S,
        metavar="S",
        help=(
            "first ask the node for its status, waiting at most S seconds (and at most --timeout), "
            "no retry: with no node at the endpoint the command fails after S seconds instead of "
            f"--timeout x (1 + --retries); 0 skips this check (default {DEFAULT_PING_TIMEOUT_S:g})"
        ),
    )


def ping_first(client: MapperClient, args: argparse.Namespace) -> Status | None:
    """The ``--ping-timeout`` check of :func:`add_ping_argument`: the node's status, asked once with
    a short timeout (None when the check is off). Raises
    :class:`~clients.client.NodeUnreachableError` when no node answers."""
    timeout_s = min(args.ping_timeout, args.timeout)
    return client.ping(timeout_s) if timeout_s > 0 else None


def late_reply_message(exc: TimeoutError, args: argparse.Namespace, pinged: bool) -> str:
    """What a CLI command says when its request timed out (after the ping, when there was one)."""
    if not pinged:  # --ping-timeout 0: no node, or a node slower than --timeout
        return str(exc)
    tries = 1 + args.retries
    return (
        f"the node at {args.query} answers its status but sent no reply to this request within "
        f"--timeout {args.timeout:g} s ({tries} tr{'y' if tries == 1 else 'ies'}); try a longer --timeout"
    )


def floor_rooms(text: str) -> int:
    """argparse type of ``--floor-rooms``: 0, or 2..30."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if n != 0 and not 2 <= n <= 30:
        raise argparse.ArgumentTypeError(f"{n} must be 0 (no floor phase) or 2..30")
    return n
