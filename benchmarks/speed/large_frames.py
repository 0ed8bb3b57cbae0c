"""Large frames through a real node: acks per second and the node's resident memory.

A robot with a 640 x 480 RGB-D camera and a 2D open-vocabulary model that sends 384-d features at
1/4 resolution (160 x 120 x 384 float16: 14.7 MB a frame) streams ``--frames`` frames of the
synthetic loop (``clients.harness.synthetic_frame``, every one a keyframe: the camera moves) into
``govnesf serve`` (a subprocess, the shipped settings, the learned model not served unless
``--model``), pipelined ``--pipeline`` deep. Printed: acks per second over the whole stream, and
the node's RSS (``/proc/PID/status`` VmRSS) every ``--sample`` frames and once settled.

Run: ``python benchmarks/speed/large_frames.py --frames 200`` (a few minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from clients.harness import NodeProcess, synthetic_frame
from protocol.messages import Frame


def rss_mb(pid: int) -> float:
    """Resident memory of a process (MB), from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def large_frame(seq: int, n: int, width: int, height: int, ov_div: int, dim: int) -> Frame:
    """A synthetic frame at ``width`` x ``height`` with a random ``dim``-d OV map at 1/``ov_div``."""
    frame = synthetic_frame(seq, n, width, height, with_ov=False)
    rng = np.random.default_rng(seq)
    frame.ov = rng.standard_normal((height // ov_div, width // ov_div, dim)).astype(np.float16)
    frame.ov_space = "minilm-l6-v2"
    return frame


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--ov-div", type=int, default=4, help="the OV map at 1/N of the image")
    p.add_argument("--dim", type=int, default=384)
    p.add_argument("--pipeline", type=int, default=8)
    p.add_argument("--sample", type=int, default=50, help="RSS every N acks")
    p.add_argument("--model", action="store_true", help="serve the learned model too")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    for name in ("frames", "width", "height", "ov_div", "dim", "pipeline", "sample"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    frames = [large_frame(i, args.frames, args.width, args.height, args.ov_div, args.dim)
              for i in range(args.frames)]
    extra = ["--set", "save_on_exit=false", "--set", "load_autosave_on_start=false"]
    if not args.model:
        extra += ["--set", "serve_model=false"]
    for item in args.set:
        extra += ["--set", item]
    with tempfile.TemporaryDirectory(prefix="govnesf-large-") as tmp:
        log = Path(tmp) / "node.log"
        node = NodeProcess(Path(tmp) / "maps", log_path=log, extra_args=extra, events=False)
        with node:
            node.wait_ready(120)
            assert node.process is not None
            pid = node.process.pid
            ov_hw = f"{args.height // args.ov_div}x{args.width // args.ov_div}"
            print(f"{args.frames} frames {args.width}x{args.height}, ov {ov_hw}x{args.dim} fp16; "
                  f"node RSS at start {rss_mb(pid):.0f} MB", flush=True)
            with node.client(timeout_s=600) as client:
                t0 = time.perf_counter()
                for k, _ in enumerate(client.send_frames(iter(frames), window=args.pipeline), start=1):
                    if k % args.sample == 0:
                        rate = k / (time.perf_counter() - t0)
                        print(f"  {k} acks: {rate:.1f} acks/s, RSS {rss_mb(pid):.0f} MB", flush=True)
                elapsed = time.perf_counter() - t0
                print(f"stream: {args.frames / elapsed:.1f} acks/s", flush=True)
                deadline = time.perf_counter() + 120
                while time.perf_counter() < deadline and not client.status().extra.get("settled", True):
                    time.sleep(0.5)
                print(f"settled: RSS {rss_mb(pid):.0f} MB", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
