"""RGB-only robots: sparse triangulated geometry, volume bounds, 3D mIoU and "find the chair".

Streams a simulated room into an in-process node (the node's real plugins: the learned model's
handlers, rendered-depth map points, and :mod:`mapper.node.workers.triangulation`) three times:

* ``depth``: frames with depth (the reference: what a robot with a depth camera gets);
* ``rgb, fixed range``: frames WITHOUT depth, triangulation off (the node before triangulation:
  volume bounds from the frusta up to ``model.max_range_m``, map points from rendered depth only);
* ``rgb + triangulation``: frames WITHOUT depth, triangulation on (bounds follow the points, and
  the points join the global map), stereo off;
* ``rgb + triangulation + stereo``: the same with dense plane-sweep depth (the node's default).

Reported per run (``--json`` writes them all):

* ack rate of the ingest path (in-process ``handle_ingest`` time only; the background workers run
  between frames, timed separately);
* triangulation: keyframes, points per keyframe, cost per keyframe (mean and p90, ms), and the
  points' distance to the true surface (nearest of ``--gt-samples`` samples of the scene's
  surfaces: about 1 cm apart in the demo room; median, p90, share within 5 cm);
* the cost volume's bounds (extent, voxel size);
* 3D mIoU of ``segment_points`` at the ground-truth surface samples the stream saw: ``govnesf``
  (learned), ``govnesf`` + DGM, ``average`` (plain averaging) and ``average_depth``, same points,
  class names as texts (without depth the depth test takes the request's points as occluders,
  ``model.point_occlusion`` / ``queries.point_occlusion``); and the same at the global map's own
  points (``map_miou_*``: what a robot asks about; each scored against the nearest ground-truth
  sample within 0.1 m, the rest left in the request and not scored);
* "find the chair": the top object's distance to the nearest real chair;
* with ``--pose-noise T_M,R_DEG`` the frames carry poses with that per-frame error (1 sigma per
  axis, :func:`clients.sim.sensor.noisy_poses`; the ground truth keeps the true ones): the keyframes'
  median pose error as sent and as the triangulation worker used them (refined where
  ``triangulation.refine_poses`` refined them), and the worker's ``poses`` status;
* the global map's points: their distance to the true surface (median, p90);
* with ``rgb+tri+stereo``, plane-sweep stereo (:mod:`mapper.geometry.plane_sweep`) on top of the
  triangulation: depths kept per keyframe, cost per keyframe, points added to the global map;
* at held-out poses (``clients.sim.export.novel_view_poses``): the node's ``render`` depth (median
  relative error) and colour (PSNR against the simulator's image, mean over the poses), at the
  measured surfaces where there are some (``model.surface_from_map``: the global map with depth,
  the triangulated and swept points without, and their planes, ``model.surface_planes``; the share
  of the pixels at a surface, of those on a plane, the planes' count, and the surface step's time
  in the first render, which fits the planes, and the later ones); the model's march alone
  (every pixel marched: depth and PSNR); the global map's surface alone
  (:func:`mapper.node.queries.map_surface_depth`: its error and its share of the pixels).

Usage::

    python benchmarks/studies/rgb_only.py --seed 3 --style apartment            # the demo room
    python benchmarks/studies/rgb_only.py --seed 9 --style studio               # 7.8 x 6.7 m, held-out style
    python benchmarks/studies/rgb_only.py --modes rgb+tri --frames 120          # one run, shorter
    python benchmarks/studies/rgb_only.py --modes rgb+tri+stereo --frames 96 --pose-noise 0.02,1.0 \
        --set triangulation.refine_poses=true                                   # odometry error, refined
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
import torch
from scipy.spatial import cKDTree

from clients.harness import chair_distance, mean_iou, sim_stream
from clients.sim.export import count_views, novel_view_poses
from clients.sim.scenes import CLASS_NAMES, LABEL_OF
from clients.sim.sensor import noisy_poses
from mapper.errors import ConfigError
from mapper.geometry.pose_refine import pose_change
from mapper.node.config import config_from_dict
from mapper.node.queries import map_surface_depth
from mapper.node.serve import install_serve_stages
from mapper.node.service import MapperNode
from mapper.training.metrics import masked_psnr
from protocol.messages import (
    Error,
    Points,
    QueryPoints,
    Render,
    RenderResult,
    Segmentation,
    SegmentPoints,
    decode,
    encode,
)

MAP_LABEL_RADIUS_M = 0.1
"""A global-map point is scored against the nearest ground-truth surface sample within this."""

MODES = {
    "depth": (True, True, False),
    "rgb": (False, False, False),
    "rgb+tri": (False, True, False),
    "rgb+tri+stereo": (False, True, True),
}
"""mode -> (frames carry depth, triangulation on, plane-sweep stereo on)."""



def _timed_pending(worker: Any) -> float:
    """Run a plugin's pending work inline (``None``: nothing); returns the seconds it took."""
    t0 = time.perf_counter()
    if worker is not None:
        worker.process_pending()
    return time.perf_counter() - t0

def _query(node: MapperNode, msg: Any) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def run(args: argparse.Namespace, mode: str) -> dict[str, Any]:
    with_depth, triangulate, stereo = MODES[mode]
    stream = sim_stream(args.seed, args.frames, args.width, args.height, depth=with_depth, style=args.style)
    scene = stream.scene
    config = config_from_dict({
        "map_dir": "/tmp/govnesf-bench-maps", "autosave_name": "", "save_on_exit": False,
        "window": {"max_keyframes": args.window},
        "model": {"checkpoint": str(args.checkpoint), "device": args.device},
        "triangulation": {"enabled": triangulate},
        "stereo": {"enabled": stereo},
    })
    for section, name, value in args.overrides:  # checked in main()
        current = _as_dict(config)
        config = config_from_dict({**current, section: {**current.get(section, {}), name: value}})
    node = MapperNode(config)
    plugins = install_serve_stages(node)  # as `govnesf serve` builds it
    runtime, rendered, tri = plugins.runtime, plugins.rendered_depth, plugins.triangulation
    if runtime is None or not runtime.ready:
        raise SystemExit(runtime.load_error if runtime is not None else "serve_model is off")
    n_gt = args.gt_samples
    gt_xyz, gt_label, _ = scene.sample_surface(n_gt, seed=args.seed, exclude_labels=(LABEL_OF["ceiling"],))
    surface, _, _ = scene.sample_surface(args.gt_samples * 4, seed=args.seed + 1)
    gt_views = np.zeros(len(gt_xyz), np.int32)
    ack_s = worker_tri_s = worker_depth_s = 0.0
    sent_poses = (noisy_poses(stream.poses, args.pose_noise[0], args.pose_noise[1], seed=args.seed)
                  if args.pose_noise else None)
    for k, (frame, view) in enumerate(stream.frames()):
        count_views(gt_xyz, stream.K, stream.poses[k], view.depth_m, gt_views)
        if sent_poses is not None:  # odometry's error: the node gets these, the ground truth stays
            frame = dataclasses.replace(frame, world_from_cam=sent_poses[k].copy())
        data = encode(frame)
        t0 = time.perf_counter()
        node.handle_ingest(data)
        ack_s += time.perf_counter() - t0
        if (k + 1) % args.process_every == 0:  # the workers, inline between frames (timed apart)
            worker_tri_s += _timed_pending(tri)
            worker_depth_s += _timed_pending(rendered)
    worker_tri_s += _timed_pending(tri)
    worker_depth_s += _timed_pending(rendered)
    row: dict[str, Any] = {
        "mode": mode, "seed": args.seed, "style": args.style, "frames": args.frames,
        "room_m": [round(float(v), 2) for v in scene.room_max - scene.room_min],
        "keyframes": len(node.state.window) + node.state.keyframes_evicted,
        "acks_per_s": args.frames / max(ack_s, 1e-9),
        "rendered_depth_worker_s": worker_depth_s,
    }
    if tri is not None:
        stats = tri.stats()
        xyz, sigma = tri.points()
        dist = cKDTree(surface).query(xyz)[0] if len(xyz) else np.zeros(0)
        row.update({
            "tri_keyframes": stats["keyframes"], "tri_points": int(len(xyz)),
            "tri_points_per_keyframe": stats["points_per_keyframe"], "tri_ms_mean": stats["mean_ms"],
            "tri_ms_p90": stats["p90_ms"], "tri_worker_s": worker_tri_s,
            "tri_median_dist_m": float(np.median(dist)) if len(dist) else None,
            "tri_p90_dist_m": float(np.percentile(dist, 90)) if len(dist) else None,
            "tri_within_5cm": float((dist <= 0.05).mean()) if len(dist) else None,
            "tri_median_sigma_m": float(np.median(sigma)) if len(sigma) else None,
            "tri_global_map_points": stats["global_map_points"],
        })
        if sent_poses is not None:
            row.update(_pose_errors(node, tri, stream.poses))
        if stereo:
            st = stats["stereo"]
            row.update({
                "stereo_keyframes": st["keyframes"], "stereo_depths_per_keyframe": st["depths_per_keyframe"],
                "stereo_ms_mean": st["mean_ms"], "stereo_global_map_points": st["global_map_points"],
            })
    runtime.sync()
    b = runtime.bounds
    assert b is not None
    row["bounds_extent_m"] = [round(n * b.voxel_size_m, 2) for n in b.dims]
    row["voxel_size_m"] = round(b.voxel_size_m, 4)
    seen = gt_views > 0
    pts, gt = gt_xyz[seen].astype(np.float32), gt_label[seen].astype(np.int64)
    texts = list(CLASS_NAMES)
    # with use_depth the depth test: input depth; without, the request's points as occluders
    # (model.point_occlusion, queries.point_occlusion) or, with those off, the keyframes' depth priors
    methods = [("govnesf", False), ("average", False), ("govnesf", True), ("average_depth", True)]

    def score(prefix: str, xyz: np.ndarray, scored: np.ndarray, truth: np.ndarray, timings: bool) -> None:
        """mIoU of every method's answer at ``xyz`` (rows ``scored`` against ``truth``), as
        ``row[prefix + method]``; None where the node has no such test (settings off). ``timings``:
        also the node's own stage timings (ms), as ``row["ms_" + stage + "_" + method]``."""
        for method, use_depth in methods:
            seg = _query(node, SegmentPoints(xyz=xyz, texts=texts, method=method, use_depth=use_depth))  # type: ignore[arg-type]
            name = f"{prefix}{method}{'+dgm' if use_depth and method == 'govnesf' else ''}"
            if isinstance(seg, Error) and seg.code == "not_ready":
                row[name] = None
                continue
            assert isinstance(seg, Segmentation), seg
            row[name] = mean_iou(seg.label[scored].astype(np.int64), truth, len(texts))[0]
            for stage in ("total", "occluders", "view_selection") if timings else ():
                if stage in seg.timing_ms:
                    row[f"ms_{stage}_{name[len(prefix):]}"] = seg.timing_ms[stage]

    score("miou_", pts, np.ones(len(pts), bool), gt, timings=True)
    row["segment_points"] = len(pts)
    # a robot's own case: segment_points at the global map's points (what query_points returns),
    # each scored against the nearest ground-truth surface sample's label within MAP_LABEL_RADIUS_M
    # (farther map points stay in the request, e.g. as occluders, and are not scored)
    map_xyz = np.asarray(node.state.global_map.snapshot().xyz, np.float32)
    if len(map_xyz):
        near_d, near_i = cKDTree(gt_xyz).query(map_xyz)
        scored = near_d <= MAP_LABEL_RADIUS_M
        row["map_scored_points"] = int(scored.sum())
        score("map_miou_", map_xyz, scored, gt_label[near_i[scored]].astype(np.int64), timings=False)
    reply = _query(node, QueryPoints(texts=["find the chair"], objects=True))
    row["chair_m"] = (chair_distance(reply.objects[0].centroid, scene)
                      if isinstance(reply, Points) and reply.objects else None)
    poses, _ = novel_view_poses(stream, args.novel_views, seed=args.seed)
    snap = node.state.global_map.snapshot()
    # depth (and colour) at the held-out poses: the node's `render` (the map's surface where it has
    # one, model.surface_from_map), the model's march alone, and the map's surface alone
    cfg = config.model
    rel_node, rel_march, rel_map, cover, psnr, psnr_march, at_surface = [], [], [], [], [], [], []
    at_plane: list[float] = []
    surface_ms: list[float] = []  # the first render fits the planes of the geometry, the others reuse them
    n_planes = 0.0
    for pose in poses:
        truth = stream.renderer.render(stream.K, pose, args.width, args.height)
        ok = (truth.depth_m > 0) & np.isfinite(truth.depth_m)
        gt = truth.depth_m[ok]
        reply = _query(node, Render(width=args.width, height=args.height, K=np.asarray(stream.K, np.float64),
                                    world_from_cam=np.asarray(pose, np.float64), outputs=["rgb", "depth"]))
        assert isinstance(reply, RenderResult) and reply.depth_m is not None and reply.rgb is not None, reply
        rel_node.append(np.abs(reply.depth_m[ok] - gt) / gt)
        at_surface.append(reply.timing_ms.get("surface_pixels", 0.0) / (args.width * args.height))
        at_plane.append(reply.timing_ms.get("plane_pixels", 0.0) / (args.width * args.height))
        surface_ms.append(reply.timing_ms.get("map_surface", 0.0))
        n_planes = reply.timing_ms.get("planes", 0.0)
        psnr.append(masked_psnr(reply.rgb, truth.rgb, max_value=255.0))
        march = runtime.render(stream.K, pose, args.width, args.height, outputs=("rgb", "depth"))
        assert march.depth_m is not None and march.rgb is not None
        rel_march.append(np.abs(march.depth_m[ok] - gt) / gt)
        psnr_march.append(masked_psnr(march.rgb, truth.rgb, max_value=255.0))
        z_map = map_surface_depth(snap, np.asarray(stream.K, np.float64), pose, args.width, args.height, cfg)
        m = ok & (z_map > 0)
        rel_map.append(np.abs(z_map[m] - truth.depth_m[m]) / truth.depth_m[m])
        cover.append(m.sum() / max(1, ok.sum()))
    row["render_depth_median_rel_err"] = float(np.median(np.concatenate(rel_node)))
    row["render_psnr_db"] = float(np.mean(psnr))
    row["render_surface_share"] = float(np.mean(at_surface))  # pixels rendered at a measured surface
    row["render_plane_share"] = float(np.mean(at_plane))  # ... of which on a plane of the geometry
    row["render_planes"] = n_planes
    row["render_surface_ms_first"] = surface_ms[0] if surface_ms else None
    row["render_surface_ms_later"] = float(np.median(surface_ms[1:])) if len(surface_ms) > 1 else None
    row["march_depth_median_rel_err"] = float(np.median(np.concatenate(rel_march)))
    row["march_psnr_db"] = float(np.mean(psnr_march))
    on_map = np.concatenate(rel_map)
    row["map_surface_depth_median_rel_err"] = float(np.median(on_map)) if on_map.size else None
    row["map_surface_cover"] = float(np.mean(cover))
    row["global_map_points"] = len(snap)
    if len(snap):  # the map's geometry: each point's distance to the true surface
        map_dist = cKDTree(surface).query(np.asarray(snap.xyz, np.float64))[0]
        row["map_median_dist_m"] = float(np.median(map_dist))
        row["map_p90_dist_m"] = float(np.percentile(map_dist, 90))
    node.stop()
    return row


def _pose_errors(node: MapperNode, tri: Any, truth: np.ndarray) -> dict[str, Any]:
    """The RGB-only keyframes' pose errors against ``truth`` (by seq): as sent, and as the
    triangulation worker used them (refined or as sent); medians in cm and degrees."""
    refined = tri.poses.refined()
    sent_err, used_err = [], []
    for kf in node.state.window.keyframes:
        if kf.depth_m is not None:
            continue
        key = (str(kf.camera), int(kf.seq), int(kf.stamp_ns))
        sent_err.append(pose_change(truth[kf.seq], kf.world_from_cam))
        used_err.append(pose_change(truth[kf.seq], refined.get(key, kf.world_from_cam)))
    s, u = np.array(sent_err).reshape(-1, 2), np.array(used_err).reshape(-1, 2)
    poses = tri.stats()["poses"]
    return {
        "pose_keyframes": len(s), "pose_refined": poses["refined"],
        "pose_sent_median_cm": 100 * float(np.median(s[:, 0])),
        "pose_sent_median_deg": float(np.median(s[:, 1])),
        "pose_used_median_cm": 100 * float(np.median(u[:, 0])),
        "pose_used_median_deg": float(np.median(u[:, 1])),
        "pose_move_median_cm": poses["median_translation_cm"], "pose_kept": poses["kept_as_sent"],
    }


def parse_overrides(items: list[str]) -> list[tuple[str, str, Any]]:
    """``SECTION.KEY=VALUE`` items (TOML values: 0, 0.5, true, "text") -> (section, key, value),
    each checked against the node config; a bad one exits with a message before any work."""
    out = []
    for item in items:
        key, eq, text = item.partition("=")
        section, dot, name = key.partition(".")
        try:
            if not (eq and dot and section and name):
                raise ValueError("expected SECTION.KEY=VALUE")
            value = tomllib.loads(f"v = {text}")["v"]
            config_from_dict({section: {name: value}})
        except (ValueError, ConfigError) as exc:  # TOMLDecodeError is a ValueError
            raise SystemExit(f"--set {item!r}: {exc}") from None
        out.append((section, name, value))
    return out


def _as_dict(config: Any) -> dict[str, Any]:
    return dataclasses.asdict(config)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 10 else f"{v:.0f}"
    return str(v)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--style", default="apartment")
    p.add_argument("--frames", type=int, default=240)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--window", type=int, default=160)
    p.add_argument("--modes", default="depth,rgb,rgb+tri", help="comma-separated: " + ", ".join(MODES))
    p.add_argument("--gt-samples", type=int, default=250_000, help="ground-truth surface samples")
    p.add_argument("--novel-views", type=int, default=4)
    p.add_argument("--checkpoint", type=Path, default=Path("checkpoints/cpu-small.json"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--process-every", type=int, default=10, help="frames between worker passes")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    p.add_argument("--pose-noise", default="", metavar="T_M,R_DEG",
                   help="per-frame pose error sent to the node (1 sigma per axis), e.g. 0.02,1.0")
    p.add_argument("--set", nargs="*", action="extend", default=[], metavar="SECTION.KEY=VALUE",
                   help="node config overrides, e.g. stereo.prior_fill_px=16")
    args = p.parse_args(argv)
    unknown = [m for m in args.modes.split(",") if m.strip() not in MODES]
    if unknown:
        raise SystemExit(f"--modes: unknown {unknown}; choose from {', '.join(MODES)}")
    args.overrides = parse_overrides(args.set)
    args.pose_noise = tuple(float(v) for v in args.pose_noise.split(",")) if args.pose_noise else ()
    if args.pose_noise and len(args.pose_noise) != 2:
        raise SystemExit("--pose-noise: expected T_M,R_DEG, e.g. 0.02,1.0")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    torch.set_num_threads(args.threads)
    rows = []
    for mode in args.modes.split(","):
        started = time.perf_counter()
        row = run(args, mode.strip())
        row["wall_s"] = time.perf_counter() - started
        rows.append(row)
        print(json.dumps({k: _fmt(v) for k, v in row.items()}), flush=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    print("\n| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(_fmt(r.get(k, "")) for k in keys) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
