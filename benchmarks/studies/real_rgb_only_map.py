"""The RGB-only node on real frames: global-map points from posed RGB on the ICL-NUIM sequence.

Streams the real sequence in ``../shared/data/icl_livingroom1`` (211 frames, read with the
dataset importer as ``govnesf import`` does, resized to ``--width``) WITHOUT depth and without OV
features (rgb, K, pose only) into an in-process node with the plugins ``govnesf serve`` installs
(the learned model's rendered-depth points, triangulation, and plane-sweep stereo unless
``--modes`` says otherwise); the workers run between frames. The sequence's own depth is used only
as ground truth: every frame's depth back-projected (every 4th pixel) is the true surface.

Reported per mode (``rgb+tri``: stereo off, the node before plane-sweep stereo; ``rgb+tri+stereo``:
the default):

* keyframes, triangulated points per keyframe and their distance to the true surface;
* swept depths kept per keyframe and the sweep's cost per keyframe;
* global-map points: count, and their distance to the true surface (median, p90, within 5 / 10 cm);
* with ``--holdout-every N`` (default 10), every N-th frame (offset N // 2) is NOT streamed; at
  those held-out real poses the node's ``render`` (``--render-width``; at the measured surfaces
  where there are some, ``model.surface_from_map``) and the model's march alone are compared with
  the real frame: depth median relative error (pixels with real depth) and PSNR.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/studies/real_rgb_only_map.py [--width 320]
        [--modes rgb+tri,rgb+tri+stereo]
        [--set model.surface_planes=false]     # node config overrides, as in rgb_only.py
        [--pose-noise 0.02,1.0]                # odometry error on the poses sent

Skips (exit 0, says so) when the sequence is absent.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))

from real_sequence import DEFAULT_DATA, ICL_K, PosedFrame, load_sequence  # noqa: E402
from rgb_only import parse_overrides  # noqa: E402

from clients.sim.sensor import noisy_poses  # noqa: E402
from mapper.node.config import config_from_dict  # noqa: E402
from mapper.node.serve import install_serve_stages  # noqa: E402
from mapper.node.service import MapperNode  # noqa: E402
from mapper.runtime.model_runtime import ModelRuntime  # noqa: E402
from mapper.training.metrics import masked_psnr  # noqa: E402
from protocol.messages import Frame, Render, RenderResult, decode, encode  # noqa: E402

MODES = {"rgb+tri": False, "rgb+tri+stereo": True}
"""mode -> plane-sweep stereo on."""


def resized(frame: PosedFrame, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb, depth, K) at ``width`` (area-averaged colour, nearest depth, K scaled)."""
    h, w = frame.rgb.shape[:2]
    s = width / w
    size = (width, round(h * s))
    rgb = cv2.resize(frame.rgb, size, interpolation=cv2.INTER_AREA)
    depth = cv2.resize(frame.depth_m, size, interpolation=cv2.INTER_NEAREST)
    return rgb, depth, np.asarray(frame.K, np.float64) * s


def true_surface(frames: list[PosedFrame], width: int) -> np.ndarray:
    """(N, 3) world points: every frame's depth back-projected, every 4th pixel."""
    parts = []
    for f in frames:
        _, depth, K = resized(f, width)
        rows, cols = np.nonzero(depth[::4, ::4] > 0)
        rows, cols = rows * 4, cols * 4
        z = depth[rows, cols].astype(np.float64)
        cam = np.stack([(cols + 0.5 - K[2]) / K[0] * z, (rows + 0.5 - K[3]) / K[1] * z, z], axis=-1)
        pose = np.asarray(f.world_from_cam, np.float64)
        parts.append(cam @ pose[:3, :3].T + pose[:3, 3])
    return np.concatenate(parts)


def _distances(tree: cKDTree, xyz: np.ndarray) -> dict[str, float | None]:
    if len(xyz) == 0:
        return {"median_m": None, "p90_m": None, "within_5cm": None, "within_10cm": None}
    d = tree.query(np.asarray(xyz, np.float64))[0]
    return {"median_m": float(np.median(d)), "p90_m": float(np.percentile(d, 90)),
            "within_5cm": float((d <= 0.05).mean()), "within_10cm": float((d <= 0.10).mean())}  # fmt: skip


def _held_out_renders(node: MapperNode, runtime: ModelRuntime, frames: list[PosedFrame], width: int
                      ) -> dict[str, Any]:  # fmt: skip
    """The node's ``render`` and the model's march alone at held-out real poses, against the real
    frames: depth median relative error (pooled over the pixels with real depth) and mean PSNR."""
    rel: dict[str, list[np.ndarray]] = {"render": [], "march": []}
    psnr: dict[str, list[float]] = {"render": [], "march": []}
    share = []
    for f in frames:
        rgb, depth, K = resized(f, width)
        h, w = depth.shape
        pose = np.asarray(f.world_from_cam, np.float64)
        request = Render(width=w, height=h, K=K, world_from_cam=pose, outputs=["rgb", "depth"])
        reply = decode(node.handle_query(encode(request)), direction="reply")
        assert isinstance(reply, RenderResult) and reply.rgb is not None and reply.depth_m is not None, reply
        march = runtime.render(K, pose, w, h, outputs=("rgb", "depth"))
        assert march.rgb is not None and march.depth_m is not None
        ok = depth > 0
        outs = (("render", reply.rgb, reply.depth_m), ("march", march.rgb, march.depth_m))
        for name, out_rgb, out_depth in outs:
            rel[name].append(np.abs(out_depth[ok] - depth[ok]) / depth[ok])
            psnr[name].append(masked_psnr(out_rgb, rgb, max_value=255.0))
        share.append(reply.timing_ms.get("surface_pixels", 0.0) / (w * h))
    return {
        "held_out": len(frames), "render_width": width,
        "render_depth_median_rel_err": float(np.median(np.concatenate(rel["render"]))),
        "render_psnr_db": float(np.mean(psnr["render"])), "render_surface_share": float(np.mean(share)),
        "march_depth_median_rel_err": float(np.median(np.concatenate(rel["march"]))),
        "march_psnr_db": float(np.mean(psnr["march"])),
    }  # fmt: skip


def run(frames: list[PosedFrame], tree: cKDTree, args: argparse.Namespace, stereo: bool) -> dict[str, Any]:
    sections: dict[str, dict[str, Any]] = {
        "window": {"max_keyframes": args.window},
        "model": {"checkpoint": str(args.checkpoint), "device": "cpu"},
        "stereo": {"enabled": stereo},
    }
    for section, name, value in args.overrides:  # checked in main()
        sections.setdefault(section, {})[name] = value
    config = config_from_dict({
        "map_dir": "/tmp/govnesf-bench-maps", "autosave_name": "", "save_on_exit": False, **sections,
    })  # fmt: skip
    node = MapperNode(config)
    plugins = install_serve_stages(node)  # as `govnesf serve` builds it
    runtime, rendered, tri = plugins.runtime, plugins.rendered_depth, plugins.triangulation
    if runtime is None or not runtime.ready:
        raise SystemExit(runtime.load_error if runtime is not None else "serve_model is off")
    assert tri is not None
    started = time.perf_counter()
    every = args.holdout_every
    held_out = [k for k in range(len(frames)) if every > 0 and k % every == every // 2]
    truth = np.stack([np.asarray(f.world_from_cam, np.float64) for f in frames])
    sent = noisy_poses(truth, *args.pose_noise, seed=0) if args.pose_noise else truth
    try:
        for k, f in enumerate(frames):
            if k in held_out:
                continue
            rgb, _, K = resized(f, args.width)
            node.handle_ingest(encode(Frame(
                seq=k, stamp_ns=int(f.stamp_ns) or (k + 1) * 33_000_000, width=rgb.shape[1],
                height=rgb.shape[0], K=K, world_from_cam=sent[k], rgb=rgb,
            )))  # fmt: skip
            if (k + 1) % args.process_every == 0:
                tri.process_pending()
                if rendered is not None:
                    rendered.process_pending()
        tri.process_pending()
        if rendered is not None:
            rendered.process_pending()
        stats = tri.stats()
        snap = node.state.global_map.snapshot()
        row: dict[str, Any] = {
            "mode": "rgb+tri+stereo" if stereo else "rgb+tri",
            "frames": len(frames), "width": args.width,
            "keyframes": stats["keyframes"], "tri_points_per_keyframe": stats["points_per_keyframe"],
            "tri_points": _distances(tree, tri.points()[0]),
            "worker_ms_per_keyframe": stats["mean_ms"],
            "stereo_depths_per_keyframe": stats["stereo"]["depths_per_keyframe"],
            "stereo_ms_per_keyframe": stats["stereo"]["mean_ms"],
            "map_points": len(snap), "map": _distances(tree, snap.xyz), "poses": stats["poses"],
            "wall_s": time.perf_counter() - started,
        }  # fmt: skip
        if held_out:
            row.update(_held_out_renders(node, runtime, [frames[k] for k in held_out], args.render_width))
        return row
    finally:
        node.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--width", type=int, default=320, help="frames are resized to this width")
    p.add_argument("--window", type=int, default=30)
    p.add_argument("--modes", default="rgb+tri,rgb+tri+stereo", help="comma-separated: " + ", ".join(MODES))
    p.add_argument("--checkpoint", type=Path, default=ROOT / "checkpoints" / "cpu-small.json")
    p.add_argument("--process-every", type=int, default=10, help="frames between worker passes")
    p.add_argument("--holdout-every", type=int, default=10,
                   help="every N-th frame (offset N // 2) is held out and rendered (0 = none)")
    p.add_argument("--render-width", type=int, default=160, help="width of the held-out renders")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", type=Path)
    p.add_argument("--pose-noise", default="", metavar="T_M,R_DEG",
                   help="per-frame pose error sent to the node (1 sigma per axis, "
                        "clients.sim.sensor.noisy_poses, seed 0), e.g. 0.02,1.0; the ground truth and "
                        "the held-out renders keep the true poses")
    p.add_argument("--set", nargs="*", action="extend", default=[], metavar="SECTION.KEY=VALUE",
                   help="node config overrides, e.g. model.surface_planes=false")
    args = p.parse_args(argv)
    args.overrides = parse_overrides(args.set)
    try:
        args.pose_noise = tuple(float(v) for v in args.pose_noise.split(",")) if args.pose_noise else ()
    except ValueError:
        p.error(f"--pose-noise must be T_M,R_DEG, got {args.pose_noise!r}")
    if args.pose_noise and len(args.pose_noise) != 2:
        p.error(f"--pose-noise must be T_M,R_DEG, got {args.pose_noise!r}")
    if args.holdout_every < 0 or not 8 <= args.render_width <= 4096:
        p.error(f"--holdout-every must be >= 0 (got {args.holdout_every}) and --render-width 8..4096 "
                f"(got {args.render_width})")
    unknown = [m for m in args.modes.split(",") if m.strip() not in MODES]
    if unknown:
        raise SystemExit(f"--modes: unknown {unknown}; choose from {', '.join(MODES)}")
    if not args.data.is_dir():
        print(f"real sequence {args.data} not found: skipped")
        return 0
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    frames, _ = load_sequence(args.data, ICL_K)
    tree = cKDTree(true_surface(frames, args.width))
    rows = []
    for mode in args.modes.split(","):
        row = run(frames, tree, args, MODES[mode.strip()])
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| mode | keyframes | triangulated / keyframe (median error) | swept depths / keyframe | "
          "worker ms / keyframe | map points | map median / p90 error | within 5 / 10 cm |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        m, t = r["map"], r["tri_points"]
        tri_err = "-" if t["median_m"] is None else f"{100 * t['median_m']:.1f} cm"
        med = "-" if m["median_m"] is None else f"{m['median_m']:.3f} / {m['p90_m']:.3f} m"
        within = ("-" if m["within_5cm"] is None
                  else f"{100 * m['within_5cm']:.0f}% / {100 * m['within_10cm']:.0f}%")
        print(f"| {r['mode']} | {r['keyframes']} | {r['tri_points_per_keyframe']} ({tri_err}) | "
              f"{r['stereo_depths_per_keyframe']} | {r['worker_ms_per_keyframe']} | {r['map_points']} | "
              f"{med} | {within} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
