"""How sharp is the model's density as a function of how many views build its cost volume?

For every ``--every``-th stream frame of each scene, the model's depth at that frame's own pose is
rendered (``mapper.model.field.render_depth_maps``, at 1/4 of the frame's size, no opacity
cut) from a cost volume over the frame's N best-overlapping stream frames (itself first: the
training's ``select_sources``), for each N of ``--views``, and compared with the frame's true
depth (median relative error over the pixels with depth; then the median over frames).

Bounds (``--bounds``):

* ``own``: over the N frames' depth points (what training and the evaluation build);
* ``fixed``: over the depth points of the frame's 8 best sources, for every N (the same box and
  voxels, only the views change);
* ``frusta``: over the N frames' frusta up to 4 m (no depth anywhere).

No input depth reaches the network in any case; bounds ``own`` and ``fixed`` use the frames'
depth points for the box only, as the "no depth" rows of docs/how-to/evaluate.md do.

A scene without ground truth (a real RGB-D recording, ``scripts/make_real_data.sh``: no ``gt/``
folder) is read with the training loader at the model's working size, its own depth as the truth.

Usage: python benchmarks/studies/volume_views.py data/val/apartment_s1000 [--views 8,16,30,80] [--every 10]
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

from mapper.model.checkpoint import load_model
from mapper.model.config import ModelConfig
from mapper.model.field import render_depth_maps
from mapper.training import evaluate as ev
from mapper.training.data import Scene, load_scene, select_sources

FRUSTUM_RANGE_M = 4.0
FIXED_VIEWS = 8


@dataclasses.dataclass
class DepthScene:
    """What this benchmark reads of a scene: the training loader's ``data`` and the true depth."""

    data: Scene
    gt_depth_m: np.ndarray  # (F, H, W)
    name: str

    @property
    def image_wh(self) -> tuple[int, int]:
        return self.data.image_wh

    @property
    def K(self) -> np.ndarray:  # noqa: N802 (the intrinsics' usual name)
        return self.data.K

    @property
    def world_from_cam(self) -> np.ndarray:
        return self.data.world_from_cam

    def __len__(self) -> int:
        return self.data.num_frames


def read_scene(path: Path, model_cfg: ModelConfig) -> DepthScene:
    """An evaluation scene (``gt/``), or a real recording without ground truth (its own depth)."""
    if (path / "gt").is_dir():
        scene = ev.load_scene(path)
        return DepthScene(scene.data, scene.gt_depth_m, scene.name)
    w, h = model_cfg.image_wh
    ov_shape = (h // 4, w // 4, model_cfg.fusion.ov_dim)  # no OV maps: zeros (not read here)
    data = load_scene(path, require_ov=False, image_wh=(w, h), ov_shape=ov_shape)
    return DepthScene(data, data.depth_m, data.name)


def frame_depth_error(model: torch.nn.Module, scene: DepthScene, frame: int, n_views: int, bounds_mode: str,
                      stride: int = 4) -> float:
    """Median relative depth error of ``frame`` rendered from a volume over ``n_views`` sources."""
    w, h = scene.image_wh
    rw, rh = max(1, w // stride), max(1, h // stride)
    K = torch.from_numpy(scene.K[frame : frame + 1]).float()
    pose = torch.from_numpy(scene.world_from_cam[frame : frame + 1]).float()
    scale = K.new_tensor([rw / w, rh / h, rw / w, rh / h])

    def sources(n: int) -> np.ndarray:
        return select_sources(scene.data, scene.K[frame], scene.world_from_cam[frame], n)

    frustum = FRUSTUM_RANGE_M if bounds_mode == "frusta" else None
    views, bounds = ev.scene_sources(model, scene, sources(n_views), frustum_range_m=frustum)
    if bounds_mode == "fixed":
        _, bounds = ev.scene_sources(model, scene, sources(FIXED_VIEWS))
    views = dataclasses.replace(views, depth_m=None)
    with torch.no_grad():
        volume = model.build_volume(views, bounds)
        depth, _ = render_depth_maps(model, volume, bounds, K * scale, pose, rw, rh, min_opacity=0.0)
    truth = F.interpolate(torch.from_numpy(scene.gt_depth_m[frame : frame + 1])[:, None], size=(rh, rw),
                          mode="nearest")[:, 0]
    valid = truth > 0
    return float(((depth - truth).abs() / truth.clamp_min(1e-6))[valid].median())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", nargs="+", type=Path, help="recorded scenes (govnesf sim record --depth)")
    p.add_argument("--checkpoint", type=Path, default=Path("checkpoints/cpu-small.json"))
    p.add_argument("--views", default="8,16,30,80", help="comma-separated numbers of views per volume")
    p.add_argument("--bounds", default="own,fixed,frusta", help="comma-separated: own, fixed, frusta")
    p.add_argument("--every", type=int, default=10, help="every k-th stream frame is rendered")
    args = p.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        views = [int(v) for v in args.views.split(",")]
        modes = args.bounds.split(",")
        if any(v < 1 for v in views) or args.every < 1 or not set(modes) <= {"own", "fixed", "frusta"}:
            raise ValueError(f"--views {args.views} (each >= 1), --bounds {args.bounds} "
                             f"(own, fixed, frusta), --every {args.every} (>= 1)")
        model, meta = load_model(args.checkpoint)
        scenes = ev.find_scene_dirs(args.scenes)
    except (FileNotFoundError, ValueError) as exc:
        print(f"{Path(__file__).name}: {exc}", file=sys.stderr)
        return 2
    print(f"checkpoint {args.checkpoint} (step {meta.get('step')}); depth median relative error at the "
          f"frames' own poses, median over every {args.every}th frame")
    print("| scene | bounds | " + " | ".join(f"{v} views" for v in views) + " | s |")
    print("|---|---|" + "---|" * len(views) + "---|")
    for d in scenes:
        scene = read_scene(d, model.cfg)
        for mode in modes:
            t0 = time.perf_counter()
            cells = []
            for n in views:
                errs = [frame_depth_error(model, scene, f, n, mode) for f in range(0, len(scene), args.every)]
                cells.append(f"{np.median(errs):.3f}")
            print(f"| {scene.name} | {mode} | " + " | ".join(cells) + f" | {time.perf_counter() - t0:.0f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
