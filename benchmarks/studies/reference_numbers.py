"""Reference 3D segmentation numbers of plain multi-view averaging (OpenScene-2D) on our world.

For held-out scenes of both styles: render views along a robot trajectory, run SimLSeg (the
SIMULATED 2D OV model) on each, fuse its features at ground-truth surface points and score the
3D segmentation (20 ScanNet classes, mIoU over present classes averaged over scenes):

* ``average``: mean over the views the point projects into (10 px border), no depth test;
* ``average_depth``: the same with the 25% relative depth test against the rendered depth;
* ``visible (oracle)``: mean over the views that truly see the point (ray-cast visibility);
* ``visible, 1/z^p (oracle)``: visible views weighted by distance, the headroom a learned
  blending (FusionNet) could take (DESIGN.md, "Where learned blending can win");
* ``visible, SimLSeg quality (oracle)``: visible views weighted by the simulator's own per-pixel
  quality (distance and grazing angle), the best any view weighting can know.

Only points that more than one view truly sees count (the same points for every method).

Usage:
    HF_HUB_OFFLINE=1 .venv/bin/python benchmarks/studies/reference_numbers.py [--scenes 3] [--frames 72]
        [--points 40000] [--distance-power 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from simlseg_calibration import parse_overrides  # noqa: E402

from clients.sim.raycast import SceneRenderer  # noqa: E402
from clients.sim.robot import default_intrinsics, robot_trajectory  # noqa: E402
from clients.sim.scenes import CLASS_NAMES, SCANNET20, generate_scene  # noqa: E402
from clients.sim.simlseg import SimLSeg, SimLSegConfig, view_quality  # noqa: E402
from clients.sim.text import get_text_encoder  # noqa: E402
from mapper.model.baselines import OVView, average_features  # noqa: E402
from mapper.model.ops.geometry import in_view, invert_pose, project_points  # noqa: E402
from mapper.training.metrics import (  # noqa: E402
    average_over_scenes,
    format_scores_table,
    predict_labels,
    scores_from_labels,
)

STYLES = ("apartment", "studio")
HELD_OUT_SEED0 = 9000
"""Reference scenes use seeds 9000.. (the same held-out seeds as the SimLSeg calibration)."""


def visibility_and_quality(renderer: SceneRenderer, view, points: np.ndarray, K: np.ndarray,
                           world_from_cam: np.ndarray, config: SimLSegConfig, border_px: float,
                           tol_m: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Oracle per-point facts of one view.

    Returns:
        visible: (N,) bool, the point projects inside the image (border cut) and the ray from the
            camera centre towards it hits nothing closer than ``tol_m`` before it.
        quality: (N,) float, SimLSeg's per-pixel quality (distance and grazing angle) at the
            point's pixel, 0 where not visible.
    """
    height, width = view.depth_m.shape
    uv, z = project_points(torch.from_numpy(points).double(), torch.from_numpy(K).double(),
                           invert_pose(torch.from_numpy(world_from_cam).double()))
    inside = in_view(uv, z, width, height, border_px=border_px).numpy()
    vis = np.zeros(len(points), bool)
    quality = np.zeros(len(points), np.float32)
    idx = np.nonzero(inside)[0]
    if idx.size == 0:
        return vis, quality
    centre = world_from_cam[:3, 3]
    delta = points[idx].astype(np.float64) - centre
    dist = np.linalg.norm(delta, axis=1)
    t_hit, _ = renderer.cast(np.broadcast_to(centre, delta.shape), delta / dist[:, None])
    vis[idx] = t_hit >= dist - tol_m
    q_img = view_quality(view, config, K)  # (H, W)
    uv_np = uv.numpy()[idx]
    cols = np.clip(np.floor(uv_np[:, 0]).astype(int), 0, width - 1)
    rows = np.clip(np.floor(uv_np[:, 1]).astype(int), 0, height - 1)
    quality[idx] = q_img[rows, cols] * vis[idx]
    return vis, quality


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=3, help="held-out scenes per style")
    ap.add_argument("--frames", type=int, default=72, help="views per scene along a robot trajectory")
    ap.add_argument("--every", type=int, default=1,
                    help="keep every k-th pose of a (frames * every)-pose trajectory (1: consecutive)")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--points", type=int, default=40000, help="ground-truth surface points per scene")
    ap.add_argument("--distance-power", type=float, nargs="+", default=[2.0],
                    help="p of the oracle's 1/z^p view weights (several values: several rows)")
    ap.add_argument("--seed", type=int, default=0, help="SimLSeg seed (combined with the scene seed)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a SimLSegConfig field (repeatable)")
    args = ap.parse_args(argv)

    encoder = get_text_encoder()
    config = SimLSegConfig(**parse_overrides(args.set))
    class_emb = encoder.encode([config.prompt_template.format(n) for n in SCANNET20])  # (20, 384)
    K = np.asarray(default_intrinsics(args.width, args.height), dtype=np.float64)
    methods = ["average", "average_depth", "visible (oracle)"] + [
        f"visible, 1/z^{p:g} (oracle)" for p in args.distance_power] + ["visible, SimLSeg quality (oracle)"]
    t0 = time.time()
    rows = []
    stats = []
    for style in STYLES:
        per_method: dict[str, list] = {m: [] for m in methods}
        for i in range(args.scenes):
            seed = HELD_OUT_SEED0 + i
            scene = generate_scene(seed, style)
            renderer = SceneRenderer(scene)
            sim = SimLSeg(CLASS_NAMES, encoder, seed=args.seed * 1_000_003 + seed, config=config)
            poses = robot_trajectory(scene, args.frames * args.every, seed)[:: args.every]
            points, labels, _ = scene.sample_surface(args.points, seed=seed)
            views, visible, quality = [], [], []
            for f, world_from_cam in enumerate(poses):
                view = renderer.render(K, world_from_cam, args.width, args.height)
                ov = sim.features(view, f, K=K)
                views.append(OVView(ov, K, world_from_cam, (args.width, args.height), view.depth_m))
                v_vis, v_q = visibility_and_quality(renderer, view, points, K, world_from_cam, config,
                                                    border_px=10.0)
                visible.append(v_vis)
                quality.append(v_q)
            vis = np.stack(visible)  # (V, N)
            qual = np.stack(quality)  # (V, N)
            counted = vis.sum(0) > 1
            results = {
                "average": average_features(points, views, use_depth=False),
                "average_depth": average_features(points, views, use_depth=True),
                "visible (oracle)": average_features(points, views, use_depth=False, view_weights=vis),
            }
            for p in args.distance_power:
                results[f"visible, 1/z^{p:g} (oracle)"] = average_features(
                    points, views, use_depth=False, view_weights=vis, distance_power=p)
            results["visible, SimLSeg quality (oracle)"] = average_features(
                points, views, use_depth=False, view_weights=qual)
            for m, (feats, _) in results.items():
                pred = predict_labels(feats.numpy()[counted], class_emb)
                per_method[m].append(scores_from_labels(labels[counted], pred))
            n_eval = int(((labels[counted] >= 0) & (labels[counted] < len(SCANNET20))).sum())
            stats.append(f"{style} seed {seed}: {n_eval} of {args.points} points evaluated "
                         f"(seen by > 1 view, ScanNet-20 label); "
                         f"{float(vis.sum(0)[counted].mean()):.1f} visible views per point")
        for m in methods:
            rows.append((f"{style}: {m}", average_over_scenes(per_method[m])))

    print(f"3D segmentation at ground-truth surface points, SimLSeg features, {args.scenes} held-out "
          f"scenes x {args.frames} views (every {args.every}. robot pose) of {args.width}x{args.height} "
          f"per style (seeds {HELD_OUT_SEED0}.."
          f"{HELD_OUT_SEED0 + args.scenes - 1})")
    print()
    print(format_scores_table(rows))
    print()
    print("\n".join(stats))
    print(f"\n({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
