"""Answers from the whole map: ``segment_points`` mIoU with a bounded window against an unbounded one.

For each recorded sim scene (``scripts/make_eval_data.sh`` writes ``data/val/<scene>/frames.govrec``
and ``gt/points.npz``), the node (in-process, the real ``MapperNode`` with the learned plugin, no
sockets) ingests the recorded frames (the wire bytes, through ``handle_ingest``) and is asked
``segment_points`` for the scene's ground-truth points with the scene's class names as texts, per
method (``average``, ``average_depth``, ``govnesf``). Runs:

* ``unbounded``: a window that holds every keyframe;
* ``bounded``: a window of ceil(keyframes / 3) keyframes (the stream has 3x more keyframes than
  the window), answered from the window and the global map, ``average_depth`` with the views of the
  keyframes that left (``queries.evicted_views = "depth"``; the node's default is ``"off"``);
* ``bounded, evicted views for both methods``: ``queries.evicted_views = "both"`` (``average`` too);
* ``bounded, no evicted views``: ``queries.evicted_views = "off"`` (the node's default);
* ``bounded, window only``: the same with ``queries.map_radius_voxels = 0`` (no map answers);
* ``bounded`` / ``unbounded, more confident (before the blend)``: ``queries.map_blend = 0``, the
  rule before it: where both answer, the map's text only where its cosine is higher
  (``map_when_more_confident = true``);
* ``bounded, no learned map features``: ``global_map.learned_features = false``; with ``, evicted
  views for both`` / ``, no evicted views`` also ``queries.evicted_views = "both"`` / ``"off"``;
* ``bounded, learned features at every eviction`` (``, no evicted views``):
  ``global_map.learned_features_once = false``, the rule before 2026-12-05 (a voxel mixed with the
  model's blend each time a keyframe that saw it leaves).

Every other run uses the shipped ``[queries]`` (``map_radius_voxels = 2.5``, ``map_blend = 0.75``);
the unbounded run too, so the comparison is like for like. (The "window first" rows
of docs/concepts/window-and-map.md, the rule before 2026-12-03, came from this script's earlier
version: ``git log``.)

Also the global map's own mIoU (each ground-truth point labelled by the nearest map point's fused
feature within the lookup radius) with and without the learned features written before eviction.
The learned features are applied synchronously after each frame (``process_pending``), as the
worker thread does when it keeps up.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/studies/bench_whole_map.py data/val/apartment_s1000 \\
        --out out/bench/whole_map

Writes ``<out>.json`` and ``<out>.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

METHODS = ("average", "average_depth", "govnesf")


def _frames(scene: Path) -> list[bytes]:
    from protocol.recording import read_recording

    return list(read_recording(scene / "frames.govrec"))


def _count_keyframes(frames: list[bytes]) -> int:
    from mapper.map.window import Keyframe, KeyframeWindow
    from mapper.node.config import WindowConfig
    from protocol.messages import Frame, decode

    window = KeyframeWindow(WindowConfig(max_keyframes=100_000))
    n = 0
    for data in frames:
        f = decode(data, direction="request")
        assert isinstance(f, Frame)
        kf = Keyframe(
            seq=f.seq, stamp_ns=f.stamp_ns, camera=f.camera, K=f.K, world_from_cam=f.world_from_cam, rgb=f.rgb
        )
        n += int(window.consider(kf).added)
    return n


def _node(
    tmp: Path, max_keyframes: int, *, radius_voxels: float, learned: bool, more_confident: bool, blend: float,
    evicted: str = "depth", learned_once: bool = True,
) -> tuple[Any, Any, Any]:
    """(node, its map-features worker or None, the model runtime) for one run."""
    from mapper.node.backends.learned import install_learned_backend
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from mapper.runtime.model_runtime import ModelRuntime

    config = config_from_dict(
        {
            "map_dir": str(tmp),
            "events_endpoint": "",
            "window": {"max_keyframes": max_keyframes},
            "global_map": {"rendered_depth": False, "learned_features": learned,
                           "learned_features_once": learned_once},
            "queries": {"map_radius_voxels": radius_voxels, "map_when_more_confident": more_confident,
                        "map_blend": blend, "evicted_views": evicted},
        }
    )
    node = MapperNode(config)
    runtime = ModelRuntime(config.model)
    if runtime.load_error:
        raise SystemExit(f"no model: {runtime.load_error}")
    install_learned_backend(node, runtime)
    provider = node.ctx.status_providers.get("map_features")
    blender = getattr(provider, "__self__", None)
    return node, blender, runtime


def _run(frames: list[bytes], node: Any, blender: Any) -> float:
    from protocol.messages import decode

    started = time.perf_counter()
    for data in frames:
        reply = decode(node.handle_ingest(data), direction="reply")
        if getattr(reply, "code", None):
            raise SystemExit(f"ingest error: {reply}")
        if blender is not None:
            blender.process_pending()
        if node.ctx.evicted_views is not None:
            node.ctx.evicted_views.process_pending()
    return time.perf_counter() - started


def _segment(
    node: Any, xyz: np.ndarray, texts: list[str], method: str
) -> tuple[np.ndarray, np.ndarray, float]:
    from protocol.messages import Segmentation, SegmentPoints, decode, encode

    started = time.perf_counter()
    reply = decode(
        node.handle_query(encode(SegmentPoints(xyz=xyz, texts=texts, method=method))),  # type: ignore[arg-type]
        direction="reply",
    )
    if not isinstance(reply, Segmentation):
        raise SystemExit(f"segment_points {method}: {reply}")
    source = reply.source if reply.source is not None else np.ones(xyz.shape[0], np.uint8)
    return reply.label.astype(np.int64), source, time.perf_counter() - started


def _map_miou(node: Any, xyz: np.ndarray, gt: np.ndarray, texts: list[str]) -> float:
    from clients.harness import mean_iou

    snap = node.state.global_map.snapshot()
    emb = node.ctx.text_encoder("bench").encode(texts)
    rows = snap.nearest_with_feature(xyz, node.ctx.map_radius_m)
    pred = np.full(xyz.shape[0], -1, np.int64)
    hit = rows >= 0
    feats = snap.feat[rows[hit]].astype(np.float32)
    pred[hit] = np.argmax(feats @ emb.T, axis=1)
    return mean_iou(pred, gt, len(texts))[0]


def _render_miou(node: Any, scene: Path, texts: list[str], n_views: int) -> tuple[float, float]:
    """2D mIoU (%) of ``render`` labels at the scene's first ``n_views`` novel views against their
    ground-truth labels (pixels with a label), and the share of labelled pixels the map answered."""
    from clients.harness import mean_iou
    from protocol.messages import Render, RenderResult, decode, encode

    views = np.load(scene / "gt" / "novel_views.npz")
    preds, gts, from_map = [], [], []
    for i in range(min(n_views, views["label"].shape[0])):
        h, w = views["label"].shape[1:]
        msg = Render(width=w, height=h, K=views["K"][i], world_from_cam=views["world_from_cam"][i],
                     outputs=["label"], texts=texts)  # fmt: skip
        reply = decode(node.handle_query(encode(msg)), direction="reply")
        if not isinstance(reply, RenderResult) or reply.label is None:
            raise SystemExit(f"render: {reply}")
        ok = views["label"][i] >= 0
        preds.append(reply.label[ok].astype(np.int64))
        gts.append(views["label"][i][ok].astype(np.int64))
        if reply.source is not None:
            from_map.append(reply.source[ok] == 2)
    miou = mean_iou(np.concatenate(preds), np.concatenate(gts), len(texts))[0]
    share = float(np.concatenate(from_map).mean()) if from_map else 0.0
    return round(100 * miou, 2), round(100 * share, 1)


def bench_scene(
    scene: Path, tmp: Path, render_views: int = 0, only: list[str] | None = None
) -> dict[str, Any]:
    from clients.harness import mean_iou
    from mapper.node.config import QueryConfig

    frames = _frames(scene)
    gt = np.load(scene / "gt" / "points.npz")
    xyz, gt_label = gt["xyz"].astype(np.float32), gt["label"].astype(np.int64)
    texts = json.loads((scene / "gt" / "class_names.json").read_text())
    n_kf = _count_keyframes(frames)
    bounded = max(1, math.ceil(n_kf / 3))
    shipped = QueryConfig()
    radius, confident, blend = shipped.map_radius_voxels, shipped.map_when_more_confident, shipped.map_blend
    runs = {  # max keyframes, map radius (voxels), learned map features ("once" per voxel,
        # "every" eviction, "" none), map when more confident, blend,
        # the evicted keyframes' views (queries.evicted_views)
        "unbounded": (10_000, radius, "once", confident, blend, "depth"),
        "bounded": (bounded, radius, "once", confident, blend, "depth"),
        "bounded, evicted views for both methods": (bounded, radius, "once", confident, blend, "both"),
        "bounded, no evicted views": (bounded, radius, "once", confident, blend, "off"),
        "bounded, window only": (bounded, 0.0, "once", False, 0.0, "off"),
        "bounded, more confident (before the blend)": (bounded, radius, "once", True, 0.0, "depth"),
        "unbounded, more confident (before the blend)": (10_000, radius, "once", True, 0.0, "depth"),
        "bounded, no learned map features": (bounded, radius, "", confident, blend, "depth"),
        "bounded, no learned map features, evicted views for both": (
            bounded, radius, "", confident, blend, "both"),
        "bounded, no learned map features, no evicted views": (
            bounded, radius, "", confident, blend, "off"),
        "bounded, learned features at every eviction": (bounded, radius, "every", confident, blend, "depth"),
        "bounded, learned features at every eviction, no evicted views": (
            bounded, radius, "every", confident, blend, "off"),
    }
    if only:
        unknown = sorted(set(only) - set(runs))
        if unknown:
            raise SystemExit(f"--runs: unknown {unknown}; known: {sorted(runs)}")
        runs = {k: v for k, v in runs.items() if k in only}
    out: dict[str, Any] = {
        "scene": scene.name,
        "frames": len(frames),
        "keyframes": n_kf,
        "window": bounded,
        "gt_points": int(xyz.shape[0]),
        "runs": {},
    }
    for name, (max_kf, radius_voxels, learned, more_confident, map_blend, evicted) in runs.items():
        node, blender, _ = _node(
            tmp, max_kf, radius_voxels=radius_voxels, learned=bool(learned), more_confident=more_confident,
            blend=map_blend, evicted=evicted, learned_once=learned != "every",
        )
        ingest_s = _run(frames, node, blender)
        row: dict[str, Any] = {"max_keyframes": max_kf, "ingest_s": round(ingest_s, 2)}
        for method in METHODS:
            label, source, seconds = _segment(node, xyz, texts, method)
            row[method] = {
                "miou": round(100 * mean_iou(label, gt_label, len(texts))[0], 2),
                "from_window": int(np.count_nonzero(source == 1)),
                "from_map": int(np.count_nonzero(source == 2)),
                "none": int(np.count_nonzero(source == 0)),
                "seconds": round(seconds, 2),
            }
        if render_views > 0:
            row["render_miou"], row["render_from_map_pct"] = _render_miou(node, scene, texts, render_views)
        if radius_voxels > 0:
            row["global_map_miou"] = round(100 * _map_miou(node, xyz, gt_label, texts), 2)
        row["map_features"] = (
            node.ctx.status_providers["map_features"]()
            if "map_features" in node.ctx.status_providers else None
        )
        node.stop()
        out["runs"][name] = row
        print(
            f"{scene.name} {name}: "
            + ", ".join(f"{m} {row[m]['miou']}" for m in METHODS)
            + (f", map {row.get('global_map_miou')}" if "global_map_miou" in row else "")
            + (f", render {row['render_miou']} ({row['render_from_map_pct']}% from map)"
               if "render_miou" in row else ""),
            flush=True,
        )
    return out


def to_markdown(results: list[dict[str, Any]]) -> str:
    lines = [
        "| scene (keyframes / window) | run | average | average_depth | govnesf | global map alone "
        "| render labels, 2D (from map) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for name, row in r["runs"].items():
            cells = [f"{row[m]['miou']:.1f} ({row[m]['from_map']} from map)" for m in METHODS]
            gm = row.get("global_map_miou")
            rend = (f"{row['render_miou']:.1f} ({row['render_from_map_pct']:.0f}%)"
                    if "render_miou" in row else "-")
            lines.append(
                f"| {r['scene']} ({r['keyframes']} / {r['window']}) | {name} | "
                + " | ".join(cells)
                + f" | {'-' if gm is None else f'{gm:.1f}'} | {rend} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench" / "whole_map")
    parser.add_argument("--render-views", type=int, default=0,
                        help="also render this many of the scene's novel views (gt/novel_views.npz) per run "
                             "and report the 2D mIoU of the render labels (0 = none)")
    parser.add_argument("--runs", default="",
                        help="';'-separated run names to do (default: every run), e.g. 'unbounded;bounded'")
    args = parser.parse_args(argv)
    only = [r.strip() for r in args.runs.split(";") if r.strip()] or None
    import tempfile

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            if not (scene / "frames.govrec").is_file():
                print(f"{scene}: no frames.govrec (make it with scripts/make_eval_data.sh)", file=sys.stderr)
                return 2
            results.append(bench_scene(scene, Path(tmp), render_views=args.render_views, only=only))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=1))
    args.out.with_suffix(".md").write_text(to_markdown(results))
    print(to_markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
