"""``govnesf replay FILE.govrec``: send a recording's frames to a node and summarise the answers.

Frames are sent byte-for-byte as recorded, pipelined (``--window`` frames in flight), at most
``--rate`` frames per second (0 = as fast as the acks come back). A truncated or corrupt tail
of the recording is reported; every complete frame before it is still sent. ``--rerun F.rrd``
logs the frames (every ``--rerun-every``-th) for the Rerun viewer (``clients/rerun_log.py``).

Exit codes: 0 done (whatever the node answered), 1 the node did not answer, 2 bad arguments or
an unreadable recording.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from clients.client import DEFAULT_INGEST, FrameResult, MapperClient, add_curve_arguments, curve_from_args
from protocol.errors import ProtocolError
from protocol.messages import Ack, Frame, decode
from protocol.recording import read_recording


@dataclass
class ReplaySummary:
    """What happened to a replayed recording."""

    sent: int = 0
    """Frames answered by the node."""
    statuses: Counter[str] = field(default_factory=Counter)
    """Acks by status: keyframe, accepted, rejected."""
    rejected_reasons: Counter[str] = field(default_factory=Counter)
    """Rejected acks by reason."""
    errors: Counter[str] = field(default_factory=Counter)
    """Error replies by ``code: message``."""
    map_version: int | None = None
    """Map version in the last ack."""
    truncated: bool = False
    """The recording ended in a cut-short or corrupt message."""
    truncation: str | None = None
    """Where and why it was cut short."""
    elapsed_s: float = 0.0
    mean_latency_s: float = 0.0
    """Mean time from sending a frame to its reply."""
    unreachable: str | None = None
    """Set when the node stopped answering (the replay ended early)."""

    def lines(self) -> list[str]:
        """A human-readable report."""
        rate = self.sent / self.elapsed_s if self.elapsed_s > 0 else 0.0
        out = [
            f"sent {self.sent} frames in {self.elapsed_s:.2f} s ({rate:.1f} frames/s, "
            f"mean ack latency {1000 * self.mean_latency_s:.1f} ms)",
            f"  keyframe {self.statuses['keyframe']}, accepted {self.statuses['accepted']}, "
            f"rejected {self.statuses['rejected']}, errors {sum(self.errors.values())}",
        ]
        for reason, count in self.rejected_reasons.most_common():
            out.append(f"  rejected x{count}: {reason}")
        for error, count in self.errors.most_common():
            out.append(f"  error x{count}: {error}")
        if self.map_version is not None:
            out.append(f"  map_version after replay: {self.map_version}")
        if self.truncated:
            out.append(f"  recording truncated: {self.truncation}")
        if self.unreachable:
            out.append(f"  node unreachable, replay stopped: {self.unreachable}")
        return out


def replay(
    path: str | Path,
    client: MapperClient,
    *,
    rate_hz: float = 0.0,
    window: int = 8,
    progress: bool = True,
    on_result: Callable[[FrameResult], None] | None = None,
    on_frame: Callable[[int, bytes], None] | None = None,
) -> ReplaySummary:
    """Send every complete frame of recording ``path`` through ``client``.

    ``on_frame(index, data)`` sees each frame's recorded bytes just before it is sent;
    ``on_result`` each reply.

    Raises:
        FileNotFoundError, ProtocolError: the recording cannot be opened (bad header).

    A node that stops answering ends the replay early with ``summary.unreachable`` set.
    """
    reader = read_recording(path)
    summary = ReplaySummary()
    payload_bytes = Path(path).stat().st_size - reader.header_size
    bar = tqdm(
        total=payload_bytes, unit="B", unit_scale=True, desc=Path(path).name, disable=not progress,
        file=sys.stderr,
    )
    sizes: dict[int, int] = {}

    def frames() -> Iterator[bytes]:
        for index, data in enumerate(reader):
            sizes[index] = len(data)
            if on_frame is not None:
                on_frame(index, data)
            yield data

    started = time.monotonic()
    latency_sum = 0.0
    try:
        for result in client.send_frames(frames(), window=window, rate_hz=rate_hz):
            summary.sent += 1
            latency_sum += result.latency_s
            reply = result.reply
            if isinstance(reply, Ack):
                summary.statuses[reply.status] += 1
                summary.map_version = reply.map_version
                if reply.status == "rejected":
                    summary.rejected_reasons[reply.reason or "?"] += 1
            else:
                summary.errors[f"{reply.code}: {reply.message}"] += 1
            bar.update(sizes.pop(result.index, 0))
            rejected = summary.statuses["rejected"] + sum(summary.errors.values())
            bar.set_postfix(kf=summary.statuses["keyframe"], rej=rejected, refresh=False)
            if on_result is not None:
                on_result(result)
    except TimeoutError as exc:
        summary.unreachable = str(exc)
    finally:
        bar.close()
        summary.elapsed_s = time.monotonic() - started
        summary.mean_latency_s = latency_sum / summary.sent if summary.sent else 0.0
        summary.truncated = reader.truncated
        summary.truncation = reader.error
    return summary


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="govnesf replay", description="Replay a .govrec recording into a mapper node."
    )
    parser.add_argument("recording", metavar="FILE.govrec", help="recording to replay")
    parser.add_argument(
        "--rate", type=float, default=0.0, metavar="HZ", help="frames per second; 0 = as fast as acks allow"
    )
    parser.add_argument(
        "--ingest", default=DEFAULT_INGEST, metavar="EP", help=f"node ingest endpoint ({DEFAULT_INGEST})"
    )
    parser.add_argument("--window", type=int, default=8, metavar="N", help="frames in flight (default 8)")
    parser.add_argument(
        "--timeout", type=float, default=5.0, metavar="S", help="seconds to wait for an ack before retrying"
    )
    parser.add_argument(
        "--retries", type=int, default=2, metavar="N", help="retries before giving up (default 2)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--rerun", metavar="FILE.rrd", help="also log the frames (camera, rgb, depth) for the Rerun viewer"
    )
    parser.add_argument(
        "--rerun-every", type=int, default=1, metavar="N", help="log every Nth frame only (default 1: all)"
    )
    from clients.rerun_log import CONNECT_HELP  # no rerun import: only the help text

    parser.add_argument("--rerun-connect", metavar="ADDR", help=CONNECT_HELP)
    add_curve_arguments(parser)
    return parser


class FrameLogger:
    """``on_frame`` for :func:`replay`: decodes every ``every``-th recorded frame and logs it to
    ``rlog`` (a :class:`clients.rerun_log.RerunLog`). Frames that do not decode are counted in
    ``skipped`` (the node answers them with an error; the replay goes on)."""

    def __init__(self, rlog: Any, every: int = 1) -> None:
        if every < 1:
            raise ValueError(f"every {every} must be >= 1")
        self.rlog = rlog
        self.every = every
        self.skipped = 0

    def __call__(self, index: int, data: bytes) -> None:
        if index % self.every:
            return
        try:
            frame = decode(data, direction="request")
        except ProtocolError:
            self.skipped += 1
            return
        if isinstance(frame, Frame):
            self.rlog.log_frame(frame)
        else:
            self.skipped += 1


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``govnesf replay``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.rate < 0 or args.window < 1 or args.timeout <= 0 or args.retries < 0 or args.rerun_every < 1:
        parser.error("need --rate >= 0, --window >= 1, --timeout > 0, --retries >= 0, --rerun-every >= 1")
    rlog = None
    from clients.rerun_log import RerunLog, RerunLogError, check_rerun_outputs  # rerun itself: lazily

    if args.rerun or args.rerun_connect:  # checked before anything is read or sent
        try:
            check_rerun_outputs(args.rerun, args.rerun_connect)
        except RerunLogError as exc:
            parser.error(str(exc))
    try:
        with contextlib.ExitStack() as stack:
            read_recording(args.recording)  # an unreadable recording fails here: no .rrd is written
            if args.rerun or args.rerun_connect:
                name = f"govnesf replay {Path(args.recording).name}"
                rlog = stack.enter_context(
                    RerunLog(args.rerun, connect=args.rerun_connect, recording_name=name)
                )
            logger = FrameLogger(rlog, args.rerun_every) if rlog is not None else None
            client = stack.enter_context(
                MapperClient(
                    ingest=args.ingest, timeout_s=args.timeout, retries=args.retries,
                    curve=curve_from_args(args),
                )
            )
            summary = replay(
                args.recording, client, rate_hz=args.rate, window=args.window, progress=not args.no_progress,
                on_frame=logger,
            )  # fmt: skip
    except FileNotFoundError:
        print(f"govnesf replay: no such recording: {args.recording}", file=sys.stderr)
        return 2
    except ProtocolError as exc:
        print(f"govnesf replay: cannot replay {args.recording}: {exc}", file=sys.stderr)
        return 2
    except RerunLogError as exc:  # the live viewer did not take the data (raised on close)
        print(f"govnesf replay: {exc}", file=sys.stderr)
        return 1
    print("\n".join(summary.lines()))
    if rlog is not None and logger is not None:
        skipped = f", {logger.skipped} undecodable skipped" if logger.skipped else ""
        where = " and ".join(([args.rerun] if args.rerun else []) + ([rlog.url] if rlog.url else []))
        print(f"wrote {where}: {rlog.frames_logged} frames logged (every {args.rerun_every}){skipped}")
    if summary.unreachable:
        print(f"govnesf replay: node unreachable: {summary.unreachable}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
