"""Global-map points from rendered depth: how accurate, how fast, and can an RGB-only robot find the chair?

Streams a simulated room (the demo's scene by default) into an in-process node that serves the
learned model, once WITH input depth and once WITHOUT (RGB + SimLSeg features only; the map's points
then come from :mod:`mapper.node.workers.depth_points`), and reports for each:

* global-map points and the time the rendered-depth worker spent per keyframe;
* geometric error of the map points: distance to the nearest ground-truth surface point
  (the simulator's depth of the same frames back-projected), median / p90, and the share within
  10 cm and 25 cm;
* "find the chair": the top object's distance to the nearest real chair;
* without depth, with the multi-view consistency filter of rendered-depth points
  (``global_map.rendered_consistency``) on and/or off (``--consistency``): the pixels checked and
  rejected. The node's triangulation plugin runs as ``govnesf serve`` installs it (its points are
  in the map and feed the consistency check).

Usage::

    python benchmarks/studies/rendered_depth_points.py [--frames 240] [--seed 3] \
        [--checkpoint checkpoints/cpu-small.json] [--consistency on,off] [--no-depth-row]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
import torch
from scipy.spatial import cKDTree

from clients.harness import chair_distance, sim_stream
from mapper.node.backends.learned import install_learned_backend
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from mapper.node.workers.triangulation import install_triangulation
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from protocol.messages import Points, QueryPoints, decode, encode


def backproject(depth: np.ndarray, K: np.ndarray, pose: np.ndarray, stride: int = 4) -> np.ndarray:
    """(M, 3) world points of every ``stride``-th pixel of a z-depth image (0 = none)."""
    h, w = depth.shape
    j, i = np.mgrid[stride // 2 : h : stride, stride // 2 : w : stride]
    z = depth[j, i]
    ok = np.isfinite(z) & (z > 0)
    cam = np.stack([(i[ok] + 0.5 - K[2]) / K[0] * z[ok], (j[ok] + 0.5 - K[3]) / K[1] * z[ok], z[ok]], 1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def run(args: argparse.Namespace, with_depth: bool, consistency: bool = True) -> dict[str, Any]:
    stream = sim_stream(args.seed, args.frames, depth=with_depth)
    overrides: dict[str, Any] = {
        "map_dir": "/tmp/govnesf-bench-maps", "autosave_name": "", "save_on_exit": False,
        "global_map": {"rendered_consistency": consistency},
    }
    for item in args.set:  # SECTION.KEY=VALUE (TOML value), e.g. global_map.rendered_consistency_voxels=1.0
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        if not (section and name and value):
            raise SystemExit(f"--set {item!r}: expected SECTION.KEY=VALUE")
        overrides.setdefault(section, {})[name] = tomllib.loads(f"v = {value}")["v"]
    config = config_from_dict(overrides)
    node = MapperNode(config)
    runtime = ModelRuntime(ModelRuntimeConfig(checkpoint=str(args.checkpoint), device="cpu"))
    if not runtime.ready:
        raise SystemExit(runtime.load_error)
    points = install_learned_backend(node, runtime)
    assert points is not None
    tri = install_triangulation(node, runtime)  # as `govnesf serve` does (None when disabled)
    gt_parts = []
    worker_s = 0.0
    started = time.perf_counter()
    for k, (frame, view) in enumerate(stream.frames()):
        node.handle_ingest(encode(frame))
        gt_parts.append(backproject(view.depth_m, stream.K, stream.poses[k]))
        if (k + 1) % args.process_every == 0:  # the worker's batching, run inline for a clean timing
            if tri is not None:
                tri.process_pending()
            t0 = time.perf_counter()
            points.process_pending()
            worker_s += time.perf_counter() - t0
    if tri is not None:
        tri.process_pending()
    t0 = time.perf_counter()
    points.process_pending()
    worker_s += time.perf_counter() - t0
    total_s = time.perf_counter() - started
    snap = node.state.global_map.snapshot()
    dist, _ = cKDTree(np.concatenate(gt_parts)).query(snap.xyz.astype(np.float64))
    reply = decode(node.handle_query(encode(QueryPoints(texts=["find the chair"], objects=True))),
                   direction="reply")
    chair = float("nan")
    if isinstance(reply, Points) and reply.objects:
        chair = chair_distance(reply.objects[0].centroid, stream.scene)
    stats = points.stats()
    node.stop()
    return {
        "input depth": "yes" if with_depth else "no (rendered)",
        "consistency": "-" if with_depth else ("on" if consistency else "off"),
        "rendered px checked": stats["consistency"]["checked"],
        "rendered px rejected": stats["consistency"]["rejected"],
        "triangulated points": 0 if tri is None else tri.stats()["global_map_points"],
        "keyframes": len(node.state.window) + node.state.keyframes_evicted,
        "rendered keyframes": stats["integrated"],
        "map points": len(snap),
        "worker ms / keyframe": 1e3 * worker_s / max(stats["integrated"], 1) if stats["integrated"] else 0.0,
        "median err (m)": float(np.median(dist)),
        "p90 err (m)": float(np.percentile(dist, 90)),
        "within 10 cm": float((dist < 0.10).mean()),
        "within 25 cm": float((dist < 0.25).mean()),
        "chair (m)": chair,
        "wall (s)": total_s,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=240)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--checkpoint", type=Path, default=Path("checkpoints/cpu-small.json"))
    p.add_argument("--process-every", type=int, default=10, help="frames between worker passes")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--consistency", default="on,off",
                   help="rows without depth: rendered_consistency on and/or off (comma separated)")
    p.add_argument("--no-depth-row", action="store_true", help="skip the row with input depth")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a node config key (TOML value); repeatable")
    args = p.parse_args(argv)
    modes = [m.strip() for m in args.consistency.split(",") if m.strip()]
    if not modes or any(m not in ("on", "off") for m in modes):
        p.error("--consistency: a comma-separated list of on / off")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    torch.set_num_threads(args.threads)
    rows = [] if args.no_depth_row else [run(args, True)]
    rows += [run(args, False, consistency=m == "on") for m in modes]
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        cells = [f"{v:.3f}" if isinstance(v, float) and k.endswith("(m)") else
                 f"{100 * v:.1f}%" if k.startswith("within") else
                 f"{v:.0f}" if isinstance(v, float) else str(v) for k, v in r.items()]
        print("| " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
