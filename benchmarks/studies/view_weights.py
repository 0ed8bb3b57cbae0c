"""Which weighting of the same candidate views helps 3D segmentation? (the blend's cues)

On the evaluation's points (``mapper.training.evaluate``: labelled, seen by > 1 frame), every view
that sees a point (and, with DGM, passes the depth test) is sampled once; the OV features are then
blended with different per-view weights over exactly those views:

* ``learned``: FusionNet's OV blending weights (``blend_points``), ``uniform``: plain averaging;
* ``x dist(a, s)``: times ``exp(-max(r - a, 0) / s)`` of the camera-to-point distance ``r``
  (2D OV models see far surfaces worse; SimLSeg's own rule is a = 2, s = 6 m);
* ``x agree(k)``: times ``exp(k (cos(f_n, m) - 1))``, the agreement of the view's OV feature with
  the weighted mean ``m`` (one pass of robust averaging);
* ``nearest K``: only the K nearest of those views;
* ``x colour(s)``: times ``exp(-(|c_n - m| / s)^2)``, the distance of the view's colour at the
  point to the weighted mean colour ``m``, re-weighted three times (photo-consistency: a view that
  sees an occluder sees its colour).

It tells which cues a blend could learn from (the range encoding, ``FusionConfig.range_encoding``,
feeds the distance), without training. Tune on validation scenes (``data/val``; about 4 minutes for
three):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/studies/view_weights.py data/val/apartment_s100[0-2]

Prints per-scene mIoU (%) and the share of the blend's weight on views that do not see the point
(ground truth), with the mean per row.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def point_normals(xyz: np.ndarray, k: int = 12) -> np.ndarray:
    """(P, 3) unit normals of a point cloud: the least principal axis of each point's k nearest
    points (the points themselves, no other geometry). Unoriented."""
    from scipy.spatial import cKDTree

    k = min(k, len(xyz))
    _, nn = cKDTree(xyz).query(xyz, k=k)
    local = xyz[nn] - xyz[nn].mean(axis=1, keepdims=True)  # (P, k, 3)
    _, vecs = np.linalg.eigh(np.einsum("pki,pkj->pij", local, local))
    return vecs[:, :, 0]  # eigh sorts ascending: the smallest variance's axis


def colour_reweighted(base: torch.Tensor, rgb: torch.Tensor, scale: float,
                      iterations: int = 3) -> torch.Tensor:
    """(P, k) ``base`` weights times ``exp(-(|c_n - m| / scale)^2)``, ``m`` the mean of the views'
    colours ``rgb`` (P, k, 3) under the current weights, ``iterations`` times from ``base``."""
    w = base
    for _ in range(iterations):
        mean = (w.unsqueeze(-1) * rgb).sum(1) / w.sum(1, keepdim=True).clamp_min(1e-12)
        w = base * torch.exp(-((rgb - mean.unsqueeze(1)).norm(dim=-1) / scale).square())
    return w


def weightings(learned: torch.Tensor, mask: torch.Tensor, dist: torch.Tensor, ov: torch.Tensor,
               incidence: torch.Tensor | None = None,
               rgb: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Per-view weights (P, k) of every row. learned / mask / dist: (P, k), views sorted by
    distance; ov: (P, k, D) the views' OV features (0 where masked); incidence (P, k): |cos| of the
    angle between each view's ray and the point's normal estimated from the points; rgb (P, k, 3):
    the views' colours at the point."""
    sel = mask.float()
    rows = {"learned": learned * sel, "uniform": sel}
    if rgb is not None:
        for scale in (0.1, 0.2):
            rows[f"learned x colour({scale:g})"] = colour_reweighted(learned * sel, rgb, scale)
            rows[f"uniform x colour({scale:g})"] = colour_reweighted(sel, rgb, scale)
    if incidence is not None:
        for beta in (0.7, 2.0):
            q = incidence.clamp_min(0.05) ** beta
            rows[f"learned x incidence^{beta:g}"] = learned * sel * q
            rows[f"uniform x incidence^{beta:g}"] = sel * q
    for a, s in ((2.0, 6.0), (1.0, 2.0), (0.0, 1.0)):
        q = torch.exp(-(dist - a).clamp_min(0) / s)
        rows[f"learned x dist({a:g}, {s:g})"] = learned * sel * q
        rows[f"uniform x dist({a:g}, {s:g})"] = sel * q
    unit = F.normalize(ov, dim=-1)
    for kappa in (2.0, 5.0, 10.0):
        for name, base in (("learned", learned * sel), ("uniform", sel)):
            m = F.normalize((base.unsqueeze(-1) * unit).sum(1), dim=-1)
            agree = (unit * m.unsqueeze(1)).sum(-1)
            rows[f"{name} x agree({kappa:g})"] = base * torch.exp(kappa * (agree - 1))
    rank = torch.arange(mask.shape[1]).expand_as(sel)
    for k in (8, 16):
        rows[f"learned, nearest {k}"] = learned * sel * (rank < k)
        rows[f"uniform, nearest {k}"] = sel * (rank < k)
    return rows


def main(argv: list[str] | None = None) -> int:
    from benchmarks.studies.ov_temperature import scene_table
    from mapper.model.checkpoint import load_model
    from mapper.model.fusion import blend
    from mapper.model.ops.geometry import camera_centers, sample_bilinear, scale_uv
    from mapper.ov.encoders import get_text_encoder
    from mapper.training import evaluate as ev
    from mapper.training.metrics import (
        NUM_SCANNET_CLASSES,
        confusion_matrix,
        predict_labels,
        segmentation_scores,
    )

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--checkpoint", default="checkpoints/cpu-small.json")
    parser.add_argument("--max-points", type=int, default=8000)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    if args.max_points < 1 or args.threads < 1:
        parser.error("--max-points and --threads must be >= 1")
    for s in args.scenes:
        if not s.is_dir():
            parser.error(f"no scene folder {s}")
    torch.set_num_threads(args.threads)
    try:
        model, _ = load_model(args.checkpoint, device="cpu")
    except (FileNotFoundError, ValueError) as exc:
        parser.error(str(exc))
    settings = ev.EvalSettings(max_points=args.max_points, do_2d=False)
    table: dict[str, list[float]] = {}
    shares: dict[str, list[float]] = {}
    for scene_dir in args.scenes:
        scene = ev.load_scene(scene_dir)
        emb = torch.from_numpy(get_text_encoder().encode(scene.class_names[:NUM_SCANNET_CLASSES]))
        sp = ev.scene_points(scene, settings)
        views, bounds = ev.scene_sources(model, scene)
        with torch.no_grad():
            volume = model.build_volume(views, bounds)
        for dgm in (False, True):
            pb = ev.blend_points(model, views, volume, bounds, sp.xyz, depth_guided_masking=dgm)
            uv, _, _ = ev.candidate_views(views, sp.xyz, depth_guided_masking=dgm)
            idx, sel = pb.view_index, pb.mask  # (P, k), nearest first
            centres = camera_centers(views.world_from_cam)  # (M, 3)
            dist = torch.cdist(sp.xyz, centres).gather(1, idx)
            rays = F.normalize(sp.xyz[:, None, :] - centres[idx], dim=-1)  # (P, k, 3)
            normal = torch.from_numpy(point_normals(sp.xyz.double().numpy())).to(rays)
            incidence = (rays * normal[:, None, :]).sum(-1).abs()
            o_wh = (views.ov.shape[-1], views.ov.shape[-2])
            ov = torch.zeros(*idx.shape, views.ov.shape[1])
            rgb = torch.zeros(*idx.shape, 3)
            for n in torch.unique(idx[sel]).tolist():
                r, s = torch.nonzero((idx == n) & sel, as_tuple=True)
                ov[r, s] = sample_bilinear(views.ov[n], scale_uv(uv[n, r], views.image_wh, o_wh))[0]
                rgb[r, s] = sample_bilinear(views.rgb[n], uv[n, r])[0]
            occluded = sp.occluded.gather(1, idx) & sel
            for name, w in weightings(pb.weights, sel, dist, ov, incidence, rgb).items():
                w = w / w.sum(1, keepdim=True).clamp_min(1e-12)
                pred = np.asarray(predict_labels(blend(w, ov), emb))
                miou = 100 * segmentation_scores(confusion_matrix(sp.gt, pred)).miou
                key = ("with DGM: " if dgm else "no depth: ") + name
                table.setdefault(key, []).append(miou)
                shares.setdefault(key, []).append(100 * float((w * occluded).sum(1)[sel.any(1)].mean()))
        print(f"{scene.name} done", file=sys.stderr, flush=True)
    names = [p.name for p in args.scenes]
    print("3D mIoU (%)\n" + scene_table(names, table))
    print("\nweight on occluded views (%, ground-truth visibility)\n" + scene_table(names, shares))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
