"""Does the learned blending avoid occluded views? Evidence for docs/how-to/evaluate.md.

For each held-out scene, at ground-truth points seen by > 1 view, without depth:

* weight ratio: mean OV blending weight a truly OCCLUDED candidate view gets, divided by the mean
  weight of a truly VISIBLE candidate of the same point (1.0 = no preference, as plain averaging;
  0 = occluded views ignored). Visibility from the ground-truth depth (``gt_visibility``).
* occluded share: fraction of the total weight on occluded views (model vs uniform averaging
  over the same candidate views).
* border: averaging cuts a 10 px image border (OpenScene-2D), the model does not, so a few
  percent of the points have no averaging view (they get label 0). mIoU of averaging without
  depth with the 10 px cut, with no cut, and of the model, on all points and on the points the
  10 px cut keeps (same points for both).
* occlusion errors: points that averaging without depth gets wrong but averaging over the truly
  visible views (oracle) gets right; the fraction of them the learned blending gets right. These
  are the points where occlusion reasoning pays.

Usage: python benchmarks/studies/blending_diagnostics.py --checkpoint checkpoints/cpu-small.json \\
           --data data/eval [--max-points 10000]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

from mapper.model.baselines import average_features
from mapper.model.checkpoint import load_model
from mapper.training import evaluate as ev
from mapper.training.metrics import NUM_SCANNET_CLASSES, predict_labels, scores_from_labels


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, type=Path)
    p.add_argument("--data", required=True, nargs="+", type=Path)
    p.add_argument("--max-points", type=int, default=10000)
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
    print(f"checkpoint {args.checkpoint} (step {meta.get('step')})")
    print("| scene | candidate views / point | occluded candidates | model weight occluded/visible "
          "| occluded share: model / uniform | occlusion-error points | fixed by model "
          "| mIoU avg 10px / avg 0px / model | same on points with a 10px view |")
    print("|---|---|---|---|---|---|---|---|---|")
    text = None
    for d in scenes:
        scene = ev.load_scene(d)
        if text is None:
            text = torch.from_numpy(get_text_encoder().encode(scene.class_names[:NUM_SCANNET_CLASSES]))
        sp = ev.scene_points(scene, settings)
        gt, pts, visible = sp.gt, sp.xyz, sp.visible
        views, bounds = ev.scene_sources(model, scene)
        with torch.no_grad():
            volume = model.build_volume(views, bounds)
        pb = ev.blend_points(model, views, volume, bounds, pts)
        vis_sel = visible.gather(1, pb.view_index) & pb.mask  # (P, k)
        occ_sel = ~visible.gather(1, pb.view_index) & pb.mask
        w = pb.weights
        both = occ_sel.any(1) & vis_sel.any(1)
        # per point: mean weight of occluded / mean weight of visible candidates, averaged
        w_occ = (w * occ_sel).sum(1) / occ_sel.sum(1).clamp_min(1)
        w_vis = (w * vis_sel).sum(1) / vis_sel.sum(1).clamp_min(1)
        ratio = float((w_occ[both] / w_vis[both].clamp_min(1e-12)).mean())
        share_model = float((w * occ_sel).sum(1)[pb.valid].mean())
        share_uniform = float((occ_sel.sum(1) / pb.mask.sum(1).clamp_min(1))[pb.valid].mean())
        avg_views = ev._avg_views(scene)
        f_avg, n_avg = average_features(pts, avg_views, use_depth=False)
        f_avg0, _ = average_features(pts, avg_views, use_depth=False, border_px=0.0)
        f_orc, _ = average_features(pts, avg_views, use_depth=False, view_weights=visible.T)
        p_avg = np.asarray(predict_labels(f_avg, text))
        p_orc = np.asarray(predict_labels(f_orc, text))
        p_mod = np.asarray(predict_labels(pb.ov, text))
        occl_err = (p_avg != gt) & (p_orc == gt)
        fixed = float((p_mod[occl_err] == gt[occl_err]).mean()) if occl_err.any() else float("nan")
        p_avg0 = np.asarray(predict_labels(f_avg0, text))
        ok = n_avg.numpy() > 0

        def miou(pred: np.ndarray, sel: np.ndarray | slice = slice(None), gt: np.ndarray = gt) -> str:
            return f"{100 * scores_from_labels(gt[sel], pred[sel]).miou:.1f}"

        border = f"{miou(p_avg)} / {miou(p_avg0)} / {miou(p_mod)}"
        border_ok = f"{miou(p_avg, ok)} / {miou(p_avg0, ok)} / {miou(p_mod, ok)}"
        print(f"| {scene.name} | {float(pb.num_views.float().mean()):.1f} | "
              f"{float(occ_sel.sum(1).float().mean()):.1f} | {ratio:.2f} | "
              f"{100 * share_model:.1f}% / {100 * share_uniform:.1f}% | "
              f"{100 * occl_err.mean():.1f}% | {100 * fixed:.1f}% | {border} | {border_ok} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
