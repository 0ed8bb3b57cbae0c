"""Render and segment latency of the learned runtime, dense sampling vs empty-space skipping.

A simulated robot (``clients.sim``, SimLSeg OV features, depth) streams keyframes into a
``KeyframeWindow`` followed by a :class:`mapper.runtime.model_runtime.ModelRuntime`; then:

* ``sync``: the first query applies the window changes (encode each keyframe once, add it to the
  cost volume) -- timed separately, as is the per-version 3D U-Net + occupancy grid;
* ``render``: a held-out view (between two stream poses) at ``--width x --height``, dense
  (every sample on the rays' [near, far] within the volume box) and with empty-space skipping;
  reports latency, evaluated samples, and the difference between the two outputs;
* ``segment``: ``--points`` surface points (back-projected keyframe depth) with method govnesf.

Run (2-core CPU: a few minutes with a trained checkpoint)::

    HF_HUB_OFFLINE=1 .venv/bin/python benchmarks/render_speed.py --checkpoint checkpoints/cpu-small

``--random-init`` uses an untrained ``cpu-small`` model (mechanics only: its density is nearly
uniform, so skipping finds little empty space).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from clients.sim.export import RecordConfig, SimStream  # noqa: E402
from mapper.model.config import get_preset  # noqa: E402
from mapper.model.field import GovNeSF  # noqa: E402
from mapper.node.config import WindowConfig  # noqa: E402
from mapper.node.window import Keyframe, KeyframeWindow  # noqa: E402
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig, RenderFrame  # noqa: E402

TEXTS = ["chair", "table", "sofa", "bed", "wall", "floor"]


def _interpolated_pose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A pose half-way between two (translation averaged, rotation of a re-orthonormalised mean)."""
    pose = np.eye(4)
    pose[:3, 3] = 0.5 * (a[:3, 3] + b[:3, 3])
    u, _, vt = np.linalg.svd(0.5 * (a[:3, :3] + b[:3, :3]))
    pose[:3, :3] = u @ vt
    return pose


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default="checkpoints/cpu-small.safetensors")
    p.add_argument("--random-init", action="store_true", help="untrained cpu-small model instead")
    p.add_argument("--seed", type=int, default=3, help="scene seed")
    p.add_argument("--frames", type=int, default=60, help="stream frames (keyframes are selected)")
    p.add_argument("--window", type=int, default=16, help="max keyframes")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--skip-dense", action="store_true", help="do not time the dense render")
    p.add_argument(
        "--thresholds", nargs="+", type=float, default=None, metavar="SIGMA",
        help="occupancy thresholds (1/m) to time skipping with (default: the runtime's)",
    )  # fmt: skip
    p.add_argument("--min-weight", type=float, default=None, help="appearance pruning weight (runtime's)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--json", metavar="FILE", help="also write the numbers as JSON")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    if args.random_init:
        torch.manual_seed(0)
        runtime = ModelRuntime(
            ModelRuntimeConfig(device="cpu"), model=GovNeSF(get_preset("cpu-small", ov_dim=384))
        )
        model_name = "cpu-small (random init)"
    else:
        runtime = ModelRuntime(ModelRuntimeConfig(checkpoint=args.checkpoint, device="cpu"))
        if not runtime.ready:
            print(runtime.load_error, file=sys.stderr)
            return 1
        model_name = f"{args.checkpoint} (step {runtime.metadata.get('step', '?')})"
    print(f"model: {model_name}; torch threads {torch.get_num_threads()}", flush=True)

    t0 = time.perf_counter()
    stream = SimStream.build(
        RecordConfig(
            seed=args.seed, frames=args.frames, width=160, height=120, depth=True, ov=True, novel_views=0
        )
    )
    window = KeyframeWindow(
        WindowConfig(max_keyframes=args.window, min_translation_m=0.15, min_rotation_deg=12)
    )
    runtime.attach(window)
    surface: list[np.ndarray] = []
    callback_s = 0.0
    for frame, _view in stream.frames():
        kf = Keyframe(
            seq=frame.seq, stamp_ns=frame.stamp_ns, camera="cam0", K=frame.K,
            world_from_cam=frame.world_from_cam, rgb=frame.rgb, depth_m=frame.depth_m, ov=frame.ov,
            ov_space=frame.ov_space,
        )  # fmt: skip
        c0 = time.perf_counter()
        update = window.consider(kf)
        callback_s += time.perf_counter() - c0
        if update.added and frame.depth_m is not None:
            d = frame.depth_m
            rows, cols = np.nonzero(d > 0)
            z = d[rows, cols]
            fx, fy, cx, cy = frame.K
            cam = np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], axis=-1)
            surface.append(cam @ frame.world_from_cam[:3, :3].T + frame.world_from_cam[:3, 3])
    elapsed_s = time.perf_counter() - t0
    print(f"simulated {args.frames} frames -> {len(window)} keyframes in the window in {elapsed_s:.1f} s "
          f"(window callbacks {1e3 * callback_s:.1f} ms in total)", flush=True)  # fmt: skip

    results: dict[str, object] = {"model": model_name, "machine": platform.processor() or platform.machine()}
    t = time.perf_counter()
    runtime.sync()
    results["sync_ms"] = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    bounds, occupancy = runtime.occupancy()
    results["unet_and_occupancy_ms"] = 1e3 * (time.perf_counter() - t)
    results["bounds"] = {"dims": list(bounds.dims), "voxel_size_m": round(bounds.voxel_size_m, 3)}
    results["occupied_fraction"] = float(occupancy.float().mean())
    print(f"sync {results['sync_ms']:.0f} ms, U-Net + occupancy {results['unet_and_occupancy_ms']:.0f} ms, "
          f"volume {bounds.dims} x {bounds.voxel_size_m:.3f} m, "
          f"occupied {100 * results['occupied_fraction']:.1f}%", flush=True)  # fmt: skip

    k = len(stream.poses) // 2
    pose = _interpolated_pose(stream.poses[k], stream.poses[k + 1])
    scale = args.width / 160
    K = np.array([stream.K[0] * scale, stream.K[1] * args.height / 120, args.width / 2, args.height / 2])
    outputs = ["rgb", "depth", "label", "score"]

    def render(skip: bool) -> tuple[RenderFrame, float]:
        t = time.perf_counter()
        frame = runtime.render(K, pose, args.width, args.height, outputs, TEXTS, empty_space_skipping=skip)
        return frame, 1e3 * (time.perf_counter() - t)

    dense = None
    if not args.skip_dense:
        dense, dense_ms = render(False)
        results["render_dense_ms"], results["render_dense_stats"] = dense_ms, dense.stats
        print(f"render {args.width}x{args.height} dense: {dense_ms / 1e3:.2f} s, {dense.stats}", flush=True)
    runs = []
    for threshold in args.thresholds or [runtime.config.occupancy_threshold]:
        runtime.config = replace(
            runtime.config,
            occupancy_threshold=threshold,
            min_weight=runtime.config.min_weight if args.min_weight is None else args.min_weight,
        )
        occupied = float(runtime.occupancy()[1].float().mean())
        frame, ms = render(True)
        run: dict[str, object] = {
            "occupancy_threshold": threshold, "min_weight": runtime.config.min_weight,
            "occupied_fraction": occupied, "render_ms": ms, "stats": frame.stats,
        }  # fmt: skip
        if dense is not None:
            assert dense.rgb is not None and frame.rgb is not None
            assert dense.depth_m is not None and frame.depth_m is not None
            assert dense.label is not None and frame.label is not None
            assert dense.score is not None and frame.score is not None
            drawn = (dense.depth_m > 0) & (frame.depth_m > 0)
            rgb_diff = np.abs(dense.rgb.astype(int) - frame.rgb.astype(int))
            run["vs_dense"] = {
                "rgb_max_abs_of_255": int(rgb_diff.max()),
                "rgb_mean_abs_of_255": round(float(rgb_diff.mean()), 3),
                "depth_mean_abs_m": round(float(np.abs(dense.depth_m - frame.depth_m)[drawn].mean()), 4)
                if drawn.any()
                else None,
                "depth_median_abs_m": round(float(np.median(np.abs(dense.depth_m - frame.depth_m)[drawn])), 4)
                if drawn.any()
                else None,
                "score_max_abs": round(float(np.abs(dense.score - frame.score).max()), 4),
                "label_agreement": round(float((dense.label == frame.label).mean()), 4),
            }
            run["speedup"] = round(float(results["render_dense_ms"]) / ms, 2)  # type: ignore[arg-type]
        runs.append(run)
        print(f"render {args.width}x{args.height} skipping: {run}", flush=True)
    results["render_skipping"] = runs

    pts = np.concatenate(surface)
    rng = np.random.default_rng(0)
    pts = pts[rng.choice(len(pts), size=min(args.points, len(pts)), replace=False)].astype(np.float32)
    for use_depth in (False, True):
        t = time.perf_counter()
        label, _, timing = runtime.segment(pts, TEXTS, use_depth=use_depth)
        elapsed = time.perf_counter() - t
        key = "segment_dgm_ms" if use_depth else "segment_ms"
        results[key] = 1e3 * elapsed
        results[key + "_stages"] = {k: round(v, 1) for k, v in timing.items()}
        print(f"segment {len(pts)} points (use_depth={use_depth}): {elapsed:.2f} s, labelled "
              f"{100 * (label >= 0).mean():.1f}%, stages {results[key + '_stages']}", flush=True)  # fmt: skip
    results["points"] = len(pts)
    results["runtime"] = runtime.stats()
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
