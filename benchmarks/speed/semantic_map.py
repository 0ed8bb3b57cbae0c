"""Benchmarks of the global semantic map and the semantic queries (docs/concepts/window-and-map.md).

    python benchmarks/speed/semantic_map.py integrate  # integrate time per 160x120 keyframe (sim frames)
    python benchmarks/speed/semantic_map.py query      # query_points on a sim room and on a large map
    python benchmarks/speed/semantic_map.py segment    # segment_points average / average_depth, 100k points
    python benchmarks/speed/semantic_map.py stream --frames 2000 --max-points 100000
                                                 # a real node: RSS and map size after a long stream

Timings are wall-clock on whatever machine runs this; the printout says what was measured.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def _keyframes(seed: int, frames: int, width: int, height: int, offset_m: float = 0.0) -> list:
    from clients.harness import sim_stream
    from mapper.map.window import Keyframe

    stream = sim_stream(seed, frames, width, height)
    out = []
    for f, _ in stream.frames():
        pose = f.world_from_cam.copy()
        pose[0, 3] += offset_m
        out.append(Keyframe(seq=f.seq, stamp_ns=f.stamp_ns, camera="cam0", K=f.K, world_from_cam=pose,
                            rgb=f.rgb, depth_m=f.depth_m, ov=f.ov, ov_space=f.ov_space))  # fmt: skip
    return out


def _ms(values: list[float]) -> str:
    values = sorted(values)
    p90 = values[int(0.9 * (len(values) - 1))]
    return f"median {1e3 * statistics.median(values):.1f} ms, p90 {1e3 * p90:.1f} ms, n={len(values)}"


def bench_integrate(args: argparse.Namespace) -> None:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.config import GlobalMapConfig

    kfs = _keyframes(args.seed, args.frames, 160, 120)
    gmap = GlobalSemanticMap(GlobalMapConfig())
    times = [gmap.integrate(kf).seconds for kf in kfs]
    print(f"integrate, 160x120 keyframes with depth + 30x40x384 ov, stride 2, 5 cm voxels: {_ms(times)}; "
          f"map {len(gmap)} points, {gmap.nbytes / 1e6:.1f} MB")


def _large_snapshot(n: int, dim: int = 384):
    from mapper.map.global_map import GlobalMapSnapshot
    from mapper.ov.encoders import get_text_encoder

    rng = np.random.default_rng(0)
    names = ["chair", "table", "bed", "sofa", "wall", "floor", "cabinet", "door", "window", "lamp"]
    emb = get_text_encoder().encode(names)
    cls = rng.integers(0, len(names), n)
    centres = rng.uniform(0, 30, (len(names) * 20, 3))
    xyz = (centres[cls * 20 + rng.integers(0, 20, n)] + rng.normal(0, 0.3, (n, 3))).astype(np.float32)
    feat = emb[cls] + 0.03 * rng.normal(size=(n, dim)).astype(np.float32)
    feat /= np.linalg.norm(feat, axis=1, keepdims=True)
    return GlobalMapSnapshot(version=1, map_version=1, voxel_size_m=0.05, xyz=xyz,
                             feat=feat.astype(np.float16), weight=np.ones(n, np.float32),
                             feat_weight=np.ones(n, np.float32), hits=np.ones(n, np.int32),
                             last_seen_ns=np.zeros(n, np.int64))  # fmt: skip


def _time_queries(snapshot, label: str, repeats: int) -> None:  # noqa: ANN001
    from mapper.node.config import QueryConfig
    from mapper.node.queries import query_points
    from mapper.ov.encoders import get_text_encoder

    enc = get_text_encoder()
    t = time.perf_counter()
    snapshot.unit_features_f32()
    first = time.perf_counter() - t
    enc.encode(["chair", "find the chair", "table", "bed"])  # prompt cache warm, as on a running node
    cold: list[float] = []
    stages: dict[str, list[float]] = {}
    for _ in range(repeats):
        t = time.perf_counter()
        reply = query_points(snapshot, enc, ["find the chair"], negatives=None, min_score=None,
                             max_points=None, objects=True, config=QueryConfig())  # fmt: skip
        cold.append(time.perf_counter() - t)
        for k, v in reply.timing_ms.items():
            stages.setdefault(k, []).append(v)
    print(f"query_points 'find the chair' on {label} ({len(snapshot)} points): {_ms(cold)}; "
          f"per-version feature cache built once in {1e3 * first:.0f} ms; stages (median ms): "
          + ", ".join(f"{k} {statistics.median(v):.1f}" for k, v in stages.items() if k != "map_points"))


def bench_query(args: argparse.Namespace) -> None:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.config import GlobalMapConfig

    gmap = GlobalSemanticMap(GlobalMapConfig())
    for kf in _keyframes(args.seed, args.frames, 160, 120):
        gmap.integrate(kf)
    _time_queries(gmap.snapshot(), f"the sim room (seed {args.seed}, {args.frames} frames)", args.repeats)
    _time_queries(_large_snapshot(args.points), "a synthetic map", args.repeats)


def bench_segment(args: argparse.Namespace) -> None:
    from clients.sim.scenes import CLASS_NAMES, LABEL_OF
    from mapper.node.queries import segment_average
    from mapper.ov.encoders import get_text_encoder

    kfs = _keyframes(args.seed, args.frames, 160, 120)
    window = kfs[:: max(1, len(kfs) // args.views)][: args.views]
    from clients.harness import sim_stream

    scene = sim_stream(args.seed, 1, 16, 12, ov=False).scene
    xyz, _, _ = scene.sample_surface(args.points, seed=0, exclude_labels=(LABEL_OF["ceiling"],))
    emb = get_text_encoder().encode(list(CLASS_NAMES))
    views = [(k.ov, k.K, k.world_from_cam, (k.width, k.height), k.depth_m) for k in window]
    for use_depth in (False, True):
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            label, _, _ = segment_average(xyz, views, emb, use_depth=use_depth)
            times.append(time.perf_counter() - t)
        name = "average_depth" if use_depth else "average"
        print(f"segment_points {name}: {len(xyz)} points, {len(views)} views (160x120, ov 30x40x384), "
              f"{len(CLASS_NAMES)} texts: {_ms(times)}; labelled {100 * (label >= 0).mean():.0f}%")


def bench_stream(args: argparse.Namespace) -> None:
    """A real node; rooms of several seeds side by side (20 m apart) so the map outgrows max_points."""
    import tempfile

    from tqdm import tqdm

    from clients.harness import NodeProcess, sim_stream

    rooms = max(1, args.rooms)
    per_room = args.frames // rooms
    root = Path(tempfile.mkdtemp(prefix="bench_stream_"))
    node = NodeProcess(root / "maps", log_path=root / "node.log", events=False,
                       extra_args=["--set", f"global_map.max_points={args.max_points}",
                                   "--set", f"window.max_keyframes={args.window}"])  # fmt: skip

    def frames():  # noqa: ANN202
        for r in range(rooms):
            stream = sim_stream(args.seed + r, per_room, 160, 120)
            for k in range(per_room):
                f = stream.frame(k, stream.render(k))
                f.seq = r * per_room + k
                f.stamp_ns = int(f.seq * 1e8)
                f.world_from_cam = f.world_from_cam.copy()
                f.world_from_cam[0, 3] += 20.0 * r
                yield f

    with node:
        node.wait_ready()
        t0 = time.perf_counter()
        with node.client(timeout_s=120.0) as client:
            for _ in tqdm(client.send_frames(frames(), window=4), total=per_room * rooms, unit="frame"):
                pass
            dt = time.perf_counter() - t0
            status = client.status()
            t = time.perf_counter()
            reply = client.query_points(["find the chair"], timeout_s=300.0)
            q_first = time.perf_counter() - t
            t = time.perf_counter()
            client.query_points(["a place to sleep"], timeout_s=300.0)
            q_second = time.perf_counter() - t
            learned = "govnesf" in status.extra.get("segment_methods", [])
            if learned:  # the learned model syncs its cost volume to the window, then blends
                pts = reply.xyz[:1] if reply.xyz.shape[0] else np.zeros((1, 3), np.float32)
                xyz = (pts + np.random.default_rng(0).normal(0, 1.0, (20_000, 3))).astype(np.float32)
                t = time.perf_counter()
                client.segment_points(xyz, ["chair", "table", "wall", "floor"], timeout_s=600.0)
                seg_s = time.perf_counter() - t
                after = client.status()
    e = status.extra
    print(f"stream: {per_room * rooms} frames (160x120, depth + ov) from {rooms} rooms in {dt:.0f} s; "
          f"keyframes {e['frames_keyframe']}, window {status.keyframes}; "
          f"global map {e['global_points']} points "
          f"(max_points {e['global_max_points']}, pruned {e['global_points_pruned']}), "
          f"{e['global_map_bytes'] / 1e6:.0f} MB; memory_bytes {status.memory_bytes / 1e6:.0f} MB; "
          f"node RSS {e['rss_bytes'] / 1e6:.0f} MB; integrate mean {e['global_integrate_ms_mean']} ms")
    print(f"query_points over the wire after the stream: first {1e3 * q_first:.0f} ms (builds the "
          f"per-version cache; node timing {reply.timing_ms.get('total', 0):.0f} ms), "
          f"next {1e3 * q_second:.0f} ms")
    if learned:
        m = after.extra.get("model", {})
        print(f"segment_points govnesf, 20k points after the stream: {seg_s:.1f} s (includes syncing "
              f"{m.get('views')} views); then memory_bytes {after.memory_bytes / 1e6:.0f} MB, "
              f"node RSS {after.extra['rss_bytes'] / 1e6:.0f} MB, "
              f"model {m.get('memory_bytes', 0) / 1e6:.0f} MB")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("part", choices=("integrate", "query", "segment", "stream"))
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--views", type=int, default=30, help="segment: keyframes in the window")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rooms", type=int, default=5, help="stream: rooms side by side")
    parser.add_argument("--max-points", type=int, default=100_000, help="stream: global_map.max_points")
    parser.add_argument("--window", type=int, default=30, help="stream: window.max_keyframes")
    args = parser.parse_args()
    {"integrate": bench_integrate, "query": bench_query, "segment": bench_segment, "stream": bench_stream}[
        args.part](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
