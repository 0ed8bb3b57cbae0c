"""Micro-benchmark of the averaging baselines (``segment_points`` methods ``average`` and
``average_depth``): :func:`mapper.model.baselines.average_features` against the previous
implementation (``average_features_reference``) on a synthetic room.

The room: ``--points`` points on the walls, floor and ceiling of a 6 x 5 x 3 m box, ``--views``
160x120 cameras on a circle inside it looking outwards and slightly down, 384-d ``ov`` maps on a
20x15 grid (float16, as the node keeps them) and depth maps z-buffered from the points (so the
depth test keeps the views that see a point). Prints JSON: seconds per method and
implementation (best of ``--repeats``), per 100k points, ``average_similarities`` (what
``segment_points`` calls: cosines to 7 texts), the mean views per point and the largest
difference between the two implementations' features.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/bench_averaging.py --points 100000 --views 30
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from clients.harness import look_at
from mapper.model.baselines import OVView, average_features, average_features_reference, average_similarities


def room_scene(n_points: int, n_views: int, dim: int = 384, seed: int = 0) -> tuple[np.ndarray, list[OVView]]:
    """(N, 3) float32 surface points and ``n_views`` views with ov and z-buffered depth."""
    rng = np.random.default_rng(seed)
    size = np.array([6.0, 5.0, 3.0])
    face = rng.integers(0, 6, n_points)
    pts = rng.random((n_points, 3)) * size
    axis, side = face // 2, face % 2
    pts[np.arange(n_points), axis] = side * size[axis]
    pts = pts.astype(np.float32)
    width, height = 160, 120
    K = np.array([60.0, 60.0, 80.0, 60.0])
    views = []
    for i in range(n_views):
        yaw = 2 * np.pi * i / n_views
        centre = np.array([3.0 + 0.5 * np.cos(yaw), 2.5 + 0.5 * np.sin(yaw), 1.5])
        world_from_cam = look_at(centre, centre + np.array([np.cos(yaw), np.sin(yaw), -0.2]))
        cam = (pts - centre) @ world_from_cam[:3, :3]
        z = cam[:, 2]
        front = z > 0.05
        u = cam[front, 0] / z[front] * K[0] + K[2]
        v = cam[front, 1] / z[front] * K[1] + K[3]
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        depth = np.full(height * width, np.inf)
        pix = v[inside].astype(int) * width + u[inside].astype(int)
        np.minimum.at(depth, pix, z[front][inside])
        depth[np.isinf(depth)] = 0.0
        ov = rng.standard_normal((15, 20, dim)).astype(np.float16)
        depth_m = depth.reshape(height, width).astype(np.float32)
        views.append(OVView(ov, K, world_from_cam, (width, height), depth_m))
    return pts, views


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--views", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--no-reference", action="store_true", help="time only the fast path")
    args = parser.parse_args()
    pts, views = room_scene(args.points, args.views)
    out: dict[str, object] = {"points": args.points, "views": args.views, "threads": torch.get_num_threads()}
    for method, use_depth in (("average", False), ("average_depth", True)):
        impls = {"fast": average_features} if args.no_reference else {
            "fast": average_features, "reference": average_features_reference}
        res = {}
        for name, fn in impls.items():
            best = float("inf")
            for _ in range(args.repeats):
                t = time.perf_counter()
                f, n = fn(pts, views, use_depth=use_depth)
                best = min(best, time.perf_counter() - t)
            res[name] = (f, n)
            out[f"{method}.{name}_s"] = best
            out[f"{method}.{name}_s_per_100k"] = best * 100_000 / args.points
        texts = np.random.default_rng(1).standard_normal((7, 384)).astype(np.float32)
        texts /= np.linalg.norm(texts, axis=1, keepdims=True)
        best = float("inf")
        for _ in range(args.repeats):  # what segment_points uses: cosines to 7 texts, no (N, D) result
            t = time.perf_counter()
            average_similarities(pts, views, texts, use_depth=use_depth)
            best = min(best, time.perf_counter() - t)
        out[f"{method}.similarities_s_per_100k"] = best * 100_000 / args.points
        out[f"{method}.views_per_point"] = float(res["fast"][1].double().mean())
        if "reference" in res:
            out[f"{method}.max_abs_diff"] = float((res["fast"][0] - res["reference"][0]).abs().max())
            out[f"{method}.n_views_equal"] = bool(torch.equal(res["fast"][1], res["reference"][1]))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
