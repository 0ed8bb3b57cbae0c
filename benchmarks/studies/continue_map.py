"""A map continued after a restart against the same frames streamed in one go, through real nodes.

Per room (a simulated ``clients.sim`` room, the robot's ``loop`` path, SimLSeg ``ov``, with input
depth and without), the frames are rendered once and streamed over loopback into ``govnesf serve``
processes (:class:`clients.harness.NodeProcess`, the shipped settings):

* ``one_go``: every frame into one node, which settles and is asked at the half too (the
  continued run pauses there: without that pause in both, the comparison would measure the
  background work that a stream faster than it leaves undone, not the restart);
* ``continued``: the first half into a node, which is asked once settled, then ``save``\\ s the map
  and is killed; a new node on the same map directory ``load``\\ s it and the second half follows.

Both are asked once settled (``status`` ``pending`` empty twice in a row): ``segment_points`` at
the ground-truth surface samples the stream saw (``govnesf``, ``average``, ``dgm`` = ``govnesf``
with ``use_depth``, and with depth ``average_depth``; the 32 class names as texts), scored as 3D
mIoU (:func:`clients.harness.mean_iou`), over all those points (``all``) and over those only the
first half saw (``first_half_only``). The continued node is also asked right after the load,
before any frame of the second half (``after_load``), against the first node's answers before the
save (``before_save``): what a restart loses by itself.

Run (seeds with ``seed % 3 == 0`` are held out: choose on the others, report those):
``python benchmarks/studies/continue_map.py --seeds 1,2,4`` (2-4 min per room and depth
setting on 2 cores), ``--quick`` (one room, 60 frames, depth only: a first look),
``--seeds 3,6,9`` for the held-out report.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.harness import NodeProcess, mean_iou
from clients.matrix.driver import pending_work
from clients.sim.export import OV_SPACE, count_views
from clients.sim.paths import camera_path
from clients.sim.raycast import SceneRenderer
from clients.sim.robot import default_intrinsics
from clients.sim.scenes import CLASS_NAMES, LABEL_OF, generate_scene
from protocol.messages import Frame

LAYOUTS = ("apartment", "studio", "office", "living_large", "sparse", "corridor")
"""The room of seed ``s`` is ``LAYOUTS[s % len(LAYOUTS)]``."""
NODE_ARGS = ("--set", "save_on_exit=false", "--set", "load_autosave_on_start=false",
             "--set", "autosave_name=")
SETTLE_POLL_S = 0.25


@dataclass
class Room:
    """A room's frames and the ground truth to ask about."""

    seed: int
    layout: str
    depth: bool
    frames: list[Frame]
    gt_xyz: np.ndarray  # (P, 3) float32: surface samples some frame saw
    gt_label: np.ndarray  # (P,) int64
    first_only: np.ndarray  # (P,) bool: seen by the first half and not by the second


def prepare(seed: int, frames: int, depth: bool, samples: int = 6000) -> Room:
    """Render ``frames`` frames of the seed's room (160x120, 70 deg) and pick the points to ask."""
    from clients.sim.simlseg import SimLSeg, SimLSegConfig
    from clients.sim.text import get_text_encoder

    layout = LAYOUTS[seed % len(LAYOUTS)]
    scene = generate_scene(seed, layout)
    poses = camera_path(scene, "loop", frames, seed=seed)
    width, height = 160, 120
    K = default_intrinsics(width, height, 70.0)
    renderer = SceneRenderer(scene)
    simlseg = SimLSeg(CLASS_NAMES, get_text_encoder(), seed=seed, config=SimLSegConfig(stride=4))
    gt_xyz, gt_label, _ = scene.sample_surface(samples, seed=seed, exclude_labels=(LABEL_OF["ceiling"],))
    half = frames // 2
    views = np.zeros((2, len(gt_xyz)), np.int32)
    out: list[Frame] = []
    for k in range(frames):
        view = renderer.render(K, poses[k], width, height)
        count_views(gt_xyz, K, poses[k], view.depth_m, views[int(k >= half)])
        ov = simlseg.features(view, frame_index=k, K=K)
        out.append(Frame(seq=k, stamp_ns=int(round(k * 1e8)), width=width, height=height, K=K.copy(),
                         world_from_cam=poses[k].copy(), rgb=view.rgb,
                         depth_m=view.depth_m if depth else None, ov=ov, ov_space=OV_SPACE))
    seen = views.sum(axis=0) > 0
    first_only = (views[0] > 0) & (views[1] == 0)
    return Room(seed, layout, depth, out, gt_xyz[seen].astype(np.float32), gt_label[seen].astype(np.int64),
                first_only[seen])


def methods(depth: bool) -> list[tuple[str, str, bool]]:
    """(name, ``segment_points`` method, ``use_depth``) asked."""
    out = [("govnesf", "govnesf", False), ("average", "average", False), ("dgm", "govnesf", True)]
    return out + ([("average_depth", "average_depth", True)] if depth else [])


def settle(client: Any, timeout_s: float) -> bool:
    """Poll ``status`` until no background work is pending twice in a row (or the timeout)."""
    t0, quiet = time.perf_counter(), 0
    while time.perf_counter() - t0 < timeout_s:
        quiet = quiet + 1 if not pending_work(client.status(timeout_s=60.0).extra) else 0
        if quiet >= 2:
            return True
        time.sleep(SETTLE_POLL_S)
    return False


def ask(client: Any, room: Room) -> dict[str, dict[str, float]]:
    """mIoU (%) per method over every asked point and over the first-half-only ones."""
    texts = list(CLASS_NAMES)
    out: dict[str, dict[str, float]] = {}
    for name, method, use_depth in methods(room.depth):
        seg = client.segment_points(room.gt_xyz, texts, method=method, use_depth=use_depth, timeout_s=600.0)
        label = seg.label.astype(np.int64)
        out[name] = {
            "all": 100.0 * mean_iou(label, room.gt_label, len(texts))[0],
            "first_half_only": 100.0 * mean_iou(label[room.first_only], room.gt_label[room.first_only],
                                                len(texts))[0],
        }
    return out


def map_status(client: Any) -> dict[str, Any]:
    """What the map holds (window keyframes, global points, map version, keyframes evicted) and what
    the learned-features and triangulation workers did."""
    status = client.status(timeout_s=60.0)
    return {"keyframes": status.keyframes, "map_version": status.map_version,
            "global_points": status.extra.get("global_points"),
            "keyframes_evicted": status.extra.get("keyframes_evicted"),
            **{f"{worker}.{k}": status.extra[worker].get(k)
               for worker, keys in (("map_features", ("done", "late", "dropped", "voxels_set")),
                                    ("triangulation", ("keyframes", "points", "stale", "restored")))
               if isinstance(status.extra.get(worker), dict) for k in keys}}


def stream(client: Any, frames: list[Frame]) -> None:
    for _ in client.send_frames(iter(frames), window=4):
        pass


def run_one_go(room: Room, work: Path, settle_s: float, log: Path | None) -> dict[str, Any]:
    with NodeProcess(work / "maps", log_path=log, extra_args=NODE_ARGS, events=False) as node:
        node.wait_ready(180.0)
        with node.client(timeout_s=600.0) as client:
            half = len(room.frames) // 2
            stream(client, room.frames[:half])
            out: dict[str, Any] = {"settled_at_half": settle(client, settle_s)}
            out["at_half"] = ask(client, room)  # as the continued run asks before its save
            stream(client, room.frames[half:])
            out["settled"] = settle(client, settle_s)
            return {**out, "miou": ask(client, room), "status": map_status(client)}


def run_continued(room: Room, work: Path, settle_s: float, log: Path | None) -> dict[str, Any]:
    half = len(room.frames) // 2
    out: dict[str, Any] = {}
    maps = work / "maps"
    with NodeProcess(maps, log_path=log, extra_args=NODE_ARGS, events=False) as node:
        node.wait_ready(180.0)
        with node.client(timeout_s=600.0) as client:
            stream(client, room.frames[:half])
            out["settled_before_save"] = settle(client, settle_s)
            out["before_save"] = ask(client, room)
            out["status_before_save"] = map_status(client)
            out["save"] = client.save("half").message
    # the node is gone (killed: a crash or a restart); a new one on the same map directory
    second_log = None if log is None else log.with_name(log.stem + "-restarted.log")
    with NodeProcess(maps, log_path=second_log, extra_args=NODE_ARGS, events=False) as node:
        node.wait_ready(180.0)
        with node.client(timeout_s=600.0) as client:
            out["load"] = client.load("half").message
            out["status_after_load"] = map_status(client)
            settle(client, settle_s)
            out["after_load"] = ask(client, room)
            stream(client, room.frames[half:])
            out["settled"] = settle(client, settle_s)
            out["miou"] = ask(client, room)
            out["status"] = map_status(client)
    return out


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per depth setting and method: continued - one go (``all`` and ``first_half_only``), median
    and worst over the rooms, and both sides' medians."""
    out: dict[str, Any] = {}
    for depth in (True, False):
        sel = [r for r in rows if r["depth"] == depth]
        if not sel:
            continue
        part: dict[str, Any] = {}
        for name in sel[0]["one_go"]["miou"]:
            for subset in ("all", "first_half_only"):
                one = [r["one_go"]["miou"][name][subset] for r in sel]
                cont = [r["continued"]["miou"][name][subset] for r in sel]
                diff = [c - o for c, o in zip(cont, one, strict=True)]
                part[f"{name}/{subset}"] = {
                    "one_go_median": round(statistics.median(one), 1),
                    "continued_median": round(statistics.median(cont), 1),
                    "diff_median": round(statistics.median(diff), 2), "diff_worst": round(min(diff), 2)}
        out["depth" if depth else "rgb_only"] = part
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1,2,4", help="comma-separated room seeds")
    parser.add_argument("--frames", type=int, default=160, help="frames in all (half before the restart)")
    parser.add_argument("--depth", choices=["on", "off", "both"], default="both")
    parser.add_argument("--settle-timeout-s", type=float, default=300.0)
    parser.add_argument("--quick", action="store_true", help="one room, 60 frames, depth only")
    parser.add_argument("--log-dir", type=Path, default=None, help="keep the nodes' logs here")
    parser.add_argument("--out", type=Path, default=None, help="write the rows and summary (JSON) here")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    depths = {"on": [True], "off": [False], "both": [True, False]}[args.depth]
    if args.quick:
        seeds, depths, args.frames = seeds[:1], [True], 60
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        for depth in depths:
            t0 = time.perf_counter()
            room = prepare(seed, args.frames, depth)
            tag = f"s{seed}-{'d' if depth else 'rgb'}"
            row: dict[str, Any] = {"seed": seed, "layout": room.layout, "depth": depth,
                                   "frames": args.frames, "points": len(room.gt_xyz),
                                   "first_half_only_points": int(room.first_only.sum())}
            for which, run in (("one_go", run_one_go), ("continued", run_continued)):
                log = None if args.log_dir is None else args.log_dir / f"{tag}-{which}.log"
                with tempfile.TemporaryDirectory(prefix="govnesf-continue-") as tmp:
                    row[which] = run(room, Path(tmp), args.settle_timeout_s, log)
            row["wall_s"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            print(json.dumps(row), flush=True)
    result = {"args": {k: str(v) for k, v in vars(args).items()}, "summary": summary(rows), "rows": rows}
    print(json.dumps(result["summary"], indent=1), flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
