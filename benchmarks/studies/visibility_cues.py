"""Can the model's own geometry tell which source views see a point?

Evidence for docs/how-to/train.md. Two parts, both without input depth (bounds over the frames'
depth points, as the "no depth" rows of docs/how-to/evaluate.md):

``ray``: for each evaluation point and each stream frame it projects into, features of the
segment from the point towards that camera: the volume feature and log(1 + density) at
0.1 ... 3 m from the point (each with a flag: the segment is that long), the point's own volume
feature, the log distance and the log number of such frames. A small MLP (2 x 32, Adam, 3000
steps of 4096 pairs) fitted to the true visibility on the ``--train`` scenes is scored on the
``--test`` scenes: ROC AUC, against the same MLP fitted on the learned blending weight alone (and
with the weight as an input too, and without the segment: the point alone; ties in the scores are
not averaged: the scores are continuous), and the 3D mIoU and occluded-weight share when
the learned OV weights are multiplied by its p(visible) (the MLP without the learned weight).

``depth``: each stream frame's depth rendered at 1/4 of its size from a volume over its 8
best-overlapping frames (the training regime, sharp: ``benchmarks/studies/volume_views.py``); the share
of truly visible / occluded (point, frame) pairs it would mask (point behind 1.25 x the rendered
depth), and the 3D mIoU with Depth Guided Masking on these depths against DGM on the true depth.

Usage:
    python benchmarks/studies/visibility_cues.py --part ray --train data/train data/val --test data/eval
    python benchmarks/studies/visibility_cues.py --part depth --test data/val
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapper.model.checkpoint import load_model
from mapper.model.field import GovNeSF, render_depth_maps
from mapper.model.ops.cost_volume import VolumeBounds, sample_volume
from mapper.model.ops.geometry import camera_centers, invert_pose, project_points
from mapper.training import evaluate as ev
from mapper.training.data import select_sources
from mapper.training.metrics import NUM_SCANNET_CLASSES, predict_labels, scores_from_labels

BACK_M = (0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
"""Distances (m) from the point towards the camera where the segment is sampled."""
STOP_M = 0.1
"""A sample counts only when it lies at least this far in front of the camera."""


def segment_features(model: GovNeSF, volume: Tensor, bounds: VolumeBounds, points: Tensor,
                     centres: Tensor) -> Tensor:
    """points (P, 3), centres (P, k, 3) camera of each pair -> (P, k, J Dv + 2 J + 1) features:
    [v at the J samples (J Dv), log(1 + sigma) (J), flags (J), log distance (1)]."""
    seg = centres - points[:, None, :]
    r = seg.norm(dim=-1).clamp_min(1e-6)  # (P, k)
    u = seg / r[..., None]
    s = points.new_tensor(BACK_M)
    q = points[:, None, None, :] + u[:, :, None, :] * s[None, None, :, None]  # (P, k, J, 3)
    ok = (s[None, None, :] < (r[..., None] - STOP_M)).to(points.dtype)
    v, inside = sample_volume(volume, bounds, q.reshape(-1, 3))
    sigma = model.density(v) * inside.to(v.dtype)
    P, k = r.shape
    J = s.numel()
    v = v.reshape(P, k, J, -1) * ok[..., None]
    return torch.cat([v.reshape(P, k, -1), torch.log1p(sigma.reshape(P, k, J)) * ok, ok,
                      torch.log(r)[..., None]], dim=-1)


class Pairs:
    """(point, frame) pairs of one scene with their features and truth."""

    def __init__(self, model: GovNeSF, scene: ev.EvalScene, max_points: int) -> None:
        sp = ev.scene_points(scene, ev.EvalSettings(max_points=max_points))
        views, bounds = ev.scene_sources(model, scene)
        self.views = dataclasses.replace(views, depth_m=None)
        with torch.no_grad():
            self.volume = model.build_volume(self.views, bounds)
            self.base = ev.blend_points(model, self.views, self.volume, bounds, sp.xyz)
            self.centres = camera_centers(views.world_from_cam)
            seg = torch.cat([segment_features(model, self.volume, bounds, sp.xyz[i:i + 1024],
                                              self.centres[self.base.view_index[i:i + 1024]])
                             for i in range(0, len(sp.xyz), 1024)])
            vpt, _ = sample_volume(self.volume, bounds, sp.xyz)
        mask = self.base.mask
        k = mask.sum(1, keepdim=True).clamp_min(1).float()
        self.features = torch.cat([seg, vpt[:, None, :].expand(-1, seg.shape[1], -1),
                                   torch.log(self.base.weights * k).clamp_min(-14)[..., None],
                                   torch.log(k)[..., None].expand(-1, seg.shape[1], 1)], dim=-1)
        self.visible = (sp.visible.gather(1, self.base.view_index) & mask).float()
        self.mask, self.sp, self.bounds, self.scene = mask, sp, bounds, scene
        J, dv = len(BACK_M), vpt.shape[1]
        n_seg = J * dv + 2 * J + 1
        self.columns = {
            "learned weight": [n_seg + dv],
            "point: v, distance, weight, views": [n_seg - 1, *range(n_seg, n_seg + dv + 2)],
            "segment + point": list(range(n_seg + dv + 2)),
            "segment + point, no weight": [*range(n_seg + dv), n_seg + dv + 1],
        }


def fit(x: Tensor, y: Tensor, seed: int = 0, steps: int = 3000) -> tuple[nn.Module, Tensor, Tensor]:
    torch.manual_seed(seed)
    mu, sd = x.mean(0), x.std(0).clamp_min(1e-4)
    net = nn.Sequential(nn.Linear(x.shape[1], 32), nn.ELU(), nn.Linear(32, 32), nn.ELU(), nn.Linear(32, 1))
    opt = torch.optim.Adam(net.parameters(), 3e-3)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        i = torch.randint(0, len(y), (4096,), generator=g)
        loss = F.binary_cross_entropy_with_logits(net((x[i] - mu) / sd).squeeze(-1), y[i])
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net, mu, sd


def auc(score: Tensor, y: Tensor) -> float:
    ranks = torch.empty_like(score, dtype=torch.float64)
    ranks[torch.argsort(score)] = torch.arange(1, len(score) + 1, dtype=torch.float64)
    pos = float(y.sum())
    return float((ranks[y > 0].sum() - pos * (pos + 1) / 2) / (pos * (len(y) - pos)))


def miou(feats: Tensor, gt: np.ndarray, text: Tensor) -> float:
    return 100.0 * scores_from_labels(gt, np.asarray(predict_labels(feats.float(), text))).miou


def part_ray(model: GovNeSF, train: list[Path], test: list[Path], max_points: int, text_fn) -> None:
    t0 = time.perf_counter()
    train_pairs = [Pairs(model, ev.load_scene(d), max_points) for d in train]
    names = list(train_pairs[0].columns)
    xs = torch.cat([p.features[p.mask] for p in train_pairs])
    ys = torch.cat([p.visible[p.mask] for p in train_pairs])
    cols = train_pairs[0].columns
    nets = {n: fit(xs[:, cols[n]], ys) for n in names}
    del train_pairs, xs, ys
    print(f"{len(train)} training scenes, fitted in {time.perf_counter() - t0:.0f} s")
    print("| scene | " + " | ".join(f"AUC {n}" for n in names)
          + " | mIoU / occluded weight: learned | x p(visible) |")
    print("|---|" + "---|" * (len(names) + 2))
    for d in test:
        scene = ev.load_scene(d)
        p = Pairs(model, scene, max_points)
        y = p.visible[p.mask]
        cells = []
        for n in names:
            net, mu, sd = nets[n]
            with torch.no_grad():
                cells.append(f"{auc(net((p.features[p.mask][:, cols[n]] - mu) / sd).squeeze(-1), y):.3f}")
        net, mu, sd = nets["segment + point, no weight"]
        c = cols["segment + point, no weight"]

        def p_visible(points: Tensor, idx: Tensor, sel: Tensor, p: Pairs = p, net: nn.Module = net,
                      mu: Tensor = mu, sd: Tensor = sd, c: list[int] = c) -> Tensor:
            with torch.no_grad():
                seg = segment_features(model, p.volume, p.bounds, points, p.centres[idx])
                vpt, _ = sample_volume(p.volume, p.bounds, points)
                k = sel.sum(1, keepdim=True).clamp_min(1).float()
                n = seg.shape[1]
                x = torch.cat([seg, vpt[:, None, :].expand(-1, n, -1), torch.zeros_like(seg[..., :1]),
                               torch.log(k)[..., None].expand(-1, n, 1)], dim=-1)
                return torch.sigmoid(net((x[..., c] - mu) / sd).squeeze(-1))

        text = text_fn(scene)
        with torch.no_grad():
            weighted = ev.blend_points(model, p.views, p.volume, p.bounds, p.sp.xyz, view_weight_fn=p_visible)
        print(f"| {scene.name} | " + " | ".join(cells)
              + f" | {miou(p.base.ov, p.sp.gt, text):.1f} / "
              + f"{100 * ev.occluded_share(p.base, p.sp.occluded):.1f}%"
              + f" | {miou(weighted.ov, p.sp.gt, text):.1f} / "
              + f"{100 * ev.occluded_share(weighted, p.sp.occluded):.1f}% |", flush=True)


def part_depth(model: GovNeSF, test: list[Path], max_points: int, text_fn, n_views: int = 8) -> None:
    print("| scene | rendered depth median rel | visible / occluded pairs masked | mIoU no depth | "
          "+ DGM on the 8-view rendered depth | + DGM on the true depth |")
    print("|---|---|---|---|---|---|")
    for d in test:
        scene = ev.load_scene(d)
        sp = ev.scene_points(scene, ev.EvalSettings(max_points=max_points))
        views, bounds = ev.scene_sources(model, scene)
        blind = dataclasses.replace(views, depth_m=None)
        w, h = scene.image_wh
        rw, rh = w // 4, h // 4
        K = sp.K * sp.K.new_tensor([rw / w, rh / h, rw / w, rh / h])
        depth = torch.zeros(len(scene), rh, rw)
        with torch.no_grad():
            volume = model.build_volume(blind, bounds)
            for i in range(len(scene)):
                src = select_sources(scene.data, scene.K[i], scene.world_from_cam[i], n_views)
                lv, lb = ev.scene_sources(model, scene, src)
                lvol = model.build_volume(dataclasses.replace(lv, depth_m=None), lb)
                depth[i : i + 1], _ = render_depth_maps(
                    model, lvol, lb, K[i : i + 1], sp.world_from_cam[i : i + 1], rw, rh, min_opacity=0.0
                )
        truth = F.interpolate(torch.from_numpy(scene.gt_depth_m)[:, None], size=(rh, rw),
                              mode="nearest")[:, 0]
        rel = float(((depth - truth).abs() / truth.clamp_min(1e-6))[truth > 0].median())
        n = len(scene)
        uv, z = project_points(sp.xyz[None].expand(n, -1, -1), K, invert_pose(sp.world_from_cam))
        u = uv[..., 0].floor().long().clamp(0, rw - 1)
        v = uv[..., 1].floor().long().clamp(0, rh - 1)
        behind = (z > 1.25 * depth[torch.arange(n)[:, None], v, u]).T  # (P, N)
        text = text_fn(scene)
        with torch.no_grad():
            none = ev.blend_points(model, blind, volume, bounds, sp.xyz)
            with_rendered = dataclasses.replace(blind, depth_m=depth)
            rendered = ev.blend_points(model, with_rendered, volume, bounds, sp.xyz,
                                       depth_guided_masking=True)
            true = ev.blend_points(model, views, volume, bounds, sp.xyz, depth_guided_masking=True)
        print(f"| {scene.name} | {rel:.3f} | {float(behind[sp.visible].float().mean()):.3f} / "
              f"{float(behind[sp.occluded].float().mean()):.3f} | {miou(none.ov, sp.gt, text):.1f} | "
              f"{miou(rendered.ov, sp.gt, text):.1f} | {miou(true.ov, sp.gt, text):.1f} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--part", choices=("ray", "depth"), required=True)
    p.add_argument("--checkpoint", type=Path, default=Path("checkpoints/cpu-small.json"))
    p.add_argument("--train", nargs="*", type=Path, default=[], help="scenes the ray part's MLP is fitted on")
    p.add_argument("--test", nargs="+", type=Path, required=True)
    p.add_argument("--max-points", type=int, default=6000)
    args = p.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from mapper.ov.encoders import get_text_encoder

    try:
        if args.part == "ray" and not args.train:
            raise ValueError("--part ray needs --train scenes")
        if args.max_points < 100:
            raise ValueError(f"--max-points {args.max_points} out of range: >= 100")
        model, meta = load_model(args.checkpoint)
        train = ev.find_scene_dirs(args.train) if args.train else []
        test = ev.find_scene_dirs(args.test)
    except (FileNotFoundError, ValueError) as exc:
        print(f"{Path(__file__).name}: {exc}", file=sys.stderr)
        return 2
    encoder = get_text_encoder()

    def text_fn(scene: ev.EvalScene) -> Tensor:
        return torch.from_numpy(encoder.encode(scene.class_names[:NUM_SCANNET_CLASSES]))

    print(f"checkpoint {args.checkpoint} (step {meta.get('step')}), {args.max_points} points a scene")
    if args.part == "ray":
        part_ray(model, train, test, args.max_points, text_fn)
    else:
        part_depth(model, test, args.max_points, text_fn)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
