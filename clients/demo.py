"""End-to-end demo (``make demo``): a simulated robot maps a room, then "find the chair".

Steps, each printed as it happens:

1. generate a procedural apartment room (``clients.sim``; seed 3 by default: chairs, a table and a
   bed) and the simulated robot's path;
2. start ``govnesf serve`` as a subprocess on free loopback ports, with the map directory under
   the output directory;
3. stream the robot's frames into it (rgb, depth and SimLSeg open-vocabulary features, 160x120)
   with a progress bar;
4. ask "find the chair", "a place to sleep" and "where is the table"; print the top objects with
   their positions, write a PLY (points coloured by score) and a JSON of the objects for each,
   and check that the top chair lies within 0.5 m of a real chair (ground-truth instances);
5. 3D semantic segmentation against ground truth: ``segment_points`` (``govnesf`` with and
   without Depth Guided Masking when the node has its model, ``average_depth`` and
   ``average``) at ground-truth surface points with the class names as texts, plus the global
   map's own labels (``query_points`` with every class name), each as mIoU;
6. save the map, stop the node with SIGINT and check that it exited cleanly (exit code 0).

Outputs under ``out/demo/`` (override with ``--out``): ``*.ply`` / ``*.json`` per query,
``segmentation.json``, ``scene.ply`` (the ground-truth mesh), the node log and the map directory.
``--rerun FILE.rrd`` (off by default) also logs the streamed frames, the queries, the map's labels
and the render for the Rerun viewer (``clients/rerun_log.py``; ``--rerun-every N`` thins frames).
The demo exits non-zero if the chair answer is wrong or the node misbehaves.

This module also provides helpers the end-to-end tests and benchmarks share:
:func:`write_synthetic_recording`, :func:`synthetic_frame` (a checkerboard floor),
:func:`sim_stream`, :func:`mean_iou`, :func:`free_endpoints` and :class:`NodeProcess`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from clients.client import MapperClient
from protocol.messages import Frame
from protocol.recording import RecordingWriter

REPO_ROOT = Path(__file__).resolve().parent.parent

# ---------------------------------------------------------------------------------------------
# synthetic frames: a camera circling a checkerboard floor (z = 0), looking at the origin

CHECKER_SIZE_M = 0.5
DEMO_OV_SPACE = "demo-checker"
DEMO_OV_DIM = 8


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cam for an OpenCV camera at ``eye`` (3,) looking at ``target`` (3,),
    world +z up (x right, y down, z forward in the camera)."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    world_from_cam = np.eye(4)
    world_from_cam[:3, 0], world_from_cam[:3, 1], world_from_cam[:3, 2] = right, down, forward
    world_from_cam[:3, 3] = eye
    return world_from_cam


def render_floor(
    width: int, height: int, K: np.ndarray, world_from_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast the checkerboard floor. Returns rgb (H, W, 3) uint8, depth_m (H, W) float32
    (0 where a ray misses the floor) and the floor cell parity (H, W) int (-1 = sky)."""
    fx, fy, cx, cy = K
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)  # pixel centres
    dirs_cam = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)], axis=-1)  # (H, W, 3)
    dirs_world = dirs_cam @ world_from_cam[:3, :3].T
    eye = world_from_cam[:3, 3]
    dz = dirs_world[..., 2]
    hits = dz < -1e-6
    t = np.where(hits, -eye[2] / np.where(hits, dz, -1.0), 0.0)  # = depth along +z (dirs_cam z = 1)
    points = eye + t[..., None] * dirs_world
    cell = np.floor(points[..., :2] / CHECKER_SIZE_M).astype(np.int64)
    parity = np.where(hits, (cell[..., 0] + cell[..., 1]) % 2, -1)
    quadrant = (points[..., 0] > 0).astype(np.int64) + 2 * (points[..., 1] > 0)
    palette = np.array([[200, 60, 60], [60, 160, 60], [60, 90, 200], [210, 180, 60]], np.float64)
    base = palette[quadrant] * np.where(parity == 1, 1.0, 0.45)[..., None]
    shade = np.clip(1.0 - 0.04 * t, 0.4, 1.0)[..., None]  # darker with distance
    sky = np.array([150.0, 190.0, 235.0]) * (0.7 + 0.3 * (rows / height))[..., None]
    rgb = np.where(hits[..., None], base * shade, sky)
    depth_m = np.where(hits, t, 0.0).astype(np.float32)
    return np.clip(rgb, 0, 255).astype(np.uint8), depth_m, parity


def synthetic_frame(
    seq: int,
    n_frames: int = 60,
    width: int = 160,
    height: int = 120,
    *,
    with_ov: bool = True,
    rgb_encoding: str = "rgb8",
) -> Frame:
    """Frame ``seq`` of a camera path once around the origin (radius 3 m, 1.5 m high), moving
    slowly near the start and end of the loop and fast in the middle."""
    phase = seq / max(n_frames, 1)
    angle = 2.0 * math.pi * (phase - math.sin(2.0 * math.pi * phase) / (2.0 * math.pi))
    eye = np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 1.5])
    world_from_cam = look_at(eye, np.array([0.0, 0.0, 0.3]))
    K = np.array([0.9 * width, 0.9 * width, width / 2.0, height / 2.0])
    rgb, depth_m, parity = render_floor(width, height, K, world_from_cam)
    ov = ov_space = None
    if with_ov:
        # A tiny stand-in for an OV feature map at 1/8 resolution: one-hot of (sky, dark, light).
        small = parity[4::8, 4::8]
        ov = np.zeros((*small.shape, DEMO_OV_DIM), np.float16)
        ov[..., 0] = small == -1
        ov[..., 1] = small == 0
        ov[..., 2] = small == 1
        ov_space = DEMO_OV_SPACE
    return Frame(
        seq=seq,
        stamp_ns=1_000_000_000 + seq * 100_000_000,  # 10 Hz
        width=width,
        height=height,
        K=K,
        world_from_cam=world_from_cam,
        rgb=rgb,
        depth_m=depth_m,
        ov=ov,
        ov_space=ov_space,
        rgb_encoding=rgb_encoding,
    )


def synthetic_frames(
    n_frames: int = 60, width: int = 160, height: int = 120, **kwargs: object
) -> Iterator[Frame]:
    for seq in range(n_frames):
        yield synthetic_frame(seq, n_frames, width, height, **kwargs)  # type: ignore[arg-type]


def write_synthetic_recording(
    path: str | Path, n_frames: int = 60, width: int = 160, height: int = 120, *, with_ov: bool = True
) -> Path:
    """Write ``n_frames`` synthetic frames to a ``.govrec`` file; returns its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"generator": "clients.demo", "scene": "checkerboard floor", "frames": n_frames}
    with RecordingWriter(path, meta) as writer:
        for frame in synthetic_frames(n_frames, width, height, with_ov=with_ov):
            writer.write(frame)
    return path


# ---------------------------------------------------------------------------------------------
# a node in a subprocess


def free_endpoints(count: int = 3) -> list[str]:
    """``count`` distinct ``tcp://127.0.0.1:PORT`` endpoints on currently free ports."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [f"tcp://127.0.0.1:{s.getsockname()[1]}" for s in sockets]
    finally:
        for s in sockets:
            s.close()


class NodeProcess:
    """``govnesf serve`` in a subprocess on free loopback ports; a context manager that always
    kills the process on exit. ``wait_ready()`` polls ``status`` until the node answers."""

    def __init__(
        self,
        map_dir: str | Path,
        *,
        log_path: str | Path | None = None,
        extra_args: Sequence[str] = (),
        events: bool = True,
    ) -> None:
        self.ingest, self.query, events_ep = free_endpoints(3)
        self.events: str | None = events_ep if events else None
        self.map_dir = Path(map_dir)
        self.log_path = Path(log_path) if log_path else None
        self.command = [
            sys.executable, "-m", "clients.cli", "serve",
            "--ingest", self.ingest, "--query", self.query, "--events", self.events or "",
            "--map-dir", str(self.map_dir), *extra_args,
        ]  # fmt: skip
        self.process: subprocess.Popen[bytes] | None = None
        self._log_file: object = None

    def start(self) -> NodeProcess:
        """Spawn the process (once; a second call does nothing)."""
        if self.process is not None:
            return self
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
        env.setdefault("HF_HUB_OFFLINE", "1")
        out = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL  # noqa: SIM115
        self._log_file = out
        self.process = subprocess.Popen(self.command, cwd=REPO_ROOT, env=env, stdout=out, stderr=out)
        return self

    def wait_ready(self, timeout_s: float = 20.0) -> None:
        """Block until the node answers ``status``; raise RuntimeError if it exits or times out."""
        deadline = time.monotonic() + timeout_s
        with MapperClient(ingest=self.ingest, query=self.query, timeout_s=0.25, retries=0) as client:
            while time.monotonic() < deadline:
                if self.process is not None and self.process.poll() is not None:
                    raise RuntimeError(
                        f"node exited with code {self.process.returncode} during start-up{self._log_hint()}"
                    )
                try:
                    client.status()
                    return
                except TimeoutError:
                    continue
        raise RuntimeError(f"node did not answer status within {timeout_s:g} s{self._log_hint()}")

    def _log_hint(self) -> str:
        return f" (log: {self.log_path})" if self.log_path else ""

    def client(self, **kwargs: object) -> MapperClient:
        """A client connected to this node."""
        return MapperClient(ingest=self.ingest, query=self.query, **kwargs)  # type: ignore[arg-type]

    def signal(self, signum: int = signal.SIGINT, timeout_s: float = 15.0) -> int:
        """Send ``signum`` and wait for the exit code."""
        assert self.process is not None
        self.process.send_signal(signum)
        return self.process.wait(timeout=timeout_s)

    def kill(self) -> None:
        """Make sure the process is gone (kills it if still running)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)
        if self._log_file not in (None, subprocess.DEVNULL):
            self._log_file.close()  # type: ignore[attr-defined]
            self._log_file = None

    def __enter__(self) -> NodeProcess:
        if self.process is None:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.kill()


# ---------------------------------------------------------------------------------------------
# the simulated robot and ground truth (shared with tests/e2e and benchmarks)

DEMO_SEED = 3
"""Scene seed of the demo: an apartment room with two chairs at a table, a bed, a kitchen run."""


def sim_stream(
    seed: int = DEMO_SEED, frames: int = 240, width: int = 160, height: int = 120, *, depth: bool = True,
    ov: bool = True, style: str = "apartment",
) -> Any:
    """A ``clients.sim.export.SimStream`` (scene, renderer, robot poses, SimLSeg); its
    ``frames()`` yields ``(Frame, RenderedView)`` lazily."""
    from clients.sim.export import RecordConfig, SimStream

    return SimStream.build(RecordConfig(seed=seed, style=style, frames=frames, width=width, height=height,
                                        depth=depth, ov=ov, novel_views=0, previews=0))


def chair_distance(centroid: np.ndarray, scene: Any, class_name: str = "chair") -> float:
    """Distance (m) from ``centroid`` (3,) to the nearest ground-truth instance centroid of a class
    (inf when the scene has none)."""
    dists = [float(np.linalg.norm(np.asarray(centroid) - inst.centroid))
             for inst in scene.instances if inst.class_name == class_name]
    return min(dists, default=math.inf)


def mean_iou(pred: np.ndarray, gt: np.ndarray, n_classes: int) -> tuple[float, dict[int, float]]:
    """Mean IoU over the classes present in ``gt`` (N,) ints; ``pred`` (N,) -1 (unlabelled) counts
    as wrong. Returns (mIoU, {class: IoU})."""
    valid_pred = (pred >= 0) & (pred < n_classes)
    inter = np.bincount(gt[valid_pred & (pred == gt)], minlength=n_classes)
    gt_count = np.bincount(gt, minlength=n_classes)
    pred_count = np.bincount(pred[valid_pred], minlength=n_classes)
    union = gt_count + pred_count - inter
    present = np.flatnonzero(gt_count > 0)
    ious = {int(c): float(inter[c] / union[c]) for c in present}
    return (float(np.mean(list(ious.values()))) if ious else 0.0), ious


def label_by_nearest(query_xyz: np.ndarray, map_xyz: np.ndarray, map_label: np.ndarray,
                     max_dist_m: float) -> np.ndarray:
    """(N,) label of the nearest map point within ``max_dist_m``, else -1."""
    from scipy.spatial import cKDTree

    out = np.full(query_xyz.shape[0], -1, np.int64)
    if map_xyz.shape[0] == 0:
        return out
    dist, idx = cKDTree(map_xyz).query(query_xyz, distance_upper_bound=max_dist_m)
    hit = np.isfinite(dist)
    out[hit] = map_label[idx[hit]]
    return out


# ---------------------------------------------------------------------------------------------
# the demo

DEMO_QUERIES = (("find the chair", "chair"), ("a place to sleep", "sleep"), ("where is the table", "table"))
N_STEPS = 6


def _step(n: int, text: str) -> None:
    print(f"\n[demo {n}/{N_STEPS}] {text}", flush=True)


def _open_rerun(path: str | None, name: str) -> AbstractContextManager[Any]:
    """A :class:`clients.rerun_log.RerunLog` on ``path`` (closed on exit), or ``None`` without one."""
    if path is None:
        return nullcontext(None)
    from clients.rerun_log import RerunLog

    return RerunLog(path, recording_name=name)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clients.demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO_ROOT / "out" / "demo"), help="output directory")
    parser.add_argument("--seed", type=int, default=DEMO_SEED, help=f"scene seed (default {DEMO_SEED})")
    parser.add_argument("--frames", type=int, default=240, help="frames the robot streams (default 240)")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--window", type=int, default=160, help="node window.max_keyframes (default 160)")
    parser.add_argument("--gt-points-per-m2", type=float, default=150.0,
                        help="density of the ground-truth surface samples for the mIoU (default 150)")
    parser.add_argument("--rerun", metavar="FILE.rrd", default=None,
                        help="also log the streamed frames, the map, the queries and the render for the "
                             "Rerun viewer (off by default)")
    parser.add_argument("--rerun-every", type=int, default=1, metavar="N",
                        help="with --rerun: log every Nth streamed frame (default 1: all)")
    args = parser.parse_args(argv)
    if args.rerun_every < 1:
        parser.error(f"--rerun-every {args.rerun_every} must be >= 1")
    if args.rerun:  # a bad path is an error before any work
        from clients.rerun_log import RerunLogError, check_rrd_path

        try:
            check_rrd_path(args.rerun)
        except RerunLogError as exc:
            parser.error(str(exc))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()

    from tqdm import tqdm

    from clients.cli.query import format_objects, objects_as_json, write_points_ply
    from clients.sim.export import count_views, write_ply
    from clients.sim.scenes import CLASS_NAMES, LABEL_OF
    from protocol.messages import Error

    _step(1, f"generating the room (apartment, seed {args.seed}) and the robot's path ({args.frames} frames)")
    stream = sim_stream(args.seed, args.frames, args.width, args.height)
    scene = stream.scene
    names = sorted({i.class_name for i in scene.instances})
    chairs = [i for i in scene.instances if i.class_name == "chair"]
    size = scene.room_max - scene.room_min
    print(f"  room {size[0]:.1f} x {size[1]:.1f} x {size[2]:.1f} m, {len(scene.instances)} objects: "
          + ", ".join(names))
    print("  chairs at " + "; ".join(", ".join(f"{v:.2f}" for v in c.centroid) for c in chairs))
    write_ply(out / "scene.ply", scene)
    n_gt = max(1, int(args.gt_points_per_m2 * float(
        scene.face_areas()[scene.face_label != LABEL_OF["ceiling"]].sum())))
    gt_xyz, gt_label, _ = scene.sample_surface(n_gt, seed=args.seed, exclude_labels=(LABEL_OF["ceiling"],))
    gt_views = np.zeros(n_gt, np.int32)

    _step(2, "starting `govnesf serve` on free loopback ports")
    node = NodeProcess(
        out / "maps", log_path=out / "node.log",
        extra_args=["--set", f"window.max_keyframes={args.window}", "--set", "autosave_name=demo",
                    "--set", "load_autosave_on_start=false"],
    )  # fmt: skip
    failures: list[str] = []
    # the node: started here and killed on the way out whatever happens; the .rrd: closed (complete)
    with node, _open_rerun(args.rerun, f"govnesf demo seed {args.seed}") as rlog:
        node.wait_ready()
        print(f"  pid {node.process.pid if node.process else '?'}; ingest {node.ingest}, query {node.query}")
        print(f"  node log: {node.log_path}")

        _step(3, f"streaming {args.frames} frames ({args.width}x{args.height}, rgb + depth + SimLSeg ov)")
        statuses: dict[str, int] = {}

        def frames() -> Iterator[Frame]:
            for k, (frame, view) in enumerate(stream.frames()):
                count_views(gt_xyz, stream.K, stream.poses[k], view.depth_m, gt_views)
                if rlog is not None and k % args.rerun_every == 0:
                    rlog.log_frame(frame)
                yield frame

        t_stream = time.monotonic()
        with node.client(timeout_s=60.0) as client:
            results = client.send_frames(frames(), window=4)
            for res in tqdm(results, total=args.frames, desc="  stream", unit="frame"):
                key = f"error:{res.reply.code}" if isinstance(res.reply, Error) else res.reply.status
                statuses[key] = statuses.get(key, 0) + 1
            dt = time.monotonic() - t_stream
            print(f"  {args.frames} frames in {dt:.1f} s ({args.frames / max(dt, 1e-9):.1f} Hz): "
                  + ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())))
            if any(k.startswith("error") for k in statuses):
                failures.append("some frames got errors")
            status = client.status()
            extra = status.extra
            print(f"  map: {extra.get('global_points')} points ({extra.get('global_points_with_features')} "
                  f"with features), {status.keyframes} keyframes in the window, map data "
                  f"{status.memory_bytes / 1e6:.0f} MB, node RSS "
                  f"{(extra.get('rss_bytes') or 0) / 1e6:.0f} MB, "
                  f"integrate {extra.get('global_integrate_ms_mean')} ms per keyframe")

            _step(4, "queries")
            answers = {}
            for text, stem in DEMO_QUERIES:
                points = client.query_points([text], timeout_s=120.0)
                answers[stem] = points
                total_ms = points.timing_ms.get("total", 0.0)
                print(f'\n  "{text}": {points.xyz.shape[0]} points, {total_ms:.0f} ms on the node')
                print("  " + format_objects(points, limit=3).replace("\n", "\n  "))
                write_points_ply(out / f"{stem}.ply", points.xyz, points.score)
                (out / f"{stem}.json").write_text(json.dumps(objects_as_json(points), indent=1) + "\n")
                print(f"  wrote {out / f'{stem}.ply'} and {out / f'{stem}.json'}")
                if rlog is not None:
                    rlog.log_query(points, [text], entity=f"world/queries/{stem}")
            chair_objects = answers["chair"].objects
            if not chair_objects:
                failures.append('"find the chair" returned no object')
                print("\n  chair check: FAILED (no object)")
            else:
                top = chair_objects[0]
                dist = chair_distance(top.centroid, scene)
                ok = dist <= 0.5
                print(f"\n  chair check: top object at ({', '.join(f'{v:.2f}' for v in top.centroid)}) is "
                      f"{dist:.2f} m from the nearest real chair -> "
                      f"{'CORRECT' if ok else 'WRONG'} (<= 0.5 m)")
                if not ok:
                    failures.append(f"top chair object is {dist:.2f} m from a real chair")

            _step(5, "3D semantic segmentation against ground truth (mIoU)")
            seen = gt_views > 0
            xyz, gt = gt_xyz[seen], gt_label[seen].astype(np.int64)
            texts = list(CLASS_NAMES)
            print(f"  {int(seen.sum())} of {n_gt} ground-truth surface points seen by the stream, "
                  f"{len(texts)} class names as texts")
            report: dict[str, Any] = {"gt_points": int(seen.sum()), "classes": texts}
            methods = [("govnesf", False), ("govnesf", True), ("average_depth", False), ("average", False)]
            if "govnesf" not in extra.get("segment_methods", []):
                print("  (the node serves no learned model: govnesf rows skipped; see the node log)")
                methods = methods[2:]
            for method_name, use_depth in methods:
                method = method_name + ("+DGM" if use_depth else "")
                seg = client.segment_points(
                    xyz, texts, method=method_name, use_depth=use_depth, timeout_s=600.0
                )
                pred = seg.label.astype(np.int64)
                covered = pred >= 0
                miou, _ = mean_iou(pred, gt, len(texts))
                miou_cov, _ = mean_iou(pred[covered], gt[covered], len(texts))
                print(f"  segment_points {method:<13}: mIoU {100 * miou:5.1f}% (points seen by the window: "
                      f"{100 * covered.mean():.0f}%, mIoU on those {100 * miou_cov:5.1f}%), "
                      f"{seg.timing_ms.get('total', 0):.0f} ms")
                report[method] = {"miou": miou, "miou_covered": miou_cov, "coverage": float(covered.mean()),
                                  "timing_ms": dict(seg.timing_ms)}
            full = client.query_points(texts, negatives=[], max_points=10_000_000, objects=False,
                                       timeout_s=300.0)
            if rlog is not None:
                rlog.log_map(full, texts)
            pred = label_by_nearest(xyz, full.xyz, full.label.astype(np.int64), 0.1)
            miou, ious = mean_iou(pred, gt, len(texts))
            print(f"  global map (fused features, nearest map point <= 0.1 m): mIoU {100 * miou:5.1f}%")
            worst = sorted(ious.items(), key=lambda kv: kv[1])[:3]
            print("  hardest classes: " + ", ".join(f"{texts[c]} {100 * v:.0f}%" for c, v in worst))
            report["global_map"] = {"miou": miou, "per_class": {texts[c]: v for c, v in ious.items()}}
            (out / "segmentation.json").write_text(json.dumps(report, indent=1) + "\n")

            if "render" in extra.get("serving", []):
                from clients.cli.render import compose_panels

                pose = stream.poses[args.frames // 3]
                render_texts = ["chair", "table", "wall", "floor", "sofa", "bed"]
                result = client.render(args.width, args.height, stream.K, pose, ["rgb", "depth", "label"],
                                       render_texts, timeout_s=600.0)
                from PIL import Image

                panels = compose_panels(result, render_texts, scale=2)
                Image.fromarray(panels["combined"]).save(out / "render.png")
                if rlog is not None:
                    rlog.log_render(result, stream.K, pose, render_texts)
                print(f"  rendered a novel view (colour, depth, semantics): {out / 'render.png'} "
                      f"in {result.timing_ms.get('handler', 0):.0f} ms on the node")

            _step(6, "save the map, then stop the node with SIGINT")
            ok_msg = client.save("demo")
            print(f"  {ok_msg.message}")
        code = node.signal(signal.SIGINT)
        print(f"  node exited with code {code}")
        if code != 0:
            failures.append(f"node exit code {code} (see {node.log_path})")
    if args.rerun:
        print(f"\nwrote {args.rerun} (view it with: rerun {args.rerun})")
    elapsed = time.monotonic() - started
    if failures:
        print(f"\ndemo FAILED after {elapsed:.0f} s: " + "; ".join(failures), file=sys.stderr)
        return 1
    print(f"\ndemo finished in {elapsed:.0f} s: the chair was found; outputs in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
