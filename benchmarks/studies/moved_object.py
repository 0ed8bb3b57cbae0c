"""A room mapped, one chair moved about 2 m, the room mapped again: what the global map keeps at
the old place, and where "find the chair" points, with visibility carving off and on.

The simulated room (``clients.sim``, style apartment) is streamed along the robot's path into an
in-process node (input depth, SimLSeg ``ov``, the ``average`` node without the learned model); then
the mesh of one chair instance is translated (to a free spot 2.0-2.8 m away, inside the room,
clear of the other objects and at least 0.4 m from every camera position of the path), the
renderer rebuilt, and the same path streamed again. Measured after each pass:

- ``chair points``: global-map points whose nearest surface of the room before the move
  (5 000 samples per m^2) is the chair's, within 5 cm;
- ``left at the old place``: of those, the ones farther than 10 cm from every surface of the
  room after the move (nothing is there any more);
- ``at the new place``: map points within 5 cm of the moved chair's surface;
- the rank (1 = best) of the first ``query_points`` object ("find the chair") whose centroid lies
  in the moved chair's box grown by 0.3 m, and of the first in the old chair's box (old place);
- the global map's integrate time, p50 / p95 (status ``global_integrate_ms_*``), both passes.

Run: ``python benchmarks/studies/moved_object.py --seed 3 --frames 240`` (about 4 min on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from clients.harness import sim_stream
from clients.sim.raycast import SceneRenderer
from clients.sim.scenes import CLASS_NAMES
from mapper.map.global_map import GlobalMapConfig, GlobalSemanticMap
from mapper.map.window import Keyframe
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from protocol.messages import Frame, QueryPoints, StatusRequest, decode, encode

SAMPLES_PER_M2 = 5000.0


def free_offset(stream: Any, chair: Any, lo_m: float = 2.0, hi_m: float = 2.8) -> np.ndarray:
    """A horizontal offset (3,) that moves ``chair`` to a free spot: inside the room, 10 cm clear
    of every other object's box, its box 0.4 m from every camera centre of the path."""
    scene = stream.scene
    others = [i for i in scene.instances if chair.instance_id not in (i.instance_id, i.support_id)]
    boxes = [(i.aabb_min, i.aabb_max) for i in others] + list(scene.structures)
    cams = stream.poses[:, :2, 3]
    best = None
    for dist in np.arange(lo_m, hi_m + 1e-9, 0.1):
        for ang in np.linspace(0.0, 2 * np.pi, 48, endpoint=False):
            off = np.array([dist * np.cos(ang), dist * np.sin(ang), 0.0])
            lo, hi = chair.aabb_min + off, chair.aabb_max + off
            if (lo[:2] < scene.room_min[:2] + 0.1).any() or (hi[:2] > scene.room_max[:2] - 0.1).any():
                continue
            if any((lo[:2] < b_hi[:2] + 0.1).all() and (hi[:2] > b_lo[:2] - 0.1).all() and lo[2] < b_hi[2]
                   for b_lo, b_hi in boxes):
                continue
            gap = np.maximum(np.maximum(lo[:2] - cams, cams - hi[:2]), 0.0)
            if np.linalg.norm(gap, axis=1).min() < 0.4:
                continue
            best = off
            break
        if best is not None:
            break
    if best is None:
        raise SystemExit(f"no free spot {lo_m}..{hi_m} m from chair {chair.instance_id}")
    return best


def move_instance(stream: Any, chair: Any, offset: np.ndarray) -> None:
    """Translate the chair's mesh (and what rests on it) by ``offset`` and rebuild the renderer."""
    scene = stream.scene
    ids = {chair.instance_id} | {i.instance_id for i in scene.instances if i.support_id == chair.instance_id}
    faces = np.isin(scene.face_instance, list(ids))
    verts = np.unique(scene.triangles[faces])
    scene.vertices[verts] += offset.astype(np.float32)
    for inst in scene.instances:
        if inst.instance_id in ids:
            inst.aabb_min, inst.aabb_max, inst.centroid = (a + offset for a in
                                                           (inst.aabb_min, inst.aabb_max, inst.centroid))
    stream.renderer = SceneRenderer(scene)


def surface(scene: Any) -> tuple[cKDTree, np.ndarray, np.ndarray]:
    """The room's surface samples: (their k-d tree, instance ids, class labels)."""
    n = int(SAMPLES_PER_M2 * scene.face_areas().sum())
    xyz, label, inst = scene.sample_surface(n, seed=0)
    return cKDTree(xyz), inst, label


@dataclass
class Passes:
    """Both passes rendered once: the frames, the room's surface before and after the move."""

    frames: list[Frame]  # pass 1, then pass 2 (seq and stamps continue)
    chair: int  # the moved instance
    offset: np.ndarray  # (3,)
    old_box: tuple[np.ndarray, np.ndarray]
    new_box: tuple[np.ndarray, np.ndarray]
    before: tuple[cKDTree, np.ndarray, np.ndarray]  # surface samples before the move (surface())
    after: tuple[cKDTree, np.ndarray, np.ndarray]


def render_passes(seed: int, frames: int) -> Passes:
    stream = sim_stream(seed=seed, frames=frames, depth=True)
    chair = next(i for i in stream.scene.instances if i.class_name == "chair")
    before = surface(stream.scene)
    old_box = (chair.aabb_min.copy(), chair.aabb_max.copy())
    offset = free_offset(stream, chair)
    out = [frame for frame, _ in stream.frames()]
    move_instance(stream, chair, offset)
    for frame, _ in stream.frames():
        frame.seq += frames
        frame.stamp_ns += int((frames + 1) * 1e9 / stream.config.fps)
        out.append(frame)
    return Passes(out, chair.instance_id, offset, old_box, (chair.aabb_min, chair.aabb_max), before,
                  surface(stream.scene))


def run(passes: Passes, carve: bool, work: Path) -> dict[str, Any]:
    config = config_from_dict({
        "map_dir": str(work), "autosave_name": "", "save_on_exit": False, "serve_model": False,
        "events_endpoint": "", "global_map": {"integrate_queue": 0, "carve": carve},
    })
    node = MapperNode(config)

    def ask(msg: Any) -> Any:
        return decode(node.handle_query(encode(msg)), direction="reply")

    (before_tree, before_inst, _), (after_tree, after_inst, _) = passes.before, passes.after
    chair, old_box, new_box = passes.chair, passes.old_box, passes.new_box
    half = len(passes.frames) // 2
    out: dict[str, Any] = {"carve": carve, "frames_per_pass": half, "chair": chair,
                           "moved_m": round(float(np.linalg.norm(passes.offset)), 2)}
    started = time.perf_counter()
    for frame in passes.frames[:half]:
        node.handle_ingest(encode(frame))
    node.ctx.drain_integrations()
    xyz = np.asarray(node.ctx.state.global_map.snapshot().xyz)
    dist, idx = before_tree.query(xyz)
    on_chair = (dist <= 0.05) & (before_inst[idx] == chair)
    out["pass1"] = {"chair_points": int(on_chair.sum()), "objects": ranks(ask, old_box, None, passes.before)}
    for frame in passes.frames[half:]:
        node.handle_ingest(encode(frame))
    node.ctx.drain_integrations()
    xyz = np.asarray(node.ctx.state.global_map.snapshot().xyz)
    dist, idx = before_tree.query(xyz)
    was_chair = (dist <= 0.05) & (before_inst[idx] == chair)
    dist_now, idx_now = after_tree.query(xyz)
    out["pass2"] = {
        "chair_points_left_at_old_place": int((was_chair & (dist_now > 0.10)).sum()),
        "chair_points_at_new_place": int(((dist_now <= 0.05) & (after_inst[idx_now] == chair)).sum()),
        "objects": ranks(ask, old_box, new_box, passes.after),
    }
    status = ask(StatusRequest())
    extra = getattr(status, "extra", None) or {}
    gm = extra
    out["global_points"] = gm.get("global_points")
    out["global_points_carved"] = gm.get("global_points_carved")
    out["integrate_ms_p50"] = gm.get("global_integrate_ms_p50")
    out["integrate_ms_p95"] = gm.get("global_integrate_ms_p95")
    out["seconds"] = round(time.perf_counter() - started, 1)
    node.stop()
    return out


def ranks(ask: Any, old_box: tuple[np.ndarray, np.ndarray], new_box: tuple[np.ndarray, np.ndarray] | None,
          room: tuple[cKDTree, np.ndarray, np.ndarray], pad: float = 0.3) -> dict[str, Any]:  # fmt: skip
    """"find the chair": the rank of the first object centred in each box (grown by ``pad``), and
    the top objects with the class of the room's surface nearest to their centroid."""
    # settled: an answer of the current map, not a stale one returned while frames arrive
    reply = ask(QueryPoints(texts=["find the chair"], settle_timeout_s=5.0))
    objects = list(reply.objects)
    tree, _, label = room
    near = [CLASS_NAMES[label[tree.query(np.asarray(o.centroid))[1]]] for o in objects]

    def first_in(box: tuple[np.ndarray, np.ndarray]) -> int | None:
        for rank, obj in enumerate(objects, 1):
            if np.all((obj.centroid >= box[0] - pad) & (obj.centroid <= box[1] + pad)):
                return rank
        return None

    return {"n_objects": len(objects), "rank_old_place": first_in(old_box),
            "rank_new_place": first_in(new_box) if new_box is not None else None,
            "top": [f"{near[k]} at {np.round(np.asarray(o.centroid), 2).tolist()}"
                    for k, o in enumerate(objects[:5])]}


def integrate_timing(passes: Passes) -> dict[str, Any]:
    """The global map's integrate time per keyframe, in process, carving off and on: every frame
    of both passes integrated into two maps in turn (the same load on the machine for both)."""
    maps = {carve: GlobalSemanticMap(GlobalMapConfig(carve=carve)) for carve in (False, True)}
    seconds: dict[bool, list[float]] = {False: [], True: []}
    for frame in passes.frames:
        kf = Keyframe(seq=frame.seq, stamp_ns=frame.stamp_ns, camera="cam0", K=np.asarray(frame.K),
                      world_from_cam=np.asarray(frame.world_from_cam), rgb=np.asarray(frame.rgb),
                      depth_m=frame.depth_m, ov=frame.ov, ov_space=frame.ov_space)
        for carve, gmap in maps.items():
            seconds[carve].append(gmap.integrate(kf).seconds)
    out: dict[str, Any] = {"keyframes": len(passes.frames)}
    for carve, secs in seconds.items():
        p50, p95 = np.percentile(1e3 * np.asarray(secs), [50, 95])
        out["carve_on" if carve else "carve_off"] = {
            "ms_p50": round(float(p50), 2), "ms_p95": round(float(p95), 2), "points": len(maps[carve])}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--frames", type=int, default=240, help="frames per pass")
    parser.add_argument("--carve", choices=["off", "on", "both"], default="both")
    args = parser.parse_args()
    modes = {"off": [False], "on": [True], "both": [False, True]}[args.carve]
    passes = render_passes(args.seed, args.frames)
    print(json.dumps({"seed": args.seed, "integrate_160x120": integrate_timing(passes)}), flush=True)
    for carve in modes:
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(run(passes, carve, Path(tmp))), flush=True)


if __name__ == "__main__":
    main()
