"""Micro-benchmark of ``query_points`` on a synthetic global map (in-process, no node): the
bare matrix-product floor, cached queries, and the first query after a map change (an
integrate of one keyframe, or a full ``restore``); as the node runs it (per-block label cache),
without the label cache (every row scored per query: what a new text costs), and with the
previous clustering (every k-d tree point pair) and snapshot (every block renormalised).

The map is ``mapper/bench/synthetic_maps.py``'s (one point per 5 cm voxel, 384-d fp16 features of a few
class names per 0.5 m block) restored into a :class:`mapper.map.global_map.GlobalSemanticMap`.
Prints JSON (milliseconds; p50 / p95 over ``--repeats``).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/bench_query_points.py --points 100000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def _pct(xs: list[float]) -> dict[str, float]:
    a = np.asarray(xs) * 1e3
    return {"p50": round(float(np.percentile(a, 50)), 2), "p95": round(float(np.percentile(a, 95)), 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()

    from mapper.bench.synthetic_maps import synthetic_map
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.map.window import Keyframe
    from mapper.node import queries
    from mapper.node.config import GlobalMapConfig, QueryConfig
    from mapper.ov.encoders import SPACE, get_text_encoder

    arrays, manifest = synthetic_map(args.points)
    arrays = {k.split(".", 1)[1]: v for k, v in arrays.items()}
    gmap = GlobalSemanticMap(GlobalMapConfig(max_points=max(2 * args.points, 1000)))
    gmap.restore({f"global.{k}": v for k, v in arrays.items()}, manifest["global_map"], map_version=1)
    enc = get_text_encoder(SPACE)
    cfg = QueryConfig()
    texts = ["find the chair"]
    enc.encode(["chair"])

    label_cache: queries.BlockLabelCache | None = None

    def ask(snap):  # noqa: ANN001, ANN202
        return queries.query_points(snap, enc, texts, negatives=None, min_score=None, max_points=None,
                                    objects=True, config=cfg, label_cache=label_cache)

    out: dict[str, object] = {"points": args.points}
    out["floor_ms"] = round(_floor(gmap.snapshot().unit_features_f32().copy()) * 1e3, 2)

    # a keyframe looking at one corner of the map (changes a few thousand voxels)
    side = float(arrays["xyz"].max())
    pose = np.eye(4)
    pose[:3, 3] = [side / 2, side / 2, -1.0]
    ov = np.random.default_rng(1).standard_normal((15, 20, 384)).astype(np.float16)
    depth = np.full((120, 160), 1.0 + side / 4, np.float32)

    def change(i: int) -> None:
        kf = Keyframe(seq=i, stamp_ns=i, camera="cam0", K=np.array([120.0, 120.0, 80.0, 60.0]),
                      world_from_cam=pose, rgb=np.zeros((120, 160, 3), np.uint8), depth_m=depth, ov=ov,
                      ov_space=SPACE)
        gmap.integrate(kf, map_version=i)

    for i in range(3):  # warm-up: the first integrates after a restore are slower (array growth)
        change(90 + i)
        ask(gmap.snapshot())
    for name, cached_labels, previous in (("new", True, False), ("no_label_cache", False, False),
                                          ("previous", False, True)):
        # new: as the node (per-block label cache); no_label_cache: every row scored per query;
        # previous: also the k-d tree clustering and a snapshot that renormalises every block
        label_cache = queries.BlockLabelCache(cfg.label_cache_blocks) if cached_labels else None
        if previous:
            queries.radius_components = queries._pair_components
        snap = gmap.snapshot()
        ask(snap)
        cached, stages = [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            r = ask(snap)
            cached.append(time.perf_counter() - t)
            stages.append(r.timing_ms)
        out[f"{name}.cached_ms"] = _pct(cached)
        out[f"{name}.cached_stages_ms_p50"] = {k: round(float(np.median([s[k] for s in stages])), 2)
                                               for k in ("score", "cluster", "select")}
        first, snap_s = [], []
        for i in range(args.repeats):
            change(100 + i)
            t = time.perf_counter()
            snap = gmap.snapshot()
            if previous:
                snap = dataclasses.replace(snap, _unit_source=None)
            t1 = time.perf_counter()
            ask(snap)
            first.append(time.perf_counter() - t)
            snap_s.append(t1 - t)
        out[f"{name}.first_after_integrate_ms"] = _pct(first)
        out[f"{name}.snapshot_copy_ms"] = _pct(snap_s)
        t = time.perf_counter()
        gmap.restore({f"global.{k}": v for k, v in arrays.items()}, manifest["global_map"], map_version=1)
        snap = gmap.snapshot()
        ask(snap)
        out[f"{name}.first_after_restore_ms"] = round((time.perf_counter() - t) * 1e3, 2)
    for name in ("new", "no_label_cache"):
        out[f"{name}.cached_over_floor_p95"] = round(out[f"{name}.cached_ms"]["p95"] / out["floor_ms"], 2)  # type: ignore[index]
    print(json.dumps(out, indent=1))


def _floor(feat32: np.ndarray) -> float:
    """Seconds of the bare (N, D) @ (D, 7) fp32 product (one text, six negatives), best of 20."""
    emb = np.random.default_rng(0).standard_normal((7, feat32.shape[1])).astype(np.float32)
    best = float("inf")
    for _ in range(20):
        t = time.perf_counter()
        feat32 @ emb.T
        best = min(best, time.perf_counter() - t)
    return best


if __name__ == "__main__":
    main()
