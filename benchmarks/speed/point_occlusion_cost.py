"""Cost of the request's points as occluders (``model.point_occlusion``,
``queries.point_occlusion``): :func:`mapper.geometry.splat.point_spacing` and
:func:`mapper.geometry.splat.occluder_depths` on the synthetic room of ``bench_averaging.py``
(points on the walls, floor and ceiling of a 6 x 5 x 3 m box, 160x120 cameras on a circle inside
it looking outwards). What ``segment_points`` with a depth test adds per request on an RGB-only
node whose window holds ``--views`` keyframes. Prints JSON: the best of ``--repeats`` wall times
(ms) per point count (the compiled kernel; ``--reference``: also the numpy reference), and the
share of pixels the z-buffers cover.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/point_occlusion_cost.py --points 20000 100000 \
        --views 30 --reference
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_averaging import room_scene  # noqa: E402

from mapper.geometry.splat import occluder_depths, point_spacing  # noqa: E402
from mapper.runtime.config import ModelRuntimeConfig  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, nargs="+", default=[20_000, 100_000])
    parser.add_argument("--views", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="kernel threads (the node: torch's)")
    parser.add_argument("--reference", action="store_true", help="also time the numpy reference")
    args = parser.parse_args()
    if min(args.points) < 2 or args.views < 1 or args.repeats < 1 or args.threads < 1:
        parser.error("--points must be >= 2 each, --views, --repeats and --threads >= 1")
    factor = ModelRuntimeConfig().point_occlusion_footprint
    rows = []
    for n in args.points:
        pts, views = room_scene(n, args.views, dim=8)
        K = np.stack([v.K for v in views])
        poses = np.stack([v.world_from_cam for v in views])
        width, height = views[0].image_wh
        best_sp = best_occ = best_ref = float("inf")
        z = np.zeros(0)
        spacing = 0.0
        occluder_depths(pts[:10], K[:1], poses[:1], width, height, 0.1, threads=args.threads)  # compile
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            spacing = point_spacing(pts)
            t1 = time.perf_counter()
            z = occluder_depths(pts, K, poses, width, height, factor * spacing, threads=args.threads)
            t2 = time.perf_counter()
            best_sp, best_occ = min(best_sp, t1 - t0), min(best_occ, t2 - t1)
            if args.reference:
                t3 = time.perf_counter()
                occluder_depths(pts, K, poses, width, height, factor * spacing, compiled=False)
                best_ref = min(best_ref, time.perf_counter() - t3)
        row = {"points": n, "views": args.views, "threads": args.threads, "spacing_m": round(spacing, 4),
               "point_spacing_ms": round(1e3 * best_sp, 1), "occluder_depths_ms": round(1e3 * best_occ, 1),
               "cover": round(float((z > 0).mean()), 3)}
        if args.reference:
            row["occluder_depths_numpy_ms"] = round(1e3 * best_ref, 1)
        rows.append(row)
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
