"""Depth priors for Depth Guided Masking on an RGB-only stream: which geometry helps `govnesf` + DGM.

Streams a simulated room WITHOUT depth into an in-process node (the learned model's handlers and
the triangulation / plane-sweep plugin, as the node runs them), then scores ``segment_points``
``govnesf`` with ``use_depth`` (DGM on the keyframes' depth priors) at the ground-truth surface
samples the stream saw (3D mIoU, class names as texts), once per prior:

* ``own``: each keyframe's own prior (its kept plane-sweep depths, filled along the image, else
  its splatted triangulated points; the node here runs with ``stereo.prior_geometry = false``);
* ``+ map``: that prior, and where it has none the global map's surface at the keyframe's pose
  (:func:`mapper.node.queries.map_surface_depth`);
* ``+ geometry``: ... the splat of every keyframe's triangulated and swept points
  (``MapperNode.surface_points``, half a map voxel each, as ``render`` uses them), at the end of
  the stream (what ``stereo.prior_geometry``, on by default, does as the stream goes);
* ``+ planes``: ... the planes of that geometry (:func:`mapper.node.queries.geometry_planes`).

Also prints ``govnesf`` without DGM, and each prior's share of the keyframes' pixels.

    OMP_NUM_THREADS=1 python benchmarks/studies/dgm_priors.py --seed 3 --style apartment
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from clients.harness import mean_iou, sim_stream  # noqa: E402
from clients.sim.export import count_views  # noqa: E402
from clients.sim.scenes import CLASS_NAMES, LABEL_OF  # noqa: E402
from mapper.geometry.planes import plane_depth  # noqa: E402
from mapper.node.config import config_from_dict  # noqa: E402
from mapper.node.queries import geometry_planes, map_surface_depth, surface_depth  # noqa: E402
from mapper.node.serve import install_serve_stages  # noqa: E402
from mapper.node.service import MapperNode  # noqa: E402
from mapper.node.workers.triangulation import keyframe_key  # noqa: E402
from protocol import decode, encode  # noqa: E402
from protocol.messages import Segmentation, SegmentPoints  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--style", default="apartment")
    p.add_argument("--frames", type=int, default=240)
    p.add_argument("--window", type=int, default=160)
    p.add_argument("--checkpoint", type=Path, default=ROOT / "checkpoints" / "cpu-small.json")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    if min(args.frames, args.window, args.threads) < 1:
        p.error("--frames, --window and --threads must be >= 1")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    torch.set_num_threads(args.threads)
    try:
        stream = sim_stream(args.seed, args.frames, 160, 120, depth=False, style=args.style)
    except ValueError as exc:  # e.g. an unknown --style
        p.error(str(exc))
    config = config_from_dict({
        "map_dir": "/tmp/govnesf-bench-maps", "autosave_name": "", "save_on_exit": False,
        "window": {"max_keyframes": args.window},
        "model": {"checkpoint": str(args.checkpoint), "device": "cpu"},
        "stereo": {"prior_geometry": False},  # the keyframes' own priors; the candidates below
    })  # fmt: skip
    node = MapperNode(config)
    plugins = install_serve_stages(node)  # as `govnesf serve` builds it
    runtime, rendered, tri = plugins.runtime, plugins.rendered_depth, plugins.triangulation
    if runtime is None or not runtime.ready:
        raise SystemExit(runtime.load_error if runtime is not None else "serve_model is off")
    assert tri is not None and rendered is not None
    gt_xyz, gt_label, _ = stream.scene.sample_surface(250_000, seed=args.seed,
                                                      exclude_labels=(LABEL_OF["ceiling"],))
    gt_views = np.zeros(len(gt_xyz), np.int32)
    try:
        for k, (frame, view) in enumerate(stream.frames()):
            count_views(gt_xyz, stream.K, stream.poses[k], view.depth_m, gt_views)
            node.handle_ingest(encode(frame))
            if (k + 1) % 10 == 0:  # the workers, between frames
                tri.process_pending()
                rendered.process_pending()
        tri.process_pending()
        rendered.process_pending()
        seen = gt_views > 0
        pts, gt = gt_xyz[seen].astype(np.float32), gt_label[seen].astype(np.int64)

        def miou(dgm: bool) -> float:
            msg = SegmentPoints(xyz=pts, texts=list(CLASS_NAMES), method="govnesf", use_depth=dgm)
            reply = decode(node.handle_query(encode(msg)), direction="reply")
            assert isinstance(reply, Segmentation), reply
            return round(100 * mean_iou(reply.label.astype(np.int64), gt, len(CLASS_NAMES))[0], 2)

        print(f"seed {args.seed} {args.style}: govnesf without DGM {miou(False)}", flush=True)
        with node.state.lock:
            keyframes = list(node.state.window.keyframes)
        own: dict[Any, np.ndarray] = {}
        for kf in keyframes:
            prior = runtime._volume.depth_priors.get(keyframe_key(kf))  # what the plugin set
            own[keyframe_key(kf)] = (np.zeros((kf.height, kf.width), np.float32) if prior is None
                                         else prior.cpu().numpy())
        providers = node.ctx.surface_points
        geometry = np.concatenate([np.asarray(f(), np.float64).reshape(-1, 3) for f in providers])
        snap = node.state.global_map.snapshot()
        planes = geometry_planes(geometry, config.model)
        footprint = config.model.surface_geometry_footprint * config.global_map.voxel_size_m

        def extra(name: str, kf: Any) -> np.ndarray:
            K, pose = np.asarray(kf.K, np.float64), np.asarray(kf.world_from_cam, np.float64)
            if name == "+ map":
                return map_surface_depth(snap, K, pose, kf.width, kf.height, config.model)
            if name == "+ geometry":
                return surface_depth(geometry, footprint, K, pose, kf.width, kf.height, config.model)
            if name == "+ planes":
                return plane_depth(planes, K, pose, kf.width, kf.height)[0]
            return np.zeros((kf.height, kf.width), np.float32)

        for name in ("own", "+ map", "+ geometry", "+ planes"):
            before, after = [], []
            for kf in keyframes:
                prior = own[keyframe_key(kf)]
                z = extra(name, kf)
                if z.shape != prior.shape:
                    z = cv2.resize(z, (prior.shape[1], prior.shape[0]), interpolation=cv2.INTER_NEAREST)
                new = np.where(prior > 0, prior, z).astype(np.float32)
                before.append(float((prior > 0).mean()))
                after.append(float((new > 0).mean()))
                runtime.set_view_depth_prior(keyframe_key(kf), new)
            print(f"  prior {name:<10}: pixels with a prior {np.mean(before):.3f} -> {np.mean(after):.3f}, "
                  f"govnesf + DGM {miou(True)}", flush=True)
    finally:
        node.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
