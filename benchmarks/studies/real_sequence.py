"""Novel views of a REAL RGB-D sequence: the learned model's rgb and depth at held-out poses.

The sequence (default ``../shared/data/icl_livingroom1``: ICL-NUIM living room 1, Handa et al.
2014, CC BY 3.0; 211 frames 640x480, Open3D ``trajectory.log``) is read with the dataset importer
(``clients.importers.open_dataset("open3d", ...)``, poses rotated to the project's z-up world as
``govnesf import`` does). For every target frame t of a held-out set (every ``--every``-th frame,
at most ``--max-targets`` spread over the sequence):

* sources: the ``--sources`` frames nearest to t's pose (camera-centre distance +
  ``--rotation-weight`` metres per radian of relative rotation) among the frames more than
  ``--gap`` frames away from t, so neither t nor its immediate neighbours are seen;
* they enter a :class:`~mapper.map.window.KeyframeWindow` followed by a
  :class:`~mapper.runtime.model_runtime.ModelRuntime` -- the node's pipeline: full-size frames,
  resized by the runtime to the checkpoint's working size (cpu-small: 160x120), encoded, added
  to the incremental cost volume -- as RGB + pose only (no OV features, no depth; with
  ``--with-depth`` the sources carry their real depth, which the runtime uses for the volume
  bounds);
* the runtime renders rgb + depth at t's pose at the working size (K scaled with it); the real
  frame, resized the same way (colour bilinear + antialias, depth nearest, as the runtime resizes
  keyframes), is the reference.

Reported per target and pooled over the targets: the median / mean of |d_hat - d| / d over the
pixels with both a real and a rendered depth, the share within 10% / 25%, the coverage (pixels
with a real depth that got a rendered depth), PSNR of the colour over all pixels (black where
nothing is rendered) and over the rendered pixels only. References to read them by: the
render's depth error after one global median scale (shape without scale bias); a flat depth at
the real frame's own median (an oracle constant); the nearest source frame shown as it is (its
colour and its real depth, not reprojected: what a camera 2-20 cm away sees).

Run (cpu-small on an idle 2-core CPU: about 15 s of CPU per target RGB-only at ``--render-scale
0.5``, 4x that at full size, about twice that with ``--with-depth``)::

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/studies/real_sequence.py --max-targets 12 --render-scale 0.5
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/studies/real_sequence.py --max-targets 12 \\
        --render-scale 0.5 --with-depth

Writes ``out/bench/real_sequence.{json,md}`` (``real_sequence_with_depth.*`` with
``--with-depth``; ``--out STEM`` to choose). A missing data folder or checkpoint: one line on
stderr, exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from clients.importers import ImportedFrame, ImporterError, ReaderOptions, open_dataset  # noqa: E402
from clients.importers.base import scale_K  # noqa: E402
from mapper.errors import ConfigError  # noqa: E402
from mapper.map.window import Keyframe, KeyframeWindow  # noqa: E402
from mapper.node.config import WindowConfig  # noqa: E402
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig  # noqa: E402
from mapper.training.metrics import (  # noqa: E402
    DepthErrors,
    depth_errors,
    has_depth,
    masked_psnr,
    relative_depth_errors,
    summarize_depth_errors,
)

DEFAULT_DATA = REPO.parent / "shared" / "data" / "icl_livingroom1"
DEFAULT_OUT = REPO / "out" / "bench" / "real_sequence"
ICL_K = (525.0, 525.0, 319.5, 239.5)
"""ICL-NUIM 640x480 intrinsics, dataset convention (pixel centres at integers)."""


# ---- the sequence -------------------------------------------------------------------------------
@dataclass(frozen=True)
class PosedFrame:
    """One frame of the sequence in the project's conventions (z-up world, half-pixel K)."""

    index: int
    rgb: np.ndarray  # (H, W, 3) uint8
    depth_m: np.ndarray  # (H, W) float32 metres, 0 = none
    K: np.ndarray  # (4,) for rgb
    world_from_cam: np.ndarray  # (4, 4)
    stamp_ns: int


def load_sequence(
    path: Path, K: tuple[float, float, float, float]
) -> tuple[list[PosedFrame], dict[str, Any]]:
    """Every frame of an Open3D-layout sequence with its depth, and facts for the report.

    Poses are re-expressed in the project's world (``reader.world_from_dataset``, the default
    ``--up-axis`` of the format), exactly as ``govnesf import`` writes them.
    """
    reader = open_dataset("open3d", path, ReaderOptions(K=K, load_depth=True))
    frames = []
    skipped = 0
    for index, item in enumerate(reader.iter_frames(range(len(reader)))):
        if not isinstance(item, ImportedFrame) or item.depth_m is None:
            skipped += 1
            continue
        frames.append(
            PosedFrame(
                index=index,
                rgb=item.rgb,
                depth_m=item.depth_m,
                K=item.K,
                world_from_cam=reader.world_from_dataset @ item.world_from_cam,
                stamp_ns=item.stamp_ns,
            )
        )
    info = {
        "path": str(path),
        "frames": len(frames),
        "skipped": skipped,
        "size_wh": [int(frames[0].rgb.shape[1]), int(frames[0].rgb.shape[0])] if frames else None,
        "up_axis": reader.up_axis,
        "warnings": reader.warnings(),
        **reader.meta(),
    }
    return frames, info


# ---- which frames: targets and their sources ----------------------------------------------------
def held_out_targets(num_frames: int, every: int, max_targets: int) -> list[int]:
    """Positions 0, every, 2 * every, ... < num_frames; at most ``max_targets`` of them (0 = all),
    spread evenly over the candidates (first and last kept).

    >>> held_out_targets(211, 10, 0)[:3], len(held_out_targets(211, 10, 0))
    ([0, 10, 20], 22)
    >>> held_out_targets(211, 10, 4)
    [0, 70, 140, 210]
    """
    candidates = list(range(0, num_frames, max(1, every)))
    if max_targets <= 0 or max_targets >= len(candidates):
        return candidates
    picks = np.linspace(0, len(candidates) - 1, max_targets).round().astype(int)
    return [candidates[i] for i in np.unique(picks)]


def pose_distances(poses: np.ndarray, target: np.ndarray, rotation_weight_m: float) -> np.ndarray:
    """(N,) distance of each (N, 4, 4) pose to ``target`` (4, 4): camera-centre distance (m) +
    ``rotation_weight_m`` x the angle of the relative rotation (radians)."""
    translation = np.linalg.norm(poses[:, :3, 3] - target[:3, 3], axis=-1)
    relative = np.einsum("ji,njk->nik", target[:3, :3], poses[:, :3, :3])  # target^T @ pose
    cos_angle = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return translation + rotation_weight_m * np.arccos(cos_angle)


def select_sources(
    poses: np.ndarray, target: int, gap: int, count: int, rotation_weight_m: float
) -> list[int]:
    """The ``count`` positions nearest to ``poses[target]`` (:func:`pose_distances`) among those
    more than ``gap`` positions away from ``target``, in sequence order.

    >>> poses = np.repeat(np.eye(4)[None], 10, axis=0); poses[:, 0, 3] = np.arange(10) * 0.1
    >>> select_sources(poses, 5, gap=1, count=4, rotation_weight_m=0.5)
    [2, 3, 7, 8]
    """
    candidates = np.array([i for i in range(len(poses)) if abs(i - target) > gap], dtype=int)
    if candidates.size == 0:
        return []
    dist = pose_distances(poses[candidates], poses[target], rotation_weight_m)
    order = np.argsort(dist, kind="stable")[:count]
    return sorted(int(i) for i in candidates[order])


# ---- the reference at the working size ----------------------------------------------------------
def resize_rgb(rgb: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 -> (h, w, 3) uint8, bilinear with antialias when shrinking: the resize the
    runtime applies to a keyframe's colour."""
    width, height = size_wh
    h0, w0 = rgb.shape[:2]
    if (w0, h0) == (width, height):
        return rgb.copy()
    x = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float().div(255.0)[None]
    x = F.interpolate(
        x, size=(height, width), mode="bilinear", align_corners=False, antialias=w0 > width or h0 > height
    ).clamp(0.0, 1.0)
    return (x[0].permute(1, 2, 0) * 255.0 + 0.5).to(torch.uint8).numpy()


def resize_depth(depth_m: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """(H, W) -> (h, w) float32 by nearest-exact sampling (never mixes two surfaces): the resize the
    runtime applies to a keyframe's depth."""
    width, height = size_wh
    if depth_m.shape == (height, width):
        return depth_m.astype(np.float32, copy=True)
    d = torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32))[None, None]
    return F.interpolate(d, size=(height, width), mode="nearest-exact")[0, 0].numpy()


def render_size(working_wh: tuple[int, int], scale: float) -> tuple[int, int]:
    """(w, h) of the renders: the working size times ``scale`` (at least 1 pixel).

    >>> render_size((160, 120), 1.0), render_size((160, 120), 0.5)
    ((160, 120), (80, 60))
    """
    return max(1, round(working_wh[0] * scale)), max(1, round(working_wh[1] * scale))


# ---- one target ---------------------------------------------------------------------------------
def keyframe_of(frame: PosedFrame, with_depth: bool) -> Keyframe:
    """A window keyframe at the sequence's full size: RGB + pose (+ real depth with ``with_depth``),
    never OV features."""
    return Keyframe(
        seq=frame.index,
        stamp_ns=frame.stamp_ns,
        camera="cam0",
        K=frame.K,
        world_from_cam=frame.world_from_cam,
        rgb=frame.rgb,
        depth_m=frame.depth_m if with_depth else None,
    )


def median_scaled(pred_m: np.ndarray, ref_m: np.ndarray) -> np.ndarray:
    """``pred_m`` times median(ref / pred) over the pixels where both have a depth: what is left of
    the error once a global scale bias is removed (the shape of the depth, not its scale).

    >>> median_scaled(np.array([[1.0, 2.0, 0.0]]), np.array([[2.0, 4.0, 3.0]])).tolist()
    [[2.0, 4.0, 0.0]]
    """
    both = has_depth(pred_m) & has_depth(ref_m)
    if not both.any():
        return pred_m.copy()
    return pred_m * np.float32(np.median(ref_m[both] / pred_m[both]))


def flat_depth(ref_m: np.ndarray) -> np.ndarray:
    """A constant depth at the reference's own median (an oracle that knows nothing of the
    shape): the error any useful depth has to beat."""
    valid = has_depth(ref_m)
    return np.full_like(ref_m, np.median(ref_m[valid]) if valid.any() else 0.0)


def image_scores(
    rgb: np.ndarray, depth_m: np.ndarray, ref_rgb: np.ndarray, ref_depth_m: np.ndarray
) -> tuple[dict[str, float], np.ndarray, int]:
    """Scores of a predicted (rgb, depth) against the reference; also the relative depth errors
    and the reference-pixel count (for pooling over targets)."""
    rel, n_ref = relative_depth_errors(depth_m, ref_depth_m)
    errors = summarize_depth_errors(rel, n_ref)
    drawn = depth_m > 0
    scores = {
        **depth_fields(errors),
        "psnr_all_db": masked_psnr(rgb, ref_rgb, max_value=255.0),
        "psnr_rendered_db": masked_psnr(rgb, ref_rgb, drawn, max_value=255.0),
        "rendered_fraction": float(drawn.mean()),
        "depth_median_rel_median_scaled": depth_errors(
            median_scaled(depth_m, ref_depth_m), ref_depth_m
        ).median_rel,
        "flat_depth_median_rel": depth_errors(flat_depth(ref_depth_m), ref_depth_m).median_rel,
    }
    return scores, rel, n_ref


def depth_fields(errors: DepthErrors) -> dict[str, float]:
    return {
        "depth_median_rel": errors.median_rel,
        "depth_mean_rel": errors.mean_rel,
        "depth_within_10pct": errors.within_10pct,
        "depth_within_25pct": errors.within_25pct,
        "depth_coverage": errors.coverage,
    }


def evaluate_target(
    model_runtime: ModelRuntime,
    frames: list[PosedFrame],
    target: int,
    sources: list[int],
    args: argparse.Namespace,
) -> tuple[dict[str, Any], np.ndarray, int]:
    """Fresh window + runtime (sharing the loaded model), the sources streamed in, one render at
    the target pose, compared with the real frame. Returns (row, relative depth errors, ref pixels)."""
    assert model_runtime.model is not None
    runtime = ModelRuntime(model_runtime.config, model=model_runtime.model)
    window = KeyframeWindow(
        WindowConfig(max_keyframes=max(1, len(sources)), min_translation_m=0.0, min_rotation_deg=0.0)
    )
    runtime.attach(window)
    for i in sources:
        window.consider(keyframe_of(frames[i], args.with_depth))
    width, height = render_size(runtime.image_wh, args.render_scale)
    t0 = time.perf_counter()
    runtime.sync()
    sync_ms = 1e3 * (time.perf_counter() - t0)

    frame = frames[target]
    h0, w0 = frame.rgb.shape[:2]
    K = scale_K(frame.K, width / w0, height / h0)
    render = runtime.render(K, frame.world_from_cam, width, height, ["rgb", "depth"])
    assert render.rgb is not None and render.depth_m is not None
    ref_rgb = resize_rgb(frame.rgb, (width, height))
    ref_depth = resize_depth(frame.depth_m, (width, height))
    scores, rel, n_ref = image_scores(render.rgb, render.depth_m, ref_rgb, ref_depth)

    poses = np.stack([frames[i].world_from_cam for i in sources])
    dist = pose_distances(poses, frame.world_from_cam, args.rotation_weight)
    nearest = frames[sources[int(np.argmin(dist))]]
    copy_scores, _, _ = image_scores(
        resize_rgb(nearest.rgb, (width, height)),
        resize_depth(nearest.depth_m, (width, height)),
        ref_rgb,
        ref_depth,
    )
    centres = poses[:, :3, 3] - frame.world_from_cam[:3, 3]
    bounds = runtime.bounds
    row = {
        "target": frame.index,
        "sources": [frames[i].index for i in sources],
        "nearest_source": nearest.index,
        "source_distance_m": {
            "min": float(np.linalg.norm(centres, axis=-1).min()),
            "max": float(np.linalg.norm(centres, axis=-1).max()),
        },
        **scores,
        "nearest_copy": {k: copy_scores[k] for k in ("depth_median_rel", "psnr_all_db")},
        "sync_ms": sync_ms,
        "render_ms": render.timing_ms.get("total", float("nan")),
        "render_stats": render.stats,
        "bounds": None
        if bounds is None
        else {"dims": list(bounds.dims), "voxel_size_m": round(bounds.voxel_size_m, 4)},
    }
    if args.save_images:
        save_images(args.out_stem, frame.index, render.rgb, render.depth_m, ref_rgb, ref_depth)
    return row, rel, n_ref


def save_images(
    stem: Path, index: int, rgb: np.ndarray, depth_m: np.ndarray, ref_rgb: np.ndarray, ref_depth_m: np.ndarray
) -> None:
    """``STEM_images/NNNNN.png``: rendered | real colour above rendered | real depth (0-4 m grey)."""
    import cv2

    def grey(d: np.ndarray) -> np.ndarray:
        g = (np.clip(d / 4.0, 0.0, 1.0) * 255.0).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=-1)

    panel = np.concatenate(
        [np.concatenate([rgb, ref_rgb], axis=1), np.concatenate([grey(depth_m), grey(ref_depth_m)], axis=1)]
    )
    folder = stem.parent / f"{stem.name}_images"
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / f"{index:05d}.png"), panel[:, :, ::-1])


# ---- summary --------------------------------------------------------------------------------------
def mean_of(rows: list[dict[str, Any]], key: str) -> float:
    """Mean of a per-target number over the targets where it is finite (NaN if none)."""
    values = [float(r[key]) for r in rows if math.isfinite(float(r[key]))]
    return float(np.mean(values)) if values else float("nan")


MEAN_KEYS = (
    "depth_median_rel", "depth_mean_rel", "depth_coverage", "psnr_all_db", "psnr_rendered_db",
    "rendered_fraction", "depth_median_rel_median_scaled", "flat_depth_median_rel", "sync_ms", "render_ms",
)  # fmt: skip


def summarize(rows: list[dict[str, Any]], rel_parts: list[np.ndarray], n_ref: int) -> dict[str, Any]:
    """Pooled depth errors (all targets' pixels together) and per-target means."""
    pooled = summarize_depth_errors(np.concatenate(rel_parts) if rel_parts else np.zeros(0), n_ref)
    copy_rows = [r["nearest_copy"] for r in rows]
    return {
        "targets": len(rows),
        "pooled": {**depth_fields(pooled), "num_compared": pooled.num_compared, "num_reference": n_ref},
        "mean_over_targets": {k: mean_of(rows, k) for k in MEAN_KEYS},
        "nearest_copy_mean_over_targets": {
            k: mean_of(copy_rows, k) for k in ("depth_median_rel", "psnr_all_db")
        },
    }


def pct(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{100 * x:.1f}%"


def db(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{x:.2f}"


def markdown(report: dict[str, Any]) -> str:
    s, cfg = report["summary"], report["settings"]
    pooled, mean, copy = s["pooled"], s["mean_over_targets"], s["nearest_copy_mean_over_targets"]
    lines = [
        f"# Real sequence: {Path(report['data']['path']).name}, "
        f"{'RGB + depth' if cfg['with_depth'] else 'RGB only'} sources",
        "",
        f"- checkpoint `{report['checkpoint']['path']}` (step {report['checkpoint'].get('step')}), "
        f"working size {cfg['working_wh'][0]}x{cfg['working_wh'][1]}, renders and references at "
        f"{cfg['render_wh'][0]}x{cfg['render_wh'][1]}",
        f"- {s['targets']} targets (every {cfg['every']}th frame, at most {cfg['max_targets'] or 'all'}), "
        f"{cfg['sources']} sources each, nearest by pose outside +-{cfg['gap']} frames "
        f"(rotation weight {cfg['rotation_weight_m_per_rad']} m/rad); "
        f"source depth: {'real' if cfg['with_depth'] else 'none'}; no OV features",
        f"- runtime overrides: {' '.join(cfg['runtime_overrides']) or 'none'}",
        f"- wall {report['wall_s']:.0f} s on {report['machine']} ({report['torch_threads']} torch threads)",
        "",
        "| | depth median rel | depth mean rel | within 10% | within 25% | coverage | PSNR all (dB) "
        "| PSNR rendered (dB) |",
        "|---|---|---|---|---|---|---|---|",
        f"| pooled pixels | {pct(pooled['depth_median_rel'])} | {pct(pooled['depth_mean_rel'])} "
        f"| {pct(pooled['depth_within_10pct'])} | {pct(pooled['depth_within_25pct'])} "
        f"| {pct(pooled['depth_coverage'])} | - | - |",
        f"| mean over targets | {pct(mean['depth_median_rel'])} | {pct(mean['depth_mean_rel'])} | - | - "
        f"| {pct(mean['depth_coverage'])} | {db(mean['psnr_all_db'])} | {db(mean['psnr_rendered_db'])} |",
        f"| render after a global median scale (shape only) | {pct(mean['depth_median_rel_median_scaled'])} "
        "| - | - | - | - | - | - |",
        f"| flat depth at the real frame's median (oracle constant) | {pct(mean['flat_depth_median_rel'])} "
        "| - | - | - | - | - | - |",
        "| nearest source frame shown as is (its real depth, not reprojected) "
        f"| {pct(copy['depth_median_rel'])} "
        f"| - | - | - | - | {db(copy['psnr_all_db'])} | - |",
        "",
        "Depth rows: median of |d_hat - d| / d; the first two rows pool all pixels / average the per-target "
        "medians, the references are per-target means.",
        "",
        f"Mean per target: sync {mean['sync_ms']:.0f} ms, render {mean['render_ms']:.0f} ms.",
        "",
        "| target | sources | depth median rel | median-scaled | flat | coverage | PSNR all | PSNR rendered "
        "| nearest copy: depth rel / PSNR | render ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["targets"]:
        src = r["sources"]
        lines.append(
            f"| {r['target']} | {len(src)} ({src[0]}..{src[-1]}) | {pct(r['depth_median_rel'])} "
            f"| {pct(r['depth_median_rel_median_scaled'])} | {pct(r['flat_depth_median_rel'])} "
            f"| {pct(r['depth_coverage'])} | {db(r['psnr_all_db'])} | {db(r['psnr_rendered_db'])} "
            f"| {pct(r['nearest_copy']['depth_median_rel'])} / {db(r['nearest_copy']['psnr_all_db'])} "
            f"| {r['render_ms']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def json_safe(value: Any) -> Any:
    """NaN / inf -> None, recursively (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def runtime_config(checkpoint: str, device: str, overrides: list[str]) -> ModelRuntimeConfig:
    """The runtime settings with ``KEY=VALUE`` overrides of :class:`ModelRuntimeConfig` fields
    (typed like the field's default), validated; ValueError naming the bad item."""
    defaults = ModelRuntimeConfig(checkpoint=checkpoint, device=device)
    names = {f.name for f in dataclasses.fields(ModelRuntimeConfig)} - {"checkpoint", "device"}
    values: dict[str, Any] = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or key not in names:
            raise ValueError(f"--runtime {item!r}: expected KEY=VALUE with KEY one of {sorted(names)}")
        default = getattr(defaults, key)
        try:
            values[key] = (
                text.lower() in ("1", "true", "yes", "on")
                if isinstance(default, bool)
                else type(default)(text)
            )
        except ValueError:
            raise ValueError(f"--runtime {item!r}: {text!r} is not a {type(default).__name__}") from None
    config = dataclasses.replace(defaults, **values)
    try:
        config.validate("--runtime")
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    return config


# ---- main ---------------------------------------------------------------------------------------
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--checkpoint", default="checkpoints/cpu-small", help="NAME, NAME.json or NAME.safetensors"
    )
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="Open3D-layout sequence folder")
    p.add_argument(
        "--K",
        type=float,
        nargs=4,
        default=ICL_K,
        metavar=("FX", "FY", "CX", "CY"),
        help="intrinsics of the full-size frames, pixel centres at integers (ICL-NUIM default)",
    )
    p.add_argument("--every", type=int, default=10, help="every N-th frame is a target")
    p.add_argument("--gap", type=int, default=3, help="frames within +-GAP of a target are never sources")
    p.add_argument("--sources", type=int, default=12, help="source keyframes per target")
    p.add_argument(
        "--rotation-weight",
        type=float,
        default=0.5,
        help="metres per radian of rotation in the pose distance that ranks sources",
    )
    p.add_argument("--max-targets", type=int, default=0, help="at most N targets, spread evenly (0 = all)")
    p.add_argument(
        "--render-scale",
        type=float,
        default=1.0,
        help="render (and compare) at the working size times this (0.5: 4x fewer rays, for a slow CPU)",
    )
    p.add_argument("--with-depth", action="store_true", help="sources carry their real depth")
    p.add_argument("--device", default="cpu", help="torch device for the runtime (cpu, cuda, auto)")
    p.add_argument(
        "--runtime",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="ModelRuntimeConfig overrides, e.g. max_range_m=2.5 samples_per_ray=48",
    )
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output stem: STEM.json and STEM.md (default out/bench/real_sequence[_with_depth])",
    )
    p.add_argument("--save-images", action="store_true", help="also write STEM_images/NNNNN.png panels")
    args = p.parse_args(argv)  # fmt: skip
    for name, lo in (("every", 1), ("gap", 0), ("sources", 1), ("max_targets", 0), ("threads", 0)):
        if getattr(args, name) < lo:
            p.error(f"--{name.replace('_', '-')} must be >= {lo}, got {getattr(args, name)}")
    if not 0 < args.render_scale <= 4:
        p.error(f"--render-scale must be in (0, 4], got {args.render_scale}")
    if args.rotation_weight < 0:
        p.error(f"--rotation-weight must be >= 0, got {args.rotation_weight}")
    stem = args.out or DEFAULT_OUT.with_name(DEFAULT_OUT.name + ("_with_depth" if args.with_depth else ""))
    args.out_stem = stem.with_suffix("") if stem.suffix in (".json", ".md") else stem
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    name = Path(__file__).name
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        config = runtime_config(str(args.checkpoint), args.device, args.runtime)
    except ValueError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    if not args.data.is_dir():
        print(f"{name}: data folder {str(args.data)!r} does not exist (see ../shared/data/README.md)",
              file=sys.stderr)  # fmt: skip
        return 2
    runtime_log = logging.getLogger("mapper.runtime.model_runtime")
    level = runtime_log.level
    runtime_log.setLevel(logging.CRITICAL)  # a load error is printed below, once
    try:
        base = ModelRuntime(config)
    finally:
        runtime_log.setLevel(level)
    if not base.ready:
        print(f"{name}: {base.load_error}", file=sys.stderr)
        return 2
    started = time.perf_counter()
    try:
        frames, data_info = load_sequence(args.data, tuple(args.K))
    except ImporterError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    if len(frames) < 2:
        print(f"{name}: {args.data} holds {len(frames)} usable frames; need at least 2", file=sys.stderr)
        return 2
    poses = np.stack([f.world_from_cam for f in frames])
    width, height = base.image_wh
    targets = held_out_targets(len(frames), args.every, args.max_targets)
    mode = "RGB + real depth" if args.with_depth else "RGB only"
    print(f"{name}: {len(frames)} frames from {args.data} loaded in {time.perf_counter() - started:.1f} s; "
          f"{len(targets)} targets, {args.sources} sources each outside +-{args.gap}, {mode}; "
          f"checkpoint {args.checkpoint} (step {base.metadata.get('step', '?')}), "
          f"working size {width}x{height}, renders {render_size((width, height), args.render_scale)}, "
          f"torch threads {torch.get_num_threads()}", flush=True)  # fmt: skip

    rows: list[dict[str, Any]] = []
    rel_parts: list[np.ndarray] = []
    n_ref_total = 0
    for k, t in enumerate(targets):
        sources = select_sources(poses, t, args.gap, args.sources, args.rotation_weight)
        if not sources:
            print(
                f"[{k + 1}/{len(targets)}] frame {frames[t].index}: no source outside +-{args.gap}, skipped"
            )
            continue
        t0 = time.perf_counter()
        row, rel, n_ref = evaluate_target(base, frames, t, sources, args)
        rows.append(row)
        rel_parts.append(rel)
        n_ref_total += n_ref
        copy = row["nearest_copy"]
        print(f"[{k + 1}/{len(targets)}] frame {row['target']}: {len(sources)} sources "
              f"({sources[0]}..{sources[-1]}, {row['source_distance_m']['min']:.2f}-"
              f"{row['source_distance_m']['max']:.2f} m away), depth median rel "
              f"{pct(row['depth_median_rel'])} mean {pct(row['depth_mean_rel'])}, coverage "
              f"{pct(row['depth_coverage'])}, PSNR {db(row['psnr_all_db'])} dB (rendered "
              f"{db(row['psnr_rendered_db'])}); nearest copy "
              f"{pct(copy['depth_median_rel'])} / {db(copy['psnr_all_db'])} dB; "
              f"sync {row['sync_ms']:.0f} ms, render "
              f"{row['render_ms']:.0f} ms, {time.perf_counter() - t0:.1f} s", flush=True)  # fmt: skip

    wall_s = time.perf_counter() - started
    report = {
        "benchmark": "real_sequence",
        "data": data_info,
        "checkpoint": {
            "path": str(args.checkpoint),
            "step": base.metadata.get("step"),
            "preset": base.metadata.get("preset"),
            "weights_sha256": base.metadata.get("weights_sha256"),
        },
        "settings": {
            "with_depth": args.with_depth,
            "every": args.every,
            "gap": args.gap,
            "sources": args.sources,
            "rotation_weight_m_per_rad": args.rotation_weight,
            "max_targets": args.max_targets,
            "working_wh": [width, height],
            "render_wh": list(render_size((width, height), args.render_scale)),
            "K_dataset": list(args.K),
            "runtime": asdict(base.config),
            "runtime_overrides": list(args.runtime),
        },
        "machine": platform.processor() or platform.machine(),
        "torch_threads": torch.get_num_threads(),
        "wall_s": wall_s,
        "summary": summarize(rows, rel_parts, n_ref_total),
        "targets": rows,
    }
    stem: Path = args.out_stem
    stem.parent.mkdir(parents=True, exist_ok=True)
    json_path, md_path = stem.parent / f"{stem.name}.json", stem.parent / f"{stem.name}.md"
    json_path.write_text(json.dumps(json_safe(report), indent=2) + "\n")
    text = markdown(report)
    md_path.write_text(text)
    print(text)
    print(f"wrote {json_path} and {md_path} ({wall_s:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
