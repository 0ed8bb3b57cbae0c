"""Cost of the kept views of evicted keyframes without depth (``queries.evicted_frames_mb``,
:mod:`mapper.map.evicted_frames`): :meth:`EvictedFrameStore.means` (Z-order blocks, frustum culling,
the compiled averaging kernel over the reduced maps) on the synthetic room of ``bench_averaging.py``
(points on the walls, floor and ceiling of a 6 x 5 x 3 m box, 160x120 cameras on a circle inside it
looking outwards; 384-d OV maps of 30 x 40 reduced to ``--cells``). What ``segment_points`` with
``average`` adds per request on an RGB-only node holding ``--views`` kept views, and what adding a
view costs. Prints JSON: the best of ``--repeats`` wall times (ms) per point count, the points
some view sees and their mean views, the store's size, the time to add a view. With
``--occlusion-spacings S`` > 0 also the means with the occlusion test ``govnesf``'s mix of the evicted
views takes (``queries.learned_evicted_views``: the points splatted into each kept view, each
covering S times their median spacing, ``model.point_occlusion_footprint``).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/evicted_frames_cost.py --points 100000 --views 1000
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

from mapper.map.evicted_frames import EvictedFrameStore  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, nargs="+", default=[20_000, 100_000])
    parser.add_argument("--views", type=int, default=1000)
    parser.add_argument("--cells", type=int, default=300)
    parser.add_argument("--dim", type=int, default=384)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="kernel threads (the node: torch's)")
    parser.add_argument("--occlusion-spacings", type=float, default=0.0,
                        help="also time the occlusion-tested means (0: not)")
    args = parser.parse_args()
    if min(args.points) < 1 or min(args.views, args.cells, args.dim, args.repeats, args.threads) < 1:
        parser.error("--points, --views, --cells, --dim, --repeats and --threads must be >= 1")
    if not args.occlusion_spacings >= 0:
        parser.error("--occlusion-spacings must be >= 0")
    rng = np.random.default_rng(0)
    _, views = room_scene(10, args.views, dim=4)  # the cameras only
    store = EvictedFrameStore()
    t0 = time.perf_counter()
    for v in views:
        ov = rng.standard_normal((30, 40, args.dim)).astype(np.float16)
        store.add(ov, v.K, v.world_from_cam, v.image_wh, max_cells=args.cells, budget_bytes=1 << 40)
    add_ms = 1e3 * (time.perf_counter() - t0) / args.views
    rows = []
    for n in args.points:
        pts, _ = room_scene(n, 1, dim=4)
        store.means(pts[:100], threads=args.threads)  # compile / load the kernel
        best = float("inf")
        hit = 0
        for _ in range(args.repeats):
            t1 = time.perf_counter()
            got_rows, _, count = store.means(pts, threads=args.threads)
            best = min(best, time.perf_counter() - t1)
            hit = int(got_rows.shape[0])
            mean_views = float(count.mean()) if count.size else 0.0
        row = {"points": n, "means_ms": round(1e3 * best, 1),
               "ms_per_100k_points": round(1e3 * best * 100_000 / n, 1),
               "points_seen": hit, "views_per_seen_point": round(mean_views, 1)}
        if args.occlusion_spacings > 0:
            from mapper.geometry.splat import point_spacing

            footprint = args.occlusion_spacings * point_spacing(pts)
            best_occ = float("inf")
            for _ in range(args.repeats):
                t1 = time.perf_counter()
                _, _, count = store.means(pts, threads=args.threads, occlusion_footprint_m=footprint)
                best_occ = min(best_occ, time.perf_counter() - t1)
            row["occluded_means_ms"] = round(1e3 * best_occ, 1)
            row["occluded_views_per_seen_point"] = round(float(count.mean()) if count.size else 0.0, 1)
        rows.append(row)
    print(json.dumps({"views": args.views, "cells": args.cells, "dim": args.dim, "threads": args.threads,
                      "store_mb": round(store.nbytes / 2**20, 1), "add_ms_per_view": round(add_ms, 2),
                      "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
