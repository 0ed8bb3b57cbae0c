"""Keyframe poses sent with odometry error, adjusted over a sliding window from dense matches.

The pure-geometry study behind ``triangulation.pose_method = "window"``
(:mod:`mapper.geometry.window_adjust`), without a node: a simulated room's frames are taken as
keyframes one after the other (every ``--stride``-th frame), their poses sent with per-frame
error (``--pose-noise T_M,R_DEG``, 1 sigma per axis, :func:`clients.sim.sensor.noisy_poses`; or
``--drift``: a random walk of such steps). Each new keyframe is matched (DIS flow) with up to
``pose_partners`` of the last ``pose_window`` keyframes (chosen at their current estimates), then
the window is adjusted jointly. Reported, against the true poses: the error of each keyframe's
pose as sent, as adjusted when it arrived (what the node's triangulation would use), and at the
end of the stream (after later keyframes constrained it); medians and 90th percentiles, and the
time per adjustment.

Usage::

    python benchmarks/studies/window_pose_adjust.py --seed 5 --frames 96 --pose-noise 0.02,1.0
    python benchmarks/studies/window_pose_adjust.py --seed 4 --style studio --stride 3 --set pose_window=8
    python benchmarks/studies/window_pose_adjust.py --real ../shared/data/icl_livingroom1 \
        --frames 0 --stride 2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from clients.harness import sim_stream
from clients.sim.sensor import noisy_poses
from mapper.errors import ConfigError
from mapper.geometry.config import DenseFlowConfig, TriangulationConfig
from mapper.geometry.dense_flow import flow_view, select_flow_partners
from mapper.geometry.pose_refine import pose_change
from mapper.geometry.window_adjust import PairMatches, adjust_poses, pair_matches


def _frames(args: argparse.Namespace) -> tuple[Any, list[np.ndarray], np.ndarray]:
    """(images (lazy), K per frame, true poses (F, 4, 4)): the simulated room, or with ``--real`` an
    Open3D-layout sequence read as ``govnesf import`` does (its poses taken as the truth)."""
    if args.real:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from real_sequence import ICL_K, load_sequence

        frames, _ = load_sequence(Path(args.real), ICL_K)
        frames = frames[: args.frames] if args.frames else frames
        return ([f.rgb for f in frames], [np.asarray(f.K, np.float64) for f in frames],
                np.stack([f.world_from_cam for f in frames]).astype(np.float64))
    stream = sim_stream(args.seed, args.frames, args.width, args.height, depth=False, ov=False,
                        style=args.style)
    return ((frame.rgb for frame, _ in stream.frames()), [np.asarray(stream.K, np.float64)] * args.frames,
            np.asarray(stream.poses, np.float64))


def study_config(args: argparse.Namespace) -> TriangulationConfig:
    """The adjustment's settings: the priors at the noise sent, then ``--set`` (ValueError or
    ConfigError on a bad value)."""
    config = TriangulationConfig(pose_prior_m=args.pose_noise[0], pose_prior_deg=args.pose_noise[1])
    for key, value in args.overrides:
        config = dataclasses.replace(config, **{key: type(getattr(config, key))(value)})
    config.validate("--set")
    return config


def run(args: argparse.Namespace) -> dict[str, Any]:
    config = study_config(args)
    flow = DenseFlowConfig()
    images, Ks, truth_all = _frames(args)
    sent_all = noisy_poses(truth_all, args.pose_noise[0], args.pose_noise[1], seed=args.seed,
                           drift=args.drift)
    views: list[Any] = []
    truth: list[np.ndarray] = []
    estimate: list[np.ndarray] = []
    used: list[np.ndarray] = []
    pairs: list[PairMatches] = []
    seconds: list[float] = []
    for k, (rgb, K) in enumerate(zip(images, Ks, strict=True)):
        if k % args.stride:
            continue
        view = flow_view(rgb, K, sent_all[k], flow.max_width)
        views.append(view)
        truth.append(truth_all[k])
        estimate.append(sent_all[k].copy())
        i = len(views) - 1
        lo = max(0, i - config.pose_window + 1)
        t0 = time.perf_counter()
        cands = [dataclasses.replace(views[j], world_from_cam=estimate[j]).posed for j in range(lo, i)]
        new = dataclasses.replace(view, world_from_cam=estimate[i]).posed
        partner_cfg = dataclasses.replace(flow, max_partners=config.pose_partners)
        chosen = select_flow_partners(new, cands, partner_cfg)
        for c in chosen:
            m = pair_matches(view, views[lo + c], i, lo + c, config, flow)
            if m is not None:
                pairs.append(m)
        local = [dataclasses.replace(p, a=p.a - lo, b=p.b - lo) for p in pairs if p.a >= lo and p.b >= lo]
        sent_w = np.stack([v.world_from_cam for v in views[lo:]])
        K_w = np.stack([v.K for v in views[lo:]])
        out = adjust_poses(K_w, sent_w, local, config, start=np.stack(estimate[lo:]))  # as the node
        for j in range(lo, i + 1):
            estimate[j] = out.world_from_cam[j - lo]
        seconds.append(time.perf_counter() - t0)
        used.append(estimate[i].copy())

    def errors(poses: list[np.ndarray]) -> dict[str, float]:
        e = np.array([pose_change(t, p) for t, p in zip(truth, poses, strict=True)])
        return {"median_cm": 100 * float(np.median(e[:, 0])),
                "p90_cm": 100 * float(np.percentile(e[:, 0], 90)),
                "median_deg": float(np.median(e[:, 1])), "p90_deg": float(np.percentile(e[:, 1], 90))}

    return {
        "keyframes": len(views), "pairs": len(pairs),
        "matches_per_pair": float(np.mean([len(p) for p in pairs])) if pairs else 0.0,
        "sent": errors([v.world_from_cam for v in views]), "used": errors(used), "end": errors(estimate),
        "adjust_ms_median": 1e3 * float(np.median(seconds)),
        "adjust_ms_p90": 1e3 * float(np.percentile(seconds, 90)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--style", default="apartment")
    parser.add_argument("--frames", type=int, default=96)
    parser.add_argument("--stride", type=int, default=1, help="every N-th frame is a keyframe")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--pose-noise", default="0.02,1.0", help="T_M,R_DEG per frame (1 sigma per axis)")
    parser.add_argument("--drift", action="store_true", help="a random walk of such steps")
    parser.add_argument("--real", default="", metavar="DIR",
                        help="an Open3D-layout sequence instead of the simulator, e.g. "
                             "../shared/data/icl_livingroom1 (its poses as the truth; --frames 0 = all)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a TriangulationConfig field (pose_window, pose_partners, ...)")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args(argv)
    if args.stride < 1 or args.frames < 0 or (args.frames < 2 and not args.real):
        parser.error(f"--stride must be >= 1 and --frames >= 2 (0 = all with --real); got {args.stride}, "
                     f"{args.frames}")
    if args.real and not Path(args.real).is_dir():
        parser.error(f"--real {args.real!r} is not a folder (an Open3D-layout sequence)")
    try:
        t, r = (float(v) for v in args.pose_noise.split(","))
    except ValueError:
        parser.error(f"--pose-noise must be T_M,R_DEG, got {args.pose_noise!r}")
    args.pose_noise = (t, r)
    args.overrides = []
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or key not in {f.name for f in dataclasses.fields(TriangulationConfig)}:
            parser.error(f"--set {item!r}: expected KEY=VALUE with KEY a TriangulationConfig field")
        args.overrides.append((key, value))
    try:
        study_config(args)
    except (ValueError, ConfigError) as exc:
        parser.error(str(exc))
    result = run(args)
    print(json.dumps(result, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
