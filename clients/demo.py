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
   map's own labels (``query_points`` with every class name), each as mIoU; then a view is
   rendered (``render.png``: colour, depth, labels; its PSNR and depth error against the
   simulator's image of the pose are printed);
6. save the map, stop the node with SIGINT and check that it exited cleanly (exit code 0);
7. RGB-only (skip with ``--no-rgb-only``): the same robot WITHOUT a depth camera (rgb, pose and
   SimLSeg features) streams into a fresh node; once its background workers (points triangulated
   from the posed RGB and plane-sweep stereo depths, ``mapper/node/workers/triangulation.py``, and
   rendered depth) are idle,
   "find the chair" must again lie within 0.5 m of a real chair, ``segment_points`` mIoU (the
   four methods of step 5; the depth test takes the requested points as occluders) is printed,
   and the view of step 5 is rendered again
   (``rgb_only/render.png``; PSNR and depth error printed; docs/concepts/rgb-only.md).

Outputs under ``out/demo/`` (override with ``--out``): ``*.ply`` / ``*.json`` per query,
``segmentation.json``, ``scene.ply`` (the ground-truth mesh), the node log and the map directory.
``--rerun FILE.rrd`` (off by default) also logs the streamed frames, the queries, the map's labels
and the render for the Rerun viewer (``clients/rerun_log.py``; ``--rerun-every N`` thins frames).
The demo exits non-zero if the chair answer is wrong or the node misbehaves.

The room, the node process and the scoring come from ``clients/harness.py``, which the end-to-end
tests and benchmarks share.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.client import MapperClient
from clients.harness import (
    DEMO_SEED,
    REPO_ROOT,
    NodeProcess,
    chair_distance,
    label_by_nearest,
    mean_iou,
    sim_stream,
)
from govnesf._extras import MissingExtraError, require
from protocol.messages import Error, Frame

DEMO_QUERIES = (("find the chair", "chair"), ("a place to sleep", "sleep"), ("where is the table", "table"))
N_STEPS = 7


def _send_all(client: MapperClient, frames: Iterable[Frame], n_frames: int) -> bool:
    """Send ``frames`` (4 in flight) with a progress bar, print the replies by kind; True if any
    frame got an error reply."""
    from tqdm import tqdm

    statuses: dict[str, int] = {}
    t_stream = time.monotonic()
    for res in tqdm(client.send_frames(frames, window=4), total=n_frames, desc="  stream", unit="frame"):
        key = f"error:{res.reply.code}" if isinstance(res.reply, Error) else res.reply.status
        statuses[key] = statuses.get(key, 0) + 1
    dt = time.monotonic() - t_stream
    print(f"  {n_frames} frames in {dt:.1f} s ({n_frames / max(dt, 1e-9):.1f} Hz): "
          + ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())))
    return any(k.startswith("error") for k in statuses)

def _step(n: int, text: str) -> None:
    print(f"\n[demo {n}/{N_STEPS}] {text}", flush=True)


def _open_rerun(path: str | None, name: str, connect: str | None = None) -> AbstractContextManager[Any]:
    """A :class:`clients.rerun_log.RerunLog` on ``path`` and/or the live viewer at ``connect``
    (closed on exit), or ``None`` without either."""
    if path is None and connect is None:
        return nullcontext(None)
    from clients.rerun_log import RerunLog

    return RerunLog(path, connect=connect, recording_name=name)


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The demo's options; a bad ``--rerun-every`` or ``--rerun`` path exits 2 before any work."""
    parser = argparse.ArgumentParser(prog="python -m clients.demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO_ROOT / "out" / "demo"), help="output directory")
    parser.add_argument("--seed", type=int, default=DEMO_SEED, help=f"scene seed (default {DEMO_SEED})")
    parser.add_argument("--frames", type=int, default=240, help="frames the robot streams (default 240)")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--window", type=int, default=160, help="node window.max_keyframes (default 160)")
    parser.add_argument("--set", dest="node_set", action="append", default=[], metavar="KEY=VALUE",
                        help="node config override passed to both nodes, as `govnesf serve --set` "
                             "(repeatable), e.g. --set model.checkpoint=out/train/x/export.safetensors")
    parser.add_argument("--gt-points-per-m2", type=float, default=150.0,
                        help="density of the ground-truth surface samples for the mIoU (default 150)")
    parser.add_argument("--rerun", metavar="FILE.rrd", default=None,
                        help="also log the streamed frames, the map, the queries and the render for the "
                             "Rerun viewer (off by default)")
    parser.add_argument("--no-rgb-only", dest="rgb_only", action="store_false",
                        help="skip step 7 (the RGB-only pass without depth)")
    parser.add_argument("--rerun-every", type=int, default=1, metavar="N",
                        help="with --rerun: log every Nth streamed frame (default 1: all)")
    from clients.rerun_log import CONNECT_HELP  # no rerun import: only the help text

    parser.add_argument("--rerun-connect", metavar="ADDR", default=None, help=CONNECT_HELP)
    args = parser.parse_args(argv)
    if args.rerun_every < 1:
        parser.error(f"--rerun-every {args.rerun_every} must be >= 1")
    if args.node_set:  # a bad key or value is an error before any work, as `govnesf serve` says it
        check = subprocess.run(
            [sys.executable, "-m", "mapper.node.cli", "--check-config", *_node_sets(args)],
            capture_output=True, text=True, cwd=REPO_ROOT, check=False,
        )  # fmt: skip
        if check.returncode != 0:
            parser.error(check.stderr.strip().removeprefix("govnesf serve: ") or "invalid --set")
    if args.rerun or args.rerun_connect:  # a bad path / no viewer is an error before any work
        from clients.rerun_log import RerunLogError, check_rerun_outputs

        try:
            check_rerun_outputs(args.rerun, args.rerun_connect)
        except RerunLogError as exc:
            parser.error(str(exc))
    return args


@dataclass
class _Room:
    """Step 1's output: the simulated stream and the ground-truth surface samples of its scene."""

    stream: Any
    """``clients.sim.export.SimStream``."""
    gt_xyz: np.ndarray
    gt_label: np.ndarray
    gt_views: np.ndarray
    """(N,) how many streamed views saw each sample (counted while streaming)."""

    @property
    def scene(self) -> Any:
        return self.stream.scene


def _generate_room(args: argparse.Namespace, out: Path) -> _Room:
    """Step 1: the room, the robot's path, ``scene.ply`` and the ground-truth surface samples."""
    from clients.sim.export import write_ply
    from clients.sim.scenes import LABEL_OF

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
    return _Room(stream, gt_xyz, gt_label, np.zeros(n_gt, np.int32))


def _node_sets(args: argparse.Namespace) -> list[str]:
    """``--set KEY=VALUE`` pairs for the node from the demo's own ``--set`` options."""
    return [arg for kv in args.node_set for arg in ("--set", kv)]


def _node_process(args: argparse.Namespace, out: Path) -> NodeProcess:
    """Step 2 (before start-up): the node, its map directory and log under ``out``."""
    _step(2, "starting `govnesf serve` on free loopback ports")
    return NodeProcess(
        out / "maps", log_path=out / "node.log",
        extra_args=["--set", f"window.max_keyframes={args.window}", "--set", "autosave_name=demo",
                    "--set", "load_autosave_on_start=false", *_node_sets(args)],
    )  # fmt: skip


def _wait_for_node(node: NodeProcess) -> None:
    """Step 2 (after start-up): wait until the node answers, print where it listens."""
    node.wait_ready()
    print(f"  pid {node.process.pid if node.process else '?'}; ingest {node.ingest}, query {node.query}")
    print(f"  node log: {node.log_path}")


def _robot_frames(room: _Room, rlog: Any, rerun_every: int) -> Iterator[Frame]:
    """The robot's frames, counting which ground-truth samples each view sees (and logging them)."""
    from clients.sim.export import count_views

    stream = room.stream
    for k, (frame, view) in enumerate(stream.frames()):
        count_views(room.gt_xyz, stream.K, stream.poses[k], view.depth_m, room.gt_views)
        if rlog is not None and k % rerun_every == 0:
            rlog.log_frame(frame)
        yield frame


def _stream(client: MapperClient, args: argparse.Namespace, room: _Room, rlog: Any,
            failures: list[str]) -> dict[str, Any]:
    """Step 3: stream the frames with a progress bar; returns the node's ``status.extra`` after."""
    _step(3, f"streaming {args.frames} frames ({args.width}x{args.height}, rgb + depth + SimLSeg ov)")
    if _send_all(client, _robot_frames(room, rlog, args.rerun_every), args.frames):
        failures.append("some frames got errors")
    status = client.status()
    extra = status.extra
    print(f"  map: {extra.get('global_points')} points ({extra.get('global_points_with_features')} "
          f"with features), {status.keyframes} keyframes in the window, map data "
          f"{status.memory_bytes / 1e6:.0f} MB, node RSS "
          f"{(extra.get('rss_bytes') or 0) / 1e6:.0f} MB, "
          f"integrate {extra.get('global_integrate_ms_mean')} ms per keyframe")
    return extra


def _queries(client: MapperClient, out: Path, scene: Any, rlog: Any, failures: list[str]) -> None:
    """Step 4: the three queries (printed, written as PLY + JSON), then the chair check."""
    from clients.cli.query import format_objects, objects_as_json, write_points_ply

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
        return
    top = chair_objects[0]
    dist = chair_distance(top.centroid, scene)
    ok = dist <= 0.5
    print(f"\n  chair check: top object at ({', '.join(f'{v:.2f}' for v in top.centroid)}) is "
          f"{dist:.2f} m from the nearest real chair -> "
          f"{'CORRECT' if ok else 'WRONG'} (<= 0.5 m)")
    if not ok:
        failures.append(f"top chair object is {dist:.2f} m from a real chair")


def _segment_points(client: MapperClient, xyz: np.ndarray, gt: np.ndarray, texts: list[str],
                    extra: dict[str, Any], report: dict[str, Any]) -> None:
    """Step 5, first part: ``segment_points`` with each method at the seen samples (mIoU). In step
    7 (no depth anywhere) the depth test of ``govnesf+DGM`` and ``average_depth`` takes the
    requested points as occluders (``model.point_occlusion``,
    ``queries.point_occlusion``; docs/concepts/rgb-only.md)."""
    methods = [("govnesf", False), ("govnesf", True), ("average_depth", False), ("average", False)]
    if "govnesf" not in extra.get("segment_methods", []):
        print("  (the node serves no learned model: govnesf rows skipped; see the node log)")
        methods = [m for m in methods if m[0] != "govnesf"]
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


def _global_map_labels(client: MapperClient, xyz: np.ndarray, gt: np.ndarray, texts: list[str],
                       rlog: Any, report: dict[str, Any]) -> None:
    """Step 5, second part: the global map's own labels (nearest map point) at the seen samples."""
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


def _segmentation(client: MapperClient, out: Path, room: _Room, extra: dict[str, Any], rlog: Any) -> None:
    """Step 5: 3D semantic segmentation of the seen ground-truth samples; ``segmentation.json``."""
    from clients.sim.scenes import CLASS_NAMES

    _step(5, "3D semantic segmentation against ground truth (mIoU)")
    seen = room.gt_views > 0
    xyz, gt = room.gt_xyz[seen], room.gt_label[seen].astype(np.int64)
    texts = list(CLASS_NAMES)
    print(f"  {int(seen.sum())} of {room.gt_views.size} ground-truth surface points seen by the stream, "
          f"{len(texts)} class names as texts")
    report: dict[str, Any] = {"gt_points": int(seen.sum()), "classes": texts}
    _segment_points(client, xyz, gt, texts, extra, report)
    _global_map_labels(client, xyz, gt, texts, rlog, report)
    (out / "segmentation.json").write_text(json.dumps(report, indent=1) + "\n")


def _render_view(client: MapperClient, args: argparse.Namespace, out: Path, room: _Room,
                 extra: dict[str, Any], rlog: Any) -> None:
    """End of steps 5 and 7, when the node serves ``render``: a view as ``OUT/render.png``, with
    its PSNR and depth error against the simulator's image of the same pose."""
    if "render" not in extra.get("serving", []):
        return
    from clients.cli.render import compose_panels

    stream = room.stream
    pose = stream.poses[args.frames // 3]
    render_texts = ["chair", "table", "wall", "floor", "sofa", "bed"]
    result = client.render(args.width, args.height, stream.K, pose, ["rgb", "depth", "label"],
                           render_texts, timeout_s=600.0)
    from PIL import Image

    panels = compose_panels(result, render_texts, scale=2)
    Image.fromarray(panels["combined"]).save(out / "render.png")
    if rlog is not None:
        rlog.log_render(result, stream.K, pose, render_texts)
    truth = stream.renderer.render(stream.K, pose, args.width, args.height)  # the simulator's view
    quality = ""
    if result.rgb is not None and result.depth_m is not None:
        mse = float(np.mean((result.rgb.astype(np.float64) - truth.rgb.astype(np.float64)) ** 2)) / 255.0**2
        both = (truth.depth_m > 0) & (result.depth_m > 0)
        rel = np.abs(result.depth_m[both] - truth.depth_m[both]) / truth.depth_m[both]
        depth_err = 100 * float(np.median(rel)) if both.any() else float("nan")
        quality = (f"; PSNR {10 * np.log10(1 / max(mse, 1e-12)):.1f} dB, depth median error "
                   f"{depth_err:.1f}% against the simulator's view; "
                   f"{int(result.timing_ms.get('surface_pixels', 0))} of {args.width * args.height} pixels "
                   "rendered at measured surfaces")
    print(f"  rendered a novel view (colour, depth, semantics): {out / 'render.png'} "
          f"in {result.timing_ms.get('handler', 0):.0f} ms on the node{quality}")


def _wait_for_workers(client: MapperClient, timeout_s: float = 900.0) -> dict[str, Any]:
    """Poll ``status`` until the triangulation and rendered-depth workers have nothing pending."""
    deadline = time.monotonic() + timeout_s
    while True:
        extra = client.status().extra
        workers = ("triangulation", "rendered_depth")
        pending = sum(int((extra.get(k) or {}).get("pending", 0)) for k in workers)
        if pending == 0 or time.monotonic() > deadline:
            return extra
        time.sleep(1.0)


def _rgb_only_pass(args: argparse.Namespace, out: Path, room: _Room, failures: list[str]) -> None:
    """Step 7: the same room and path without depth into a fresh node; chair check and mIoU."""
    from clients.sim.scenes import CLASS_NAMES

    _step(7, "RGB-only: the same robot WITHOUT a depth camera (rgb + pose + SimLSeg ov), a fresh node")
    rgb_out = out / "rgb_only"
    rgb_out.mkdir(parents=True, exist_ok=True)
    stream = sim_stream(args.seed, args.frames, args.width, args.height, depth=False)
    node = NodeProcess(
        rgb_out / "maps", log_path=rgb_out / "node.log",
        extra_args=["--set", f"window.max_keyframes={args.window}", "--set", "autosave_name=demo-rgb-only",
                    "--set", "load_autosave_on_start=false", *_node_sets(args)],
    )  # fmt: skip
    with node:
        node.wait_ready()
        with node.client(timeout_s=60.0) as client:
            if _send_all(client, (frame for frame, _ in stream.frames()), args.frames):
                failures.append("RGB-only: some frames got errors")
            t_wait = time.monotonic()
            extra = _wait_for_workers(client)
            tri = extra.get("triangulation") or {}
            print(f"  background workers idle after {time.monotonic() - t_wait:.0f} s more; triangulated "
                  f"{tri.get('keyframes', 0)} keyframes: {tri.get('points_per_keyframe', 0)} points and "
                  f"{tri.get('mean_ms', 0)} ms per keyframe (off the ack path), {tri.get('points', 0)} "
                  f"points kept, {tri.get('global_map_points', 0)} into the global map")
            stereo = tri.get("stereo") or {}
            if stereo.get("keyframes"):
                print(f"  plane-sweep stereo: {stereo['keyframes']} keyframes, "
                      f"{stereo['depths_per_keyframe']} depths kept per keyframe, "
                      f"{stereo['mean_ms']} ms per keyframe, {stereo['global_map_points']} into the map")
            bounds = (extra.get("model") or {}).get("bounds")
            if bounds:
                print(f"  cost volume bounds: {bounds}")
            chair = client.query_points(["find the chair"], timeout_s=120.0)
            report: dict[str, Any] = {"triangulation": tri}
            if not chair.objects:
                failures.append('RGB-only: "find the chair" returned no object')
                print("  RGB-only chair check: FAILED (no object)")
            else:
                top = chair.objects[0]
                dist = chair_distance(top.centroid, room.scene)
                ok = dist <= 0.5
                report["chair_m"] = dist
                where = ", ".join(f"{v:.2f}" for v in top.centroid)
                print(f"  RGB-only chair check: top object at ({where}) is {dist:.2f} m from the nearest "
                      f"real chair -> {'CORRECT' if ok else 'WRONG'} (<= 0.5 m)")
                if not ok:
                    failures.append(f"RGB-only: top chair object is {dist:.2f} m from a real chair")
            seen = room.gt_views > 0  # the same poses as step 3: the same seen samples
            texts = list(CLASS_NAMES)
            _segment_points(client, room.gt_xyz[seen], room.gt_label[seen].astype(np.int64), texts,
                            extra, report)
            (rgb_out / "segmentation.json").write_text(json.dumps(report, indent=1) + "\n")
            _render_view(client, args, rgb_out, room, extra, None)
        code = node.signal(signal.SIGINT)
        print(f"  RGB-only node exited with code {code}")
        if code != 0:
            failures.append(f"RGB-only node exit code {code} (see {node.log_path})")


def _stop_node(node: NodeProcess, failures: list[str]) -> None:
    """Step 6, after the save: SIGINT, and the node must exit with code 0."""
    code = node.signal(signal.SIGINT)
    print(f"  node exited with code {code}")
    if code != 0:
        failures.append(f"node exit code {code} (see {node.log_path})")


def _finish(args: argparse.Namespace, out: Path, started: float, failures: list[str]) -> int:
    """The closing lines; the exit code (1 when any check failed)."""
    if args.rerun:
        print(f"\nwrote {args.rerun} (view it with: rerun {args.rerun})")
    elapsed = time.monotonic() - started
    if failures:
        print(f"\ndemo FAILED after {elapsed:.0f} s: " + "; ".join(failures), file=sys.stderr)
        return 1
    print(f"\ndemo finished in {elapsed:.0f} s: the chair was found; outputs in {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    try:  # before anything is written: the simulated room needs the [sim] extra
        from clients.sim.raycast import raycast_backend, torch_device

        require("trimesh", "sim", "the demo's room mesh (scene.ply)")
        backend = raycast_backend()  # open3d where installed, else torch (GOVNESF_SIM_RAYCAST)
        if backend == "torch":
            print(f"demo: the simulator ray casts with torch on {torch_device()} (GOVNESF_SIM_RAYCAST; "
                  "Open3D, where installed, is the default)")
    except (MissingExtraError, ValueError) as exc:
        print(f"demo: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    room = _generate_room(args, out)
    node = _node_process(args, out)
    failures: list[str] = []
    # the node: started here and killed on the way out whatever happens; the .rrd: closed (complete)
    with node, _open_rerun(args.rerun, f"govnesf demo seed {args.seed}", args.rerun_connect) as rlog:
        _wait_for_node(node)
        with node.client(timeout_s=60.0) as client:
            extra = _stream(client, args, room, rlog, failures)
            _queries(client, out, room.scene, rlog, failures)
            _segmentation(client, out, room, extra, rlog)
            _render_view(client, args, out, room, extra, rlog)
            _step(6, "save the map, then stop the node with SIGINT")
            ok_msg = client.save("demo")
            print(f"  {ok_msg.message}")
        _stop_node(node, failures)
    if args.rgb_only:
        _rgb_only_pass(args, out, room, failures)
    return _finish(args, out, started, failures)


if __name__ == "__main__":
    raise SystemExit(main())
