"""Two rooms one after the other into a node whose global map is bounded far below both: what the
first room's answers keep once the second is mapped, with paging (the default) and with the old
prune (``global_map.paging=false``), through real nodes.

Room A (a simulated ``clients.sim`` room, the robot's ``loop`` path, SimLSeg ``ov``, input depth)
is streamed into a ``govnesf serve`` process (:class:`clients.harness.NodeProcess`, the shipped
settings plus ``global_map.max_points``), the node settles and is asked ``segment_points`` at the
ground-truth surface samples room A's frames saw (``average`` and ``govnesf``; the 32 class names
as texts; 3D mIoU, :func:`clients.harness.mean_iou`) and ``query_points`` for each class present
(the matches inside room A's box, ``region``); then room B (another seed's room, its poses moved 12 m along x)
is streamed, the node settles and room A is asked again. Modes: ``unbounded`` (the shipped
``max_points``: what the answers do when room A's keyframes leave the window and nothing is
dropped), ``paging`` and ``prune``. Reported per mode: the answers before and after, and ``status``
(resident, paged, total and pruned points, tile store bytes, RSS).

Run: ``python benchmarks/studies/two_rooms_bounded.py`` (two rooms of 120 frames, max_points
30000: about 10 min on 2 cores), ``--quick`` (60 frames, ``average`` only: a first look). Seeds
with ``seed % 3 == 0`` are held out; the defaults (1 and 2) are tuning seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.harness import NodeProcess, mean_iou
from clients.matrix.driver import _settle
from clients.sim.scenes import CLASS_NAMES
from protocol.messages import Frame

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling, run as a file or imported
from continue_map import NODE_ARGS  # noqa: E402
from continue_map import prepare as prepare_room  # noqa: E402

OFFSET_M = 12.0


@dataclass
class Room:
    frames: list[Frame]
    gt_xyz: np.ndarray  # (P, 3) float32 world points some frame saw
    gt_label: np.ndarray  # (P,) int64


def prepare(seed: int, frames: int, offset_m: float, samples: int = 6000) -> Room:
    """Render the seed's room (160x120, 70 deg, input depth; ``continue_map.prepare``'s frames) with
    its world moved ``offset_m`` along x (the poses and the ground truth; the rendering is the
    room's own)."""
    room = prepare_room(seed, frames, depth=True, samples=samples)
    shift = np.eye(4)
    shift[0, 3] = offset_m
    for frame in room.frames:
        frame.world_from_cam = shift @ frame.world_from_cam
    gt_xyz = (room.gt_xyz.astype(np.float64) + shift[:3, 3]).astype(np.float32)
    return Room(room.frames, gt_xyz, room.gt_label)


def ask(client: Any, room: Room, methods: list[str]) -> dict[str, Any]:
    """Room A's answers: segment mIoU (%) per method, and query_points matches inside its box."""
    texts = list(CLASS_NAMES)
    out: dict[str, Any] = {}
    for method in methods:
        started = time.perf_counter()
        seg = client.segment_points(room.gt_xyz, texts, method=method, timeout_s=900.0)
        out[f"miou_{method}"] = round(100.0 * mean_iou(seg.label.astype(np.int64), room.gt_label,
                                                       len(texts))[0], 2)
        out[f"segment_{method}_s"] = round(time.perf_counter() - started, 2)
    low, high = room.gt_xyz.min(axis=0) - 0.5, room.gt_xyz.max(axis=0) + 0.5
    present = [CLASS_NAMES[c] for c in np.unique(room.gt_label)]
    started = time.perf_counter()
    matches = 0
    for text in present:
        pts = client.query_points([text], objects=False, max_points=200_000, region=(low, high),
                                  timeout_s=600.0)
        matches += int(pts.xyz.shape[0])
    out["query_matches_in_room"] = matches
    out["query_ms_per_text"] = round(1e3 * (time.perf_counter() - started) / max(len(present), 1), 1)
    # the same texts over the whole map: how many map points each query scored (resident + the
    # paged tiles whose summary says they may match) and its time
    scored, times = [], []
    for text in present:
        pts = client.query_points([text], objects=True, timeout_s=600.0)
        scored.append(pts.timing_ms.get("map_points", 0.0))
        times.append(pts.timing_ms.get("total", 0.0))
    out["whole_map_query_points_scored_mean"] = round(float(np.mean(scored)), 1)
    out["whole_map_query_ms_p50"] = round(float(np.median(times)), 1)
    out["whole_map_matches"] = sum(int(client.query_points([text], objects=False, max_points=200_000,
                                                           timeout_s=600.0).xyz.shape[0]) for text in present)
    return out


def map_status(client: Any) -> dict[str, Any]:
    extra = client.status(timeout_s=60.0).extra
    keys = ("global_points", "global_points_total", "global_points_paged", "global_tiles_paged",
            "global_points_pruned", "global_points_paged_out", "global_points_paged_in",
            "global_tile_store_bytes", "global_integrate_ms_mean", "global_integrate_ms_p95", "rss_bytes")
    out = {k: extra.get(k) for k in keys}
    for worker, fields in (("evicted_views", ("done", "dropped", "stale", "deferred", "voxels")),
                           ("map_features", ("done", "late", "dropped", "voxels_set"))):
        if isinstance(extra.get(worker), dict):
            out.update({f"{worker}.{f}": extra[worker].get(f) for f in fields})
    return out


def run(mode: str, room_a: Room, room_b: Room, max_points: int, methods: list[str], work: Path,
        settle_s: float, settings: list[str]) -> dict[str, Any]:
    args: tuple[str, ...] = (*NODE_ARGS, *(a for kv in settings for a in ("--set", kv)))
    if mode != "unbounded":  # unbounded: the shipped max_points, far above both rooms
        args = (*args, "--set", f"global_map.max_points={max_points}",
                "--set", f"global_map.paging={'true' if mode == 'paging' else 'false'}")
    out: dict[str, Any] = {"mode": mode}
    with NodeProcess(work / mode, extra_args=args, events=False, log_path=work / f"{mode}.log") as node:
        node.wait_ready(180.0)
        with node.client(timeout_s=600.0) as client:
            for name, room in (("a", room_a), ("b", room_b)):
                for _ in client.send_frames(iter(room.frames), window=4):
                    pass
                out[f"settled_after_{name}"] = _settle(client, settle_s)[0]
                out[f"status_after_{name}"] = map_status(client)
                out[f"room_a_after_{name}"] = ask(client, room_a, methods)
    return out


def compare_skips(room_a: Room, room_b: Room, max_points: int) -> dict[str, Any]:
    """``global_map.tile_skip`` "exact" against "centroids" on the same map: two in-process nodes
    (no learned model, background work done in line, so both maps are equal) fed both rooms, then
    a whole-map ``query_points`` per class present: matches, points scored, time."""
    from protocol.messages import Points, QueryPoints, decode, encode
    from tests.node_helpers import in_process_node

    texts = [CLASS_NAMES[c] for c in np.unique(np.concatenate([room_a.gt_label, room_b.gt_label]))]
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rule in ("exact", "centroids"):
            settings = {"integrate_queue": 0, "max_points": max_points, "tile_skip": rule}
            node = in_process_node(Path(tmp) / rule, global_map=settings)
            for frame in (*room_a.frames, *room_b.frames):
                node.handle_ingest(encode(frame))
                if node.ctx.evicted_views is not None:
                    node.ctx.evicted_views.process_pending()
            answers, scored, times = [], [], []
            for text in texts:
                started = time.perf_counter()
                reply = decode(node.handle_query(encode(QueryPoints(texts=[text], objects=False,
                                                                    max_points=200_000))), direction="reply")
                assert isinstance(reply, Points), reply
                times.append(1e3 * (time.perf_counter() - started))
                answers.append({tuple(p) for p in reply.xyz.tolist()})
                scored.append(reply.timing_ms["map_points"])
            total = node.ctx.state.global_map.total_points
            out[rule] = {"answers": answers, "scored_share": round(float(np.mean(scored)) / total, 4),
                         "ms_p50": round(float(np.median(times)), 1)}
    exact, rough = out["exact"], out["centroids"]
    pairs = list(zip(exact["answers"], rough["answers"], strict=True))
    return {"texts": len(texts), "matches_exact": sum(len(a) for a, _ in pairs),
            "matches_centroids": sum(len(b) for _, b in pairs),
            "matches_kept": sum(len(a & b) for a, b in pairs),
            "extra_in_centroids": sum(len(b - a) for a, b in pairs),
            **{f"{rule}_{k}": v for rule in out for k, v in out[rule].items() if k != "answers"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1,2", help="room A's and room B's seeds")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--max-points", type=int, default=30_000)
    parser.add_argument("--modes", default="unbounded,paging,prune",
                        help="unbounded (the shipped max_points), paging, prune (global_map.paging=false)")
    parser.add_argument("--quick", action="store_true", help="60 frames per room, average only")
    parser.add_argument("--compare-skips", action="store_true",
                        help="only compare global_map.tile_skip exact and centroids on one map, in-process")
    parser.add_argument("--settle-s", type=float, default=600.0)
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    parser.add_argument("--work", type=Path, default=None, help="keep the nodes' map dirs and logs here")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                        help="a node setting for every mode (repeatable), e.g. queries.evicted_views=false")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    if len(seeds) != 2 or args.frames < 2 or args.max_points < 1:
        parser.error("--seeds takes two seeds, --frames >= 2, --max-points >= 1")
    frames = 60 if args.quick else args.frames
    methods = ["average"] if args.quick else ["average", "govnesf"]
    room_a, room_b = prepare(seeds[0], frames, 0.0), prepare(seeds[1], frames, OFFSET_M)
    if args.compare_skips:
        print(json.dumps(compare_skips(room_a, room_b, args.max_points), indent=1))
        return
    results = []
    modes = args.modes.split(",")
    if not set(modes) <= {"unbounded", "paging", "prune"}:
        parser.error(f"--modes: {args.modes!r}: each of unbounded, paging, prune")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work if args.work is not None else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for mode in modes:
            started = time.perf_counter()
            row = run(mode, room_a, room_b, args.max_points, methods, work, args.settle_s, args.settings)
            row["seconds"] = round(time.perf_counter() - started, 1)
            results.append(row)
            print(json.dumps(row, indent=1), flush=True)
    for row in results:
        before, after = row["room_a_after_a"], row["room_a_after_b"]
        deltas = {k: round(after[k] - before[k], 2) for k in before if k.startswith("miou_")}
        print(f"{row['mode']}: room A before {before} after {after}; mIoU change {deltas}; "
              f"status after B {row['status_after_b']}")
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
