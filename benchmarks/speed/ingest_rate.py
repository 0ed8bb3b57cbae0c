"""Ingest throughput and latency of a real node over loopback.

Starts ``govnesf serve`` in a subprocess (free loopback ports, temporary map directory), sends
N synthetic frames (rgb8 by default) with the pipelined client, and prints acks per second.
With ``--window 1`` (one frame in flight) the per-frame round-trip latency is the number to
read. Frames are pre-encoded so the client's encoding cost is not measured.

    .venv/bin/python benchmarks/speed/ingest_rate.py                 # 1000 frames 160x120, windows 1 and 16
    .venv/bin/python benchmarks/speed/ingest_rate.py --window 1 --frames 300 --with-ov --encoding jpeg
    .venv/bin/python benchmarks/speed/ingest_rate.py --window 16 --frames 300 --with-ov \
        --set triangulation.refine_poses=true --set 'triangulation.pose_method="window"'    # RGB-only
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.harness import NodeProcess, synthetic_frame  # noqa: E402
from protocol.messages import Ack, encode  # noqa: E402


def run(node: NodeProcess, payloads: list[bytes], window: int) -> dict[str, float]:
    latencies: list[float] = []
    statuses: dict[str, int] = {}
    with node.client(timeout_s=10.0, retries=0) as client:
        client.status()  # connect before timing
        started = time.perf_counter()
        for result in client.send_frames(payloads, window=window):
            latencies.append(result.latency_s)
            key = result.reply.status if isinstance(result.reply, Ack) else f"error:{result.reply.code}"
            statuses[key] = statuses.get(key, 0) + 1
        elapsed = time.perf_counter() - started
    latencies.sort()
    return {
        "frames": len(latencies),
        "elapsed_s": elapsed,
        "acks_per_s": len(latencies) / elapsed,
        "latency_p50_ms": 1000 * statistics.median(latencies),
        "latency_p95_ms": 1000 * latencies[int(0.95 * (len(latencies) - 1))],
        **{f"n_{k}": float(v) for k, v in sorted(statuses.items())},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument(
        "--window", type=int, action="append", help="frames in flight (repeatable; default 1 and 16)"
    )
    parser.add_argument("--encoding", choices=("rgb8", "jpeg", "png"), default="rgb8")
    parser.add_argument("--with-ov", action="store_true", help="include the demo's small OV feature map")
    parser.add_argument("--with-depth", action="store_true", help="keep the float32 depth map")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a node setting (as `govnesf serve --set`), repeatable, e.g. "
                             "triangulation.refine_poses=true")
    args = parser.parse_args(argv)
    if any("=" not in item for item in args.set):
        parser.error(f"--set expects KEY=VALUE, got {args.set}")
    windows = args.window or [1, 16]

    payloads = []
    for seq in range(args.frames):
        frame = synthetic_frame(
            seq, args.frames, args.width, args.height, with_ov=args.with_ov, rgb_encoding=args.encoding
        )
        if not args.with_depth:
            frame.depth_m = None
        payloads.append(encode(frame))
    mean_kb = sum(map(len, payloads)) / len(payloads) / 1024
    print(
        f"{args.frames} frames {args.width}x{args.height} {args.encoding}"
        f"{' +depth' if args.with_depth else ''}{' +ov' if args.with_ov else ''}, {mean_kb:.1f} KiB each"
    )
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        extra = [a for item in args.set for a in ("--set", item)]
        node = NodeProcess(Path(tmp) / "maps", log_path=Path(tmp) / "node.log", events=False,
                           extra_args=extra)
        with node:
            node.wait_ready()
            print(
                f"node start-up (process spawn to first status reply): {time.perf_counter() - started:.2f} s"
            )
            for window in windows:
                r = run(node, payloads, window)
                counts = ", ".join(f"{k[2:]} {int(v)}" for k, v in r.items() if k.startswith("n_"))
                print(
                    f"window {window:>3}: {r['acks_per_s']:8.1f} acks/s  "
                    f"({r['frames']} in {r['elapsed_s']:.2f} s)  "
                    f"latency p50 {r['latency_p50_ms']:.2f} ms, p95 {r['latency_p95_ms']:.2f} ms  [{counts}]"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
