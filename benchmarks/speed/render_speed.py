"""Render and segment latency of the learned runtime, dense sampling vs empty-space skipping.

A simulated robot (``clients.sim``, SimLSeg OV features, depth) streams keyframes into a
``KeyframeWindow`` followed by a :class:`mapper.runtime.model_runtime.ModelRuntime`; then:

* ``sync``: the first query applies the window changes (encode each keyframe once, add it to the
  cost volume) -- timed separately, as is the per-version 3D U-Net + occupancy grid;
* ``render``: a held-out view (between two stream poses) at ``--width x --height``, dense
  (every sample on the rays' [near, far] within the volume box) and with empty-space skipping;
  reports latency, evaluated samples, and the difference between the two outputs;
* ``segment``: ``--points`` surface points (back-projected keyframe depth) with method govnesf;
* ``--map-surface``: the keyframes also go into a global map (as the node fuses frames with
  depth), and the view is rendered at the map's surfaces (``model.surface_from_map``, what the
  node's ``render`` does: :func:`mapper.node.queries.map_surface_depth`, then
  ``ModelRuntime.render(surface_depth_m=...)``), timed with the splat.

Every render also reports its PSNR against the simulator's image, its depth's median relative
error and its labels' accuracy against the simulator's (pixels whose class is one of the texts).

Run (2-core CPU: a few minutes with a trained checkpoint)::

    HF_HUB_OFFLINE=1 .venv/bin/python benchmarks/speed/render_speed.py --checkpoint checkpoints/cpu-small

``--random-init`` uses an untrained ``cpu-small`` model (mechanics only: its density is nearly
uniform, so skipping finds little empty space).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.sim.export import RecordConfig, SimStream  # noqa: E402
from clients.sim.scenes import CLASS_NAMES  # noqa: E402
from mapper.map.global_map import GlobalSemanticMap  # noqa: E402
from mapper.map.window import Keyframe, KeyframeWindow  # noqa: E402
from mapper.model.config import get_preset  # noqa: E402
from mapper.model.field import GovNeSF  # noqa: E402
from mapper.node.config import GlobalMapConfig, WindowConfig  # noqa: E402
from mapper.node.queries import map_surface_depth  # noqa: E402
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig, RenderFrame  # noqa: E402
from mapper.training.metrics import depth_errors  # noqa: E402

TEXTS = ["chair", "table", "sofa", "bed", "wall", "floor"]


def _interpolated_pose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A pose half-way between two (translation averaged, rotation of a re-orthonormalised mean)."""
    pose = np.eye(4)
    pose[:3, 3] = 0.5 * (a[:3, 3] + b[:3, 3])
    u, _, vt = np.linalg.svd(0.5 * (a[:3, :3] + b[:3, :3]))
    pose[:3, :3] = u @ vt
    return pose


LEVERS = ("occupancy_threshold", "min_weight", "stop_transmittance", "termination_block", "appearance_groups")


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"--sizes: expected WIDTHxHEIGHT, got {text!r}") from None
    return w, h


def parse_variant(text: str, base: ModelRuntimeConfig) -> dict[str, object]:
    """``key=value,key=value`` -> runtime config overrides (typed like the field's default)."""
    out: dict[str, object] = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        if not hasattr(base, key) or not value:
            raise SystemExit(f"--variants: {item!r} is not KEY=VALUE with KEY a [model] setting")
        kind = type(getattr(base, key))
        out[key] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return out


def load_reference(path: Path, K: np.ndarray, pose: np.ndarray) -> RenderFrame | None:
    """A dense render saved by an earlier run for the same camera (None: missing or another view)."""
    if not path.exists():
        return None
    z = np.load(path)
    if not (np.allclose(z["K"], K) and np.allclose(z["pose"], pose)):
        return None
    return RenderFrame(
        rgb=z["rgb"], depth_m=z["depth"], label=z["label"], score=z["score"], opacity=z["opacity"],
        timing_ms={"total": 1e3 * float(z["seconds"])}, stats={"from": str(path)},
    )  # fmt: skip


def psnr(rgb: np.ndarray, truth: np.ndarray) -> float:
    """PSNR (dB) of two uint8 images."""
    mse = float(np.mean((rgb.astype(np.float64) / 255.0 - truth.astype(np.float64) / 255.0) ** 2))
    return 10.0 * float(np.log10(1.0 / max(mse, 1e-12)))


def compare(dense: RenderFrame, frame: RenderFrame) -> dict[str, object]:
    """How far a fast render is from the dense one."""
    assert dense.rgb is not None and frame.rgb is not None
    assert dense.depth_m is not None and frame.depth_m is not None
    assert dense.label is not None and frame.label is not None
    assert dense.score is not None and frame.score is not None
    drawn = (dense.depth_m > 0) & (frame.depth_m > 0)
    rgb_diff = np.abs(dense.rgb.astype(int) - frame.rgb.astype(int))
    depth_diff = np.abs(dense.depth_m - frame.depth_m)[drawn]
    return {
        "rgb_max_abs_of_255": int(rgb_diff.max()),
        "rgb_mean_abs_of_255": round(float(rgb_diff.mean()), 3),
        "psnr_vs_dense_db": round(psnr(frame.rgb, dense.rgb), 2),
        "depth_mean_abs_m": round(float(depth_diff.mean()), 4) if drawn.any() else None,
        "depth_median_abs_m": round(float(np.median(depth_diff)), 4) if drawn.any() else None,
        "score_max_abs": round(float(np.abs(dense.score - frame.score).max()), 4),
        "label_agreement": round(float((dense.label == frame.label).mean()), 4),
    }


def against_dense(dense: RenderFrame, frame: RenderFrame, run: dict[str, Any], entry: dict[str, Any],
                  ms: float) -> dict[str, object]:  # fmt: skip
    """A fast ``run`` (its ``frame``, ``ms``) against the dense render of the same view (``entry``)."""
    return {
        "vs_dense": compare(dense, frame),
        "psnr_delta_db": round(float(run["psnr_db"]) - float(entry["dense_psnr_db"]), 3),
        "speedup": round(float(entry["dense_ms"]) / ms, 2),
    }


def against_truth(frame: RenderFrame, view: Any) -> dict[str, object]:
    """A render against the simulator's view: depth median relative error (where both have depth)
    and label accuracy (pixels whose class is one of TEXTS)."""
    out: dict[str, object] = {}
    if frame.depth_m is not None:
        errors = depth_errors(frame.depth_m, view.depth_m)
        out["depth_median_rel_err"] = round(errors.median_rel, 4) if errors.num_compared else None
        out["depth_cover"] = round(errors.coverage, 4)
    if frame.label is not None:
        truth = np.full(view.label.shape, -1)
        for i, text in enumerate(TEXTS):
            if text in CLASS_NAMES:
                truth[view.label == CLASS_NAMES.index(text)] = i
        scored = truth >= 0
        accuracy = float((frame.label == truth)[scored].mean()) if scored.any() else None
        out["label_accuracy"] = None if accuracy is None else round(accuracy, 4)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default="checkpoints/cpu-small.safetensors")
    p.add_argument("--random-init", action="store_true", help="untrained cpu-small model instead")
    p.add_argument("--seed", type=int, default=3, help="scene seed")
    p.add_argument("--frames", type=int, default=60, help="stream frames (keyframes are selected)")
    p.add_argument("--window", type=int, default=16, help="max keyframes")
    p.add_argument("--sizes", nargs="+", default=["160x120"], metavar="WxH", help="render sizes")
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--skip-dense", action="store_true", help="do not time the dense render")
    p.add_argument(
        "--thresholds", nargs="+", type=float, default=None, metavar="SIGMA",
        help="occupancy thresholds (1/m) to time skipping with (default: the runtime's)",
    )  # fmt: skip
    p.add_argument("--min-weight", type=float, default=None, help="appearance pruning weight (runtime's)")
    p.add_argument(
        "--variants", nargs="+", default=None, metavar="KEY=VALUE[,KEY=VALUE]",
        help="[model] overrides for the fast path, each timed and compared with dense "
        "(e.g. appearance_groups=2,stop_transmittance=0.01); replaces --thresholds",
    )  # fmt: skip
    p.add_argument("--repeat", type=int, default=1, help="time each render this often, keep the fastest")
    p.add_argument(
        "--reference-dir", default=None, metavar="DIR",
        help="keep the dense renders in DIR/dense_WxH.npz and reuse them in later runs of the same "
        "view (a dense 320x240 render takes minutes on 2 cores)",
    )  # fmt: skip
    p.add_argument(
        "--segment-reference", action="store_true",
        help="also run segment_points with batched_view_groups flipped and report the label agreement",
    )  # fmt: skip
    p.add_argument(
        "--map-surface", action="store_true",
        help="also render at the surfaces of a global map of the keyframes (model.surface_from_map)",
    )  # fmt: skip
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--json", metavar="FILE", help="also write the numbers as JSON")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    if args.random_init:
        torch.manual_seed(0)
        runtime = ModelRuntime(
            ModelRuntimeConfig(device="cpu"), model=GovNeSF(get_preset("cpu-small", ov_dim=384))
        )
        model_name = "cpu-small (random init)"
    else:
        runtime = ModelRuntime(ModelRuntimeConfig(checkpoint=args.checkpoint, device="cpu"))
        if not runtime.ready:
            print(runtime.load_error, file=sys.stderr)
            return 1
        model_name = f"{args.checkpoint} (step {runtime.metadata.get('step', '?')})"
    print(f"model: {model_name}; torch threads {torch.get_num_threads()}", flush=True)

    t0 = time.perf_counter()
    stream = SimStream.build(
        RecordConfig(
            seed=args.seed, frames=args.frames, width=160, height=120, depth=True, ov=True, novel_views=0
        )
    )
    window = KeyframeWindow(
        WindowConfig(max_keyframes=args.window, min_translation_m=0.15, min_rotation_deg=12)
    )
    runtime.attach(window)
    surface: list[np.ndarray] = []
    global_map = GlobalSemanticMap(GlobalMapConfig()) if args.map_surface else None
    callback_s = 0.0
    for frame, _view in stream.frames():
        kf = Keyframe(
            seq=frame.seq, stamp_ns=frame.stamp_ns, camera="cam0", K=frame.K,
            world_from_cam=frame.world_from_cam, rgb=frame.rgb, depth_m=frame.depth_m, ov=frame.ov,
            ov_space=frame.ov_space,
        )  # fmt: skip
        c0 = time.perf_counter()
        update = window.consider(kf)
        callback_s += time.perf_counter() - c0
        if update.added and global_map is not None:
            global_map.integrate(kf)
        if update.added and frame.depth_m is not None:
            d = frame.depth_m
            rows, cols = np.nonzero(d > 0)
            z = d[rows, cols]
            fx, fy, cx, cy = frame.K
            cam = np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], axis=-1)
            surface.append(cam @ frame.world_from_cam[:3, :3].T + frame.world_from_cam[:3, 3])
    elapsed_s = time.perf_counter() - t0
    print(f"simulated {args.frames} frames -> {len(window)} keyframes in the window in {elapsed_s:.1f} s "
          f"(window callbacks {1e3 * callback_s:.1f} ms in total)", flush=True)  # fmt: skip

    results: dict[str, object] = {"model": model_name, "machine": platform.processor() or platform.machine()}
    t = time.perf_counter()
    runtime.sync()
    results["sync_ms"] = 1e3 * (time.perf_counter() - t)
    t = time.perf_counter()
    bounds, occupancy = runtime.occupancy()
    results["unet_and_occupancy_ms"] = 1e3 * (time.perf_counter() - t)
    results["bounds"] = {"dims": list(bounds.dims), "voxel_size_m": round(bounds.voxel_size_m, 3)}
    results["occupied_fraction"] = float(occupancy.float().mean())
    print(f"sync {results['sync_ms']:.0f} ms, U-Net + occupancy {results['unet_and_occupancy_ms']:.0f} ms, "
          f"volume {bounds.dims} x {bounds.voxel_size_m:.3f} m, "
          f"occupied {100 * float(results['occupied_fraction']):.1f}%", flush=True)  # type: ignore[arg-type]

    k = len(stream.poses) // 2
    pose = _interpolated_pose(stream.poses[k], stream.poses[k + 1])
    outputs = ["rgb", "depth", "label", "score"]
    base = runtime.config
    variants = [parse_variant(v, base) for v in args.variants] if args.variants else [
        {"occupancy_threshold": t, **({} if args.min_weight is None else {"min_weight": args.min_weight})}
        for t in (args.thresholds or [base.occupancy_threshold])
    ]  # fmt: skip
    renders: list[dict[str, object]] = []
    for size in args.sizes:
        width, height = parse_size(size)
        K = np.array([stream.K[0] * width / 160, stream.K[1] * height / 120, width / 2, height / 2])
        view = stream.renderer.render(K, pose, width, height)  # what the simulator sees from the view
        truth = view.rgb

        def render(
            skip: bool, K: np.ndarray = K, width: int = width, height: int = height
        ) -> tuple[RenderFrame, float]:
            best = float("inf")
            for _ in range(args.repeat):
                t, c = time.perf_counter(), time.process_time()
                frame = runtime.render(K, pose, width, height, outputs, TEXTS, empty_space_skipping=skip)
                wall = 1e3 * (time.perf_counter() - t)
                if wall < best:
                    best = wall
                    # CPU time of this process (all its threads): the load-independent measure
                    frame.stats["cpu_ms"] = round(1e3 * (time.process_time() - c), 1)
            return frame, best

        entry: dict[str, object] = {"width": width, "height": height}
        dense = None
        if not args.skip_dense:
            runtime.config = base
            cached = Path(args.reference_dir) / f"dense_{width}x{height}.npz" if args.reference_dir else None
            dense = load_reference(cached, K, pose) if cached is not None else None
            if dense is None:
                dense, dense_ms = render(False)
                if cached is not None:
                    cached.parent.mkdir(parents=True, exist_ok=True)
                    arrays = {"rgb": dense.rgb, "depth": dense.depth_m, "label": dense.label,
                              "score": dense.score, "opacity": dense.opacity}  # fmt: skip
                    kept: dict[str, Any] = {k: v for k, v in arrays.items() if v is not None}
                    np.savez(cached, seconds=dense_ms / 1e3, K=K, pose=pose, **kept)
            else:
                dense_ms = float(dense.timing_ms["total"])
                print(f"dense {width}x{height}: the reference render in {cached} (timed when it was made)")
            assert dense.rgb is not None
            entry.update(
                dense_ms=dense_ms, dense_stats=dense.stats, dense_psnr_db=round(psnr(dense.rgb, truth), 3),
                dense_vs_truth=against_truth(dense, view),
            )
            print(f"render {width}x{height} dense: {dense_ms / 1e3:.2f} s, PSNR {entry['dense_psnr_db']} dB, "
                  f"{dense.stats}", flush=True)  # fmt: skip
        runs = []
        for variant in variants:
            runtime.config = replace(base, **variant)
            occupied = float(runtime.occupancy()[1].float().mean())
            fast, ms = render(True)
            assert fast.rgb is not None
            run: dict[str, object] = {
                "config": {**variant, **{key: getattr(runtime.config, key) for key in LEVERS}},
                "occupied_fraction": round(occupied, 4), "render_ms": ms, "stats": fast.stats,
                "psnr_db": round(psnr(fast.rgb, truth), 3), "vs_truth": against_truth(fast, view),
            }  # fmt: skip
            if dense is not None:
                run.update(against_dense(dense, fast, run, entry, ms))
            runs.append(run)
            print(f"render {width}x{height} fast: {run}", flush=True)
        runtime.config = base
        if global_map is not None:
            snap = global_map.snapshot()
            best, frame = float("inf"), None
            for _ in range(args.repeat):
                t, c = time.perf_counter(), time.process_time()
                depth = map_surface_depth(snap, K, pose, width, height, base)
                out = runtime.render(K, pose, width, height, outputs, TEXTS, surface_depth_m=depth)
                wall = 1e3 * (time.perf_counter() - t)
                if wall < best:
                    best, frame = wall, out
                    out.stats["cpu_ms"] = round(1e3 * (time.process_time() - c), 1)
                    out.stats["map_pixels"] = int(np.count_nonzero(depth))
            assert frame is not None and frame.rgb is not None
            run = {
                "config": "map surface", "render_ms": best, "stats": frame.stats,
                "psnr_db": round(psnr(frame.rgb, truth), 3), "vs_truth": against_truth(frame, view),
            }  # fmt: skip
            if dense is not None:
                run.update(against_dense(dense, frame, run, entry, best))
            runs.append(run)
            print(f"render {width}x{height} map surface: {run}", flush=True)
        entry["fast"] = runs
        renders.append(entry)
    results["renders"] = renders

    pts = np.concatenate(surface)
    rng = np.random.default_rng(0)
    pts = pts[rng.choice(len(pts), size=min(args.points, len(pts)), replace=False)].astype(np.float32)
    for use_depth in (False, True):
        t, c = time.perf_counter(), time.process_time()
        label, _, timing = runtime.segment(pts, TEXTS, use_depth=use_depth)
        elapsed = time.perf_counter() - t
        timing["cpu"] = 1e3 * (time.process_time() - c)
        key = "segment_dgm_ms" if use_depth else "segment_ms"
        results[key] = 1e3 * elapsed
        results[key + "_per_100k_s"] = round(elapsed * 1e5 / len(pts), 3)
        results[key + "_stages"] = {k: round(v, 1) for k, v in timing.items()}
        print(f"segment {len(pts)} points (use_depth={use_depth}): {elapsed:.2f} s, labelled "
              f"{100 * (label >= 0).mean():.1f}%, stages {results[key + '_stages']}", flush=True)  # fmt: skip
        if not use_depth and args.segment_reference:
            runtime.config = replace(base, batched_view_groups=not base.batched_view_groups)
            ref = runtime.segment(pts, TEXTS)
            runtime.config = base
            results["segment_label_agreement"] = round(float((ref[0] == label).mean()), 5)
            agreement = 100 * float(results["segment_label_agreement"])  # type: ignore[arg-type]
            print(f"segment labels equal to the reference path: {agreement:.2f}%")
    results["points"] = len(pts)
    results["runtime"] = runtime.stats()
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
