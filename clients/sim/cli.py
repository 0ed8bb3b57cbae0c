"""`govnesf sim`: record the simulated robot to disk, or stream it straight into a node.

    govnesf sim record --seed 0 --style apartment --frames 300 --width 160 --height 120 [--depth]
                       [--no-ov] --out DIR
    govnesf sim record --seed 0 --floor-rooms 20 --frames 20000 --depth --out DIR   # a floor tour
    govnesf sim stream --seed 0 --style apartment --frames 300 [--depth] [--no-ov]
                       --ingest tcp://127.0.0.1:5555 --rate 10

See docs/how-to/simulator.md for the export layout.
"""

from __future__ import annotations

import argparse
import copy
import re
import sys
import time
from collections import Counter
from typing import Any

import numpy as np

from clients.sim.export import FLOOR_PATH, RGB_ENCODINGS, RecordConfig, SimStream, record
from clients.sim.paths import PATH_KINDS
from clients.sim.scenes.floor import FLOOR_ROOMS
from clients.sim.sensor import POSE_ERRORS, perturb_poses
from protocol.messages import ROBOT_RE, Frame


def _add_common(p: argparse.ArgumentParser) -> None:
    from clients.sim.scenes import STYLES

    p.add_argument("--seed", type=int, required=True, help="scene seed (>= 0)")
    p.add_argument("--style", default="apartment", choices=sorted(STYLES), help="scene style")
    p.add_argument("--frames", type=int, default=300, help="number of frames (default 300)")
    p.add_argument("--width", type=int, default=160, help="image width, pixels (default 160)")
    p.add_argument("--height", type=int, default=120, help="image height, pixels (default 120)")
    p.add_argument("--hfov", type=float, default=70.0, help="horizontal field of view, degrees")
    p.add_argument("--depth", action="store_true", help="send rendered depth with each frame")
    p.add_argument("--no-ov", action="store_true", help="do not send SimLSeg open-vocabulary features")
    p.add_argument("--ov-stride", type=int, default=None,
                   help="SimLSeg output stride (feature map is H/stride x W/stride; default SimLSeg's)")
    p.add_argument("--trajectory-seed", type=int, default=None, help="robot path seed (default: --seed)")
    p.add_argument("--max-step", type=float, default=0.08,
                   help="largest horizontal camera move per frame, metres (default 0.08)")
    p.add_argument("--fps", type=float, default=10.0, help="nominal frame rate for stamps (default 10)")
    p.add_argument("--rgb-encoding", default="rgb8", choices=RGB_ENCODINGS, help="colour encoding")
    p.add_argument("--floor-rooms", type=int, default=0,
                   help=f"a floor of N rooms ({FLOOR_ROOMS[0]}..{FLOOR_ROOMS[1]}) of --style joined by "
                        "corridors instead of one room (default 0: one room)")
    p.add_argument("--path", default=None, choices=sorted((*PATH_KINDS, FLOOR_PATH)),
                   help=f"camera path (default: loop in a room, {FLOOR_PATH} on a floor: every room, "
                        "then the first rooms again)")
    p.add_argument("--revisit-rooms", type=int, default=2,
                   help=f"{FLOOR_PATH}: how many of the first rooms the tour comes back to (default 2)")


def _config(args: argparse.Namespace, **extra: Any) -> RecordConfig:
    cfg = RecordConfig(seed=args.seed, style=args.style, frames=args.frames, width=args.width,
                       height=args.height, hfov_deg=args.hfov, depth=args.depth, ov=not args.no_ov,
                       trajectory_seed=args.trajectory_seed, fps=args.fps, rgb_encoding=args.rgb_encoding,
                       ov_stride=args.ov_stride, max_step_m=args.max_step, floor_rooms=args.floor_rooms,
                       path=args.path, revisit_rooms=args.revisit_rooms, **extra)
    cfg.validate()
    return cfg


def _record(args: argparse.Namespace) -> int:
    cfg = _config(args, novel_views=args.novel_views, points_per_m2=args.points_per_m2,
                  previews=args.previews)
    summary = record(cfg, args.out, progress=not args.quiet)
    print(f"wrote {summary.frames} frames to {summary.out_dir} in {summary.seconds:.1f} s "
          f"(render {summary.seconds_render:.1f} s, ov {summary.seconds_ov:.1f} s); "
          f"recording {summary.recording_bytes / 1e6:.1f} MB, {summary.gt_points} gt points")
    return 0


def _named(frame: Frame, robot: str) -> Frame:
    """``frame`` with its ``robot`` set (the name was checked; ``frame`` itself when none)."""
    if not robot:
        return frame
    named = copy.copy(frame)
    named.robot = robot
    return named


def _posed(frame: Frame, world_from_cam: np.ndarray) -> Frame:
    """``frame`` with the pose odometry reported (``frame`` itself when it is the true one)."""
    if np.array_equal(frame.world_from_cam, world_from_cam):
        return frame
    posed = copy.copy(frame)
    posed.world_from_cam = np.asarray(world_from_cam, np.float64)
    return posed


def _stream(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from clients.client import MapperClient, curve_from_args
    from protocol.errors import ProtocolError
    from protocol.messages import Error

    if args.rate < 0:
        raise ValueError(f"--rate {args.rate} must be >= 0 (0 = as fast as the node acks)")
    if not re.fullmatch(r"(tcp|ipc|inproc)://\S+", args.ingest):
        raise ValueError(f"--ingest {args.ingest!r} is not a ZeroMQ endpoint (e.g. tcp://127.0.0.1:5555)")
    if args.window < 1 or args.timeout <= 0:
        raise ValueError(f"--window {args.window} must be >= 1 and --timeout {args.timeout} > 0")
    if not ROBOT_RE.fullmatch(args.robot):
        raise ValueError(f"--robot {args.robot!r} is not a robot name: 0..32 characters from [A-Za-z0-9_.-]")
    try:
        curve = curve_from_args(args)
    except ProtocolError as exc:
        raise ValueError(exc.message) from None
    cfg = _config(args, novel_views=0, previews=0)
    stream = SimStream.build(cfg)
    sent = perturb_poses(stream.poses, args.pose_error, seed=cfg.seed)  # what odometry reports
    statuses: Counter[str] = Counter()
    t0 = time.perf_counter()
    with MapperClient(ingest=args.ingest, timeout_s=args.timeout, curve=curve) as client:
        frames = (_named(_posed(frame, sent[k]), args.robot)
                  for k, (frame, _) in enumerate(stream.frames()))
        results = client.send_frames(frames, window=args.window, rate_hz=args.rate)
        for res in tqdm(results, total=cfg.frames, desc=f"sim stream -> {args.ingest}", unit="frame",
                        disable=args.quiet):
            if isinstance(res.reply, Error):
                statuses[f"error:{res.reply.code}"] += 1
                print(f"frame {res.index}: error {res.reply.code}: {res.reply.message}", file=sys.stderr)
            else:
                statuses[res.reply.status] += 1
                if res.reply.status == "rejected":
                    print(f"frame {res.index}: rejected: {res.reply.reason}", file=sys.stderr)
    dt = time.perf_counter() - t0
    print(f"sent {cfg.frames} frames in {dt:.1f} s ({cfg.frames / max(dt, 1e-9):.1f} Hz): "
          + ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())))
    return 0 if not any(k.startswith("error") for k in statuses) else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="govnesf sim", description="simulated robot in procedural rooms")
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="render a trajectory to DIR/frames.govrec plus ground truth")
    _add_common(rec)
    rec.add_argument("--out", required=True, help="output folder (new or empty)")
    rec.add_argument("--novel-views", type=int, default=8, help="held-out views for gt/ (default 8)")
    rec.add_argument("--points-per-m2", type=float, default=500.0, help="gt surface sample density")
    rec.add_argument("--previews", type=int, default=4, help="preview PNG frames (default 4)")
    rec.add_argument("--quiet", action="store_true", help="no progress bar")
    st = sub.add_parser("stream", help="render frames and send them to a node's ingest endpoint")
    _add_common(st)
    st.add_argument("--ingest", default="tcp://127.0.0.1:5555", help="node ingest endpoint")
    st.add_argument("--rate", type=float, default=10.0,
                    help="frames per second, 0 = unthrottled (default 10)")
    st.add_argument("--window", type=int, default=1, help="frames in flight before waiting for acks")
    st.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for each ack")
    st.add_argument("--pose-error", default="exact", choices=sorted(POSE_ERRORS),
                    help="odometry error on the poses sent (the scenario matrix's levels: noise_1cm = "
                         "1 cm / 0.5 deg per frame, noise_3cm = 3 cm / 1.5 deg, drift = a random walk); "
                         "default exact")
    st.add_argument("--robot", default="",
                    help="robot name on every frame ([A-Za-z0-9_.-]{0,32}; each robot has its own window "
                         "in the node; default: none, the default robot)")
    st.add_argument("--quiet", action="store_true", help="no progress bar")
    from clients.client import add_curve_arguments

    add_curve_arguments(st)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of `govnesf sim`; returns the process exit status."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        if args.command == "record":
            return _record(args)
        return _stream(args)
    except (ValueError, TimeoutError) as exc:
        print(f"govnesf sim {args.command}: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bad endpoint string, an unreachable address: say so, no traceback
        import zmq

        if isinstance(exc, zmq.ZMQError):
            print(f"govnesf sim {args.command}: ZeroMQ error for {getattr(args, 'ingest', '?')!r}: {exc}",
                  file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    raise SystemExit(main())
