"""Does the model's own density know which views are occluded? Evidence for docs/how-to/evaluate.md.

The learned OV weights ignore occlusion (``blending_diagnostics.py``). This asks whether the
density field could supply it: for each evaluation point and each candidate view, the
transmittance T of the model's density on the segment from the camera centre to the point
(``mapper.training.evaluate.view_transmittance``, stopping 1.5 voxels short of the point), then

* T on truly visible vs truly occluded candidates (ground-truth visibility, as the diagnostics);
* 3D mIoU without depth when the learned OV weights are multiplied by T (renormalised), and when
  plain averaging (0 px border, the model's candidates) is weighted by T;

for a volume over the frames' depth points (as the "no depth" rows of the evaluation) and over
their frusta (no depth anywhere).

Usage: python benchmarks/studies/density_visibility.py --checkpoint checkpoints/cpu-small.json \\
           --data data/eval [--max-points 5000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from mapper.model.baselines import average_features
from mapper.model.checkpoint import load_model
from mapper.model.ops.geometry import camera_centers
from mapper.training import evaluate as ev
from mapper.training.metrics import NUM_SCANNET_CLASSES, predict_labels, scores_from_labels


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, type=Path)
    p.add_argument("--data", required=True, nargs="+", type=Path)
    p.add_argument("--max-points", type=int, default=5000)
    p.add_argument("--samples", type=int, default=16, help="density samples per camera-point segment")
    args = p.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from mapper.ov.encoders import get_text_encoder

    try:
        model, meta = load_model(args.checkpoint)
        scenes = ev.find_scene_dirs(args.data)
    except (FileNotFoundError, ValueError) as exc:
        print(f"{Path(__file__).name}: {exc}", file=sys.stderr)
        return 2
    settings = ev.EvalSettings(max_points=args.max_points)
    print(f"checkpoint {args.checkpoint} (step {meta.get('step')}), {args.max_points} points a scene, "
          f"{args.samples} samples a segment")
    print("| scene | bounds | mean T visible / occluded candidates | model | model x T | avg 0px "
          "| avg 0px x T | occluded weight: model / model x T | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    text = None
    for d in scenes:
        scene = ev.load_scene(d)
        if text is None:
            text = torch.from_numpy(get_text_encoder().encode(scene.class_names[:NUM_SCANNET_CLASSES]))
        sp = ev.scene_points(scene, settings)
        gt, pts, K, poses = sp.gt, sp.xyz, sp.K, sp.world_from_cam
        visible, occluded = sp.visible, sp.occluded

        def miou(feats: torch.Tensor, gt: np.ndarray = gt, text: torch.Tensor = text) -> float:
            pred = np.asarray(predict_labels(feats.float(), text))
            return 100.0 * scores_from_labels(gt, pred).miou

        for bounds_name, frustum in (("depth points", None), ("frusta", 4.0)):
            t0 = time.perf_counter()
            views, bounds = ev.scene_sources(model, scene, frustum_range_m=frustum)
            views = ev.dataclasses.replace(views, depth_m=None)
            with torch.no_grad():
                volume = model.build_volume(views, bounds)
            centres = camera_centers(views.world_from_cam)  # (N, 3)

            def t_fn(points: torch.Tensor, idx: torch.Tensor, sel: torch.Tensor,
                     volume: torch.Tensor = volume, bounds: ev.VolumeBounds = bounds,
                     centres: torch.Tensor = centres) -> torch.Tensor:
                return ev.view_transmittance(model, volume, bounds, points, centres[idx],
                                             n_samples=args.samples)

            base = ev.blend_points(model, views, volume, bounds, pts)
            vis = ev.blend_points(model, views, volume, bounds, pts, view_weight_fn=t_fn)
            # T for every (point, view) pair, for the averaging rows and the visible/occluded means
            n_views = centres.shape[0]
            parts = []
            for i in range(0, len(pts), 2048):
                chunk = pts[i : i + 2048]
                every = torch.arange(n_views).expand(len(chunk), -1)
                parts.append(t_fn(chunk, every, torch.ones(len(chunk), n_views, dtype=torch.bool)))
            T = torch.cat(parts)  # (P, N)
            avg_views = ev._avg_views(scene)
            cand = ev._averaging_mask(pts, K, poses, scene.image_wh, None, border_px=0.0)  # (P, N)
            avg, _ = average_features(pts, avg_views, use_depth=False, border_px=0.0)
            avg_t, _ = average_features(pts, avg_views, use_depth=False, border_px=0.0,
                                        view_weights=(T * cand).T.contiguous())
            t_vis = float(T[visible & cand].mean())
            t_occ = float(T[occluded & cand].mean())
            share, share_t = ev.occluded_share(base, occluded), ev.occluded_share(vis, occluded)
            print(f"| {scene.name} | {bounds_name} | {t_vis:.2f} / {t_occ:.2f} | {miou(base.ov):.1f} "
                  f"| {miou(vis.ov):.1f} | {miou(avg):.1f} | {miou(avg_t):.1f} "
                  f"| {100 * share:.1f}% / {100 * share_t:.1f}% "
                  f"| {time.perf_counter() - t0:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
