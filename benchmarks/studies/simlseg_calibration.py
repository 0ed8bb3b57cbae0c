"""Calibrate SimLSeg (the SIMULATED 2D open-vocabulary model) against the ground truth.

Renders held-out scenes of both styles along robot trajectories, runs SimLSeg on every view and
scores its single-view 2D segmentation: features upsampled to the image (nearest or bilinear),
argmax cosine over the 20 ScanNet class-name embeddings, compared with the ground-truth label
image (other labels ignored). Confusion matrices are accumulated per scene; mIoU is over the
classes present in the scene, averaged over scenes (``mapper.training.metrics``). A near / far split by
distance along the ray shows how quality falls with distance.

Target (docs/concepts/simlseg.md): single-view mIoU 45-60% on both styles (LSeg on ScanNet: 55.9).

Usage:
    HF_HUB_OFFLINE=1 .venv/bin/python benchmarks/studies/simlseg_calibration.py [--scenes 3] [--frames 24]
        [--set noise_std=0.03 --set near_m=2.0] [--upsample bilinear]

This is a benchmark script (it imports both sides: the simulated client and the mapper's
metrics), not part of either package.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.sim.raycast import SceneRenderer  # noqa: E402
from clients.sim.robot import default_intrinsics, robot_trajectory  # noqa: E402
from clients.sim.scenes import CLASS_NAMES, SCANNET20, generate_scene  # noqa: E402
from clients.sim.simlseg import SimLSeg, SimLSegConfig  # noqa: E402
from clients.sim.text import get_text_encoder  # noqa: E402
from mapper.training.metrics import (  # noqa: E402
    average_over_scenes,
    confusion_matrix,
    format_scores_table,
    segmentation_scores,
)

STYLES = ("apartment", "studio")
HELD_OUT_SEED0 = 9000
"""Calibration scenes use seeds 9000.. (training data should use other seeds)."""


def parse_overrides(items: list[str]) -> dict[str, object]:
    """``["noise_std=0.03", "confusion_mix=0.5,1.0"]`` -> typed SimLSegConfig overrides."""
    fields = {f.name: f for f in dataclasses.fields(SimLSegConfig)}
    out: dict[str, object] = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in fields:
            raise SystemExit(f"unknown SimLSegConfig field {key!r}; fields: {sorted(fields)}")
        default = getattr(SimLSegConfig(), key)
        if isinstance(default, tuple):
            out[key] = tuple(float(v) for v in value.split(","))
        else:
            out[key] = type(default)(value)
    return out


def upsample_predict(ov: np.ndarray, class_emb: torch.Tensor, height: int, width: int,
                     mode: str) -> np.ndarray:
    """(h, w, D) features -> (H, W) argmax-cosine labels over ``class_emb`` (C, D) (unit rows)."""
    if mode == "nearest":
        logits = torch.from_numpy(ov.astype(np.float32)) @ class_emb.T  # (h, w, C)
        labels = logits.argmax(-1)
        rows = (torch.arange(height) * ov.shape[0]) // height
        cols = (torch.arange(width) * ov.shape[1]) // width
        return labels[rows][:, cols].numpy()
    t = torch.from_numpy(ov.astype(np.float32)).permute(2, 0, 1)[None]
    up = F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False)[0]  # (D, H, W)
    return torch.einsum("dhw,cd->hwc", up, class_emb).argmax(-1).numpy()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=3, help="held-out scenes per style")
    ap.add_argument("--frames", type=int, default=30, help="views per scene along a robot trajectory")
    ap.add_argument("--every", type=int, default=4,
                    help="keep every k-th pose of a (frames * every)-pose trajectory (views spread out)")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--near-far-m", type=float, default=2.5, help="near/far split, distance along the ray")
    ap.add_argument("--upsample", choices=("nearest", "bilinear"), default="bilinear")
    ap.add_argument("--seed", type=int, default=0, help="SimLSeg seed (combined with the scene seed)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a SimLSegConfig field (repeatable)")
    ap.add_argument("--per-class", action="store_true", help="print per-class IoU columns")
    args = ap.parse_args(argv)

    config = SimLSegConfig(**parse_overrides(args.set))
    encoder = get_text_encoder()
    n_cls = len(SCANNET20)
    class_emb = torch.from_numpy(encoder.encode([config.prompt_template.format(n) for n in SCANNET20]))
    K = np.asarray(default_intrinsics(args.width, args.height), dtype=np.float64)

    t0 = time.time()
    rows = []
    for style in STYLES:
        per_scene, near_scenes, far_scenes = [], [], []
        for i in range(args.scenes):
            seed = HELD_OUT_SEED0 + i
            scene = generate_scene(seed, style)
            renderer = SceneRenderer(scene)
            sim = SimLSeg(CLASS_NAMES, encoder, seed=args.seed * 1_000_003 + seed, config=config)
            poses = robot_trajectory(scene, args.frames * args.every, seed)[:: args.every]
            cm = np.zeros((n_cls, n_cls), np.int64)
            cm_near, cm_far = cm.copy(), cm.copy()
            for f, world_from_cam in enumerate(poses):
                view = renderer.render(K, world_from_cam, args.width, args.height)
                ov = sim.features(view, f, K=K)
                pred = upsample_predict(ov, class_emb, args.height, args.width, args.upsample)
                gt = view.label
                near = view.ray_dist_m < args.near_far_m
                cm += confusion_matrix(gt.ravel(), pred.ravel(), n_cls)
                cm_near += confusion_matrix(gt[near], pred[near], n_cls)
                cm_far += confusion_matrix(gt[~near], pred[~near], n_cls)
            per_scene.append(segmentation_scores(cm))
            near_scenes.append(segmentation_scores(cm_near))
            far_scenes.append(segmentation_scores(cm_far))
        rows.append((f"{style}", average_over_scenes(per_scene)))
        rows.append((f"{style} near (<{args.near_far_m:g} m)", average_over_scenes(near_scenes)))
        rows.append((f"{style} far (>={args.near_far_m:g} m)", average_over_scenes(far_scenes)))

    print(f"SimLSeg single-view 2D segmentation, {args.scenes} held-out scenes x {args.frames} views "
          f"(every {args.every}th robot pose) per style, {args.width}x{args.height}, {args.upsample} "
          f"upsampling, seeds {HELD_OUT_SEED0}.."
          f"{HELD_OUT_SEED0 + args.scenes - 1}")
    overrides = {k: v for k, v in dataclasses.asdict(config).items() if v != getattr(SimLSegConfig(), k)}
    print(f"config overrides: {overrides or 'none (defaults)'}")
    print()
    print(format_scores_table(rows, SCANNET20, per_class=args.per_class))
    print(f"\n({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
