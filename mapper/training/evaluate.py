"""Evaluation of GOV-NeSF against its baselines on held-out simulated scenes (paper Tables 1-3).

Data: directories written by ``govnesf sim record --depth`` (docs/how-to/simulator.md) plus
``gt/novel_ov.npy`` (SimLSeg at the ground-truth novel views, ``scripts/novel_view_ov.py``);
``scripts/make_eval_data.sh`` makes them. The mapper never imports the simulator: everything
here reads those files from disk.

Protocol (the official code's, see DESIGN.md, with our fixes):

* **2D novel views** (Table 1): each ``gt/novel_views.npz`` view is rendered from its nearest
  ``num_source_views`` stream frames by pose (the cost volume is built from those source views
  over the scene's bounds). Rendered OV features -> labels by argmax cosine to the text
  embeddings of the 20 ScanNet class names; mIoU / mAcc / oAcc over the pixels labelled with
  one of those classes; PSNR / SSIM of the rendered colour. Reference rows: SimLSeg run on the
  ground-truth image at the novel view, and the Distill baseline.
* **3D** (Tables 2-3): ground-truth surface points seen by more than one stream frame
  (``n_views > 1``), each blended as a single sample from all stream frames (cost volume over all
  of them), without depth and with Depth Guided Masking; side by side with plain averaging
  (``mapper.model.baselines.average_features``, 10 px border, without depth and with the 25% depth
  test), the Distill baseline and, as headroom references, averaging over the views that truly
  see the point (ground-truth visibility oracle). With ``EvalSettings.rgb_only_node``
  (``govnesf evaluate --rgb-only-node``) also the node's real RGB-only pipeline: the frames
  streamed without depth through an in-process node, its ``segment_points`` answers scored
  (:mod:`mapper.training.eval_node`).
* Scores per scene (classes present in the scene), then averaged over the scenes of a style.

Point queries go through ``blend_points``: the model's own per-point pipeline (projection,
visibility / DGM mask, sampling, FusionNet, softmax blending) with an optional cap of
``views_per_point`` nearest views per point, sampling only the selected views; with no cap it
equals ``GovNeSF.query_points`` (tested). It also returns the blending weights, so the
evaluation can measure how much weight lands on occluded views.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.checks import check_shape
from mapper.model.baselines import OVView, average_features
from mapper.model.field import GovNeSF, SourceViews, render_depth_maps, render_rays
from mapper.model.fusion import blend
from mapper.model.ops.cost_volume import VolumeBounds, sample_volume
from mapper.model.ops.geometry import (
    camera_centers,
    in_view,
    invert_pose,
    pixel_rays,
    project_points,
    sample_bilinear,
    sample_nearest,
    scale_uv,
)
from mapper.model.ops.rendering import Rays
from mapper.training.data import Scene, select_sources, source_batch
from mapper.training.data import load_scene as load_data_scene
from mapper.training.metrics import (
    NUM_SCANNET_CLASSES,
    SegmentationScores,
    average_over_scenes,
    confusion_matrix,
    predict_labels,
    segmentation_scores,
)

__all__ = [
    "EvalScene",
    "NovelViews",
    "PointBlend",
    "EvalSettings",
    "blend_points",
    "occluded_share",
    "scene_points",
    "ScenePoints",
    "view_transmittance",
    "candidate_views",
    "find_scene_dirs",
    "gt_visibility",
    "load_scene",
    "novel_view_sources",
    "nearest_view_selection",
    "psnr",
    "render_view",
    "scene_sources",
    "ssim",
    "evaluate_scene",
    "summarise",
    "format_report",
]

AVERAGING_BORDER_PX = 10.0
"""OpenScene-2D's border cut for averaging (official evaluation code)."""
DEPTH_REL_TOL = 0.25
"""Relative depth tolerance of the averaging depth test and of DGM."""


# ---- data ---------------------------------------------------------------------------------------
@dataclass
class NovelViews:
    """Held-out views of a scene (ground truth)."""

    K: np.ndarray  # (V, 4)
    world_from_cam: np.ndarray  # (V, 4, 4)
    rgb: np.ndarray  # (V, H, W, 3) uint8
    label: np.ndarray  # (V, H, W) int, -1 = none
    ov: np.ndarray | None  # (V, h, w, D) float16: SimLSeg at the ground-truth view, if present
    depth_m: np.ndarray | None = None  # (V, H, W) float32 true z-depth, 0 = none (when recorded)


@dataclass
class EvalScene:
    """One recorded scene, loaded for evaluation: the training loader's ``mapper.training.data.Scene``
    (frames, depth points for bounds and source selection) plus the ground truth."""

    data: Scene
    style: str
    seed: int
    gt_depth_m: np.ndarray  # (F, H, W) float32 ground-truth depth of the stream frames (analysis)
    points_xyz: np.ndarray  # (P, 3) float32 ground-truth surface points
    points_label: np.ndarray  # (P,) int
    points_n_views: np.ndarray  # (P,) int stream frames that see each point
    novel: NovelViews | None

    @property
    def name(self) -> str:
        return self.data.name

    @property
    def class_names(self) -> list[str]:
        return self.data.class_names

    @property
    def rgb(self) -> np.ndarray:  # (F, H, W, 3) uint8
        return self.data.rgb

    @property
    def depth_m(self) -> np.ndarray:  # (F, H, W) float32 recorded z-depth, 0 = none
        return self.data.depth_m

    @property
    def ov(self) -> np.ndarray:  # (F, h, w, D) float16 SimLSeg features of the stream frames
        return self.data.ov

    @property
    def K(self) -> np.ndarray:  # (F, 4)
        return self.data.K

    @property
    def world_from_cam(self) -> np.ndarray:  # (F, 4, 4)
        return self.data.world_from_cam

    @property
    def image_wh(self) -> tuple[int, int]:
        return self.data.image_wh

    def __len__(self) -> int:
        return self.data.num_frames


def find_scene_dirs(paths: Sequence[str | Path]) -> list[Path]:
    """Scene directories among ``paths``: each path is a scene (has ``frames.govrec``) or a folder
    whose direct subfolders are scenes. Raises ``FileNotFoundError`` naming a path with none."""
    out: list[Path] = []
    for p in map(Path, paths):
        if (p / "frames.govrec").is_file():
            out.append(p)
            continue
        if not p.is_dir():
            raise FileNotFoundError(f"{p}: no such directory")
        subs = sorted(d for d in p.iterdir() if (d / "frames.govrec").is_file())
        if not subs:
            raise FileNotFoundError(f"{p}: neither a recorded scene (frames.govrec) nor a folder of scenes")
        out.extend(subs)
    return out


def load_scene(path: str | Path) -> EvalScene:
    """Read a ``govnesf sim record --depth`` directory (docs/how-to/simulator.md layout) for evaluation."""
    path = Path(path)
    gt = path / "gt"
    for need in ("points.npz", "stream.npz", "class_names.json"):
        if not (gt / need).is_file():
            raise FileNotFoundError(f"{path}: gt/{need} missing; record with `govnesf sim record`")
    data = load_data_scene(path)
    pts = np.load(gt / "points.npz", allow_pickle=False)
    stream = np.load(gt / "stream.npz", allow_pickle=False)
    novel = None
    if (gt / "novel_views.npz").is_file():
        nv = np.load(gt / "novel_views.npz", allow_pickle=False)
        nov_ov = np.load(gt / "novel_ov.npy", allow_pickle=False) if (gt / "novel_ov.npy").is_file() else None
        if nov_ov is not None and nov_ov.shape[0] != nv["K"].shape[0]:
            raise ValueError(f"{path}: gt/novel_ov.npy has {nov_ov.shape[0]} views, gt/novel_views.npz "
                             f"{nv['K'].shape[0]}; re-run scripts/novel_view_ov.py")
        novel = NovelViews(
            K=nv["K"].astype(np.float64), world_from_cam=nv["world_from_cam"].astype(np.float64),
            rgb=nv["rgb"], label=nv["label"].astype(np.int64), ov=nov_ov,
            depth_m=nv["depth_m"].astype(np.float32) if "depth_m" in nv.files else None,
        )
    info: dict[str, Any] = {}
    if (gt / "scene.json").is_file():
        info = json.loads((gt / "scene.json").read_text())
    return EvalScene(
        data=data,
        style=str(info.get("style", "unknown")),
        seed=int(info.get("seed", -1)),
        gt_depth_m=stream["depth_m"].astype(np.float32),
        points_xyz=pts["xyz"].astype(np.float32),
        points_label=pts["label"].astype(np.int64),
        points_n_views=pts["n_views"].astype(np.int64),
        novel=novel,
    )


def scene_sources(model: GovNeSF, scene: EvalScene, index: np.ndarray | None = None,
                  *, device: torch.device | str = "cpu",
                  frustum_range_m: float | None = None) -> tuple[SourceViews, VolumeBounds]:
    """Source views (encoded) of the stream frames ``index`` (all when None) and the volume
    bounds over their depth points: exactly what training builds (``mapper.training.data.source_batch``).
    With ``frustum_range_m`` the bounds come from the frames' frusta instead (no depth used), as
    the node builds them for frames without depth."""
    sel = np.arange(len(scene)) if index is None else np.asarray(index, dtype=np.int64)
    src = source_batch(scene.data, sel, model.cfg, frustum_range_m=frustum_range_m).to(device)
    with torch.no_grad():
        views = model.make_source_views(src.rgb, src.ov, src.K, src.world_from_cam, src.depth_m)
    return views, src.bounds


def novel_view_sources(scene: EvalScene, view: int, n: int) -> np.ndarray:
    """(n,) stream frames for novel view ``view``: best overlap first, as in training's validation."""
    assert scene.novel is not None
    return select_sources(scene.data, scene.novel.K[view], scene.novel.world_from_cam[view], n)


# ---- point queries ------------------------------------------------------------------------------
@dataclass
class PointBlend:
    """OV features at points with the views that took part and their blending weights."""

    ov: Tensor  # (P, D) blended (or, distill mode, regressed) OV feature, 0 where invalid
    valid: Tensor  # (P,) bool: some view took part
    num_views: Tensor  # (P,) long: views that took part
    view_index: Tensor  # (P, k) long: source-view index of each slot (meaningless where ~mask)
    mask: Tensor  # (P, k) bool: slot holds a view that took part
    weights: Tensor  # (P, k) OV blending weights (distill mode: uniform over the slots)


@torch.no_grad()
def view_transmittance(model: GovNeSF, volume: Tensor, bounds: VolumeBounds, points: Tensor,
                       centres: Tensor, *, n_samples: int = 16, stop_m: float | None = None) -> Tensor:
    """Transmittance of the model's density from each camera centre to each point: ``exp(-sum
    sigma delta)`` over ``n_samples`` midpoints of the segment, stopping ``stop_m`` short of the
    point (default 1.5 voxels, so the point's own surface does not occlude it).

    Args:
        points: (P, 3); centres: (P, k, 3) camera centre of each (point, view) pair.

    Returns:
        (P, k) in (0, 1]; 1 where the segment is shorter than ``stop_m``.
    """
    stop = 1.5 * bounds.voxel_size_m if stop_m is None else stop_m
    seg = points.to(centres.dtype)[:, None, :] - centres  # (P, k, 3)
    length = seg.norm(dim=-1)
    direction = seg / length.clamp_min(1e-9)[..., None]
    end = (length - stop).clamp_min(0.0)  # (P, k)
    frac = (torch.arange(n_samples, device=centres.device, dtype=centres.dtype) + 0.5) / n_samples
    samples = centres[..., None, :] + direction[..., None, :] * (end[..., None] * frac)[..., None]
    sigma, _ = model.density_at(volume, bounds, samples.reshape(-1, 3).to(volume.dtype))
    optical = sigma.reshape(*end.shape, n_samples).sum(-1) * (end / n_samples).to(sigma.dtype)
    return torch.exp(-optical)


def candidate_views(views: SourceViews, points: Tensor, *, depth_guided_masking: bool,
                    depth_mask_ratio: float = DEPTH_REL_TOL) -> tuple[Tensor, Tensor, Tensor]:
    """The model's visibility test (``GovNeSF.sample_views``): in front and inside the image and,
    with DGM and depth, |z - depth| <= ratio x depth (views without a measurement pass).

    Args:
        points: (P, 3).

    Returns:
        uv (N, P, 2) pixel coordinates, z (N, P) depth (m), mask (P, N) bool.
    """
    n = len(views)
    wh = views.image_wh
    pts = points.to(views.K.dtype).unsqueeze(0).expand(n, -1, -1)
    uv, z = project_points(pts, views.K, invert_pose(views.world_from_cam))  # (N, P, 2), (N, P)
    mask = in_view(uv, z, wh[0], wh[1])
    if depth_guided_masking and views.depth_m is not None:
        d_wh = (views.depth_m.shape[-1], views.depth_m.shape[-2])
        measured, _ = sample_nearest(views.depth_m.unsqueeze(1), scale_uv(uv, wh, d_wh))
        measured = measured.squeeze(-1)
        has_depth = torch.isfinite(measured) & (measured > 0)
        agrees = (z - measured).abs() <= depth_mask_ratio * measured
        mask = mask & (agrees | ~has_depth)
    return uv, z, mask.transpose(0, 1)


def _select(mask: Tensor, distance: Tensor, k: int | None) -> tuple[Tensor, Tensor]:
    """(P, N) mask and distance -> the k nearest masked views: index (P, k'), mask (P, k').

    k' = min(k, the largest number of masked views of any point) (all masked views when k is None).
    """
    most = int(mask.sum(dim=1).max()) if mask.numel() else 0
    k_eff = max(1, most if k is None else min(k, most))
    score = distance.masked_fill(~mask, float("inf"))
    _, idx = torch.topk(score, k_eff, dim=1, largest=False, sorted=True)
    return idx, mask.gather(1, idx)


def blend_points(
    model: GovNeSF,
    views: SourceViews,
    volume: Tensor,
    bounds: VolumeBounds,
    points: Tensor,
    *,
    depth_guided_masking: bool = False,
    views_per_point: int | None = None,
    chunk_size: int = 2048,
    view_weight_fn: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
) -> PointBlend:
    """Point-mode OV features (``GovNeSF.query_points``) blended from at most ``views_per_point``
    views per point: the nearest (camera-centre distance) of the views that see it.

    Only the selected views are sampled. With ``views_per_point=None`` every view that sees the
    point takes part, which equals ``query_points``.

    Args:
        views: N source views; volume: (Dv, X, Y, Z) over ``bounds``; points: (P, 3) world (m).
        view_weight_fn: optional ``(points (P, 3), view_index (P, k), mask (P, k)) -> (P, k)``
            multiplier >= 0 of the learned OV weights (renormalised over the views; analysis,
            e.g. :func:`view_transmittance`); a point whose multipliers are all 0 keeps its weights.

    Returns:
        PointBlend (k = the most views any point of a chunk used; pad slots have mask False).
    """
    if views_per_point is not None and views_per_point < 1:
        raise ValueError(f"views_per_point {views_per_point} out of range: must be >= 1 or None (all)")
    if chunk_size < 1:
        raise ValueError(f"chunk_size {chunk_size} out of range: must be >= 1")
    parts = [
        _blend_chunk(model, views, volume, bounds, points[i : i + chunk_size], depth_guided_masking,
                     views_per_point, view_weight_fn)
        for i in range(0, points.shape[0], chunk_size)
    ]
    if not parts:
        parts = [_blend_chunk(model, views, volume, bounds, points, depth_guided_masking, views_per_point,
                              view_weight_fn)]
    k = max(p.mask.shape[1] for p in parts)

    def pad(t: Tensor, value: float | bool) -> Tensor:
        return F.pad(t, (0, k - t.shape[1]), value=value) if t.shape[1] < k else t

    return PointBlend(
        ov=torch.cat([p.ov for p in parts]),
        valid=torch.cat([p.valid for p in parts]),
        num_views=torch.cat([p.num_views for p in parts]),
        view_index=torch.cat([pad(p.view_index, 0) for p in parts]),
        mask=torch.cat([pad(p.mask, False) for p in parts]),
        weights=torch.cat([pad(p.weights, 0.0) for p in parts]),
    )


@torch.no_grad()
def _blend_chunk(model: GovNeSF, views: SourceViews, volume: Tensor, bounds: VolumeBounds, points: Tensor,
                 depth_guided_masking: bool, views_per_point: int | None,
                 view_weight_fn: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None) -> PointBlend:
    wh = views.image_wh
    uv, z, mask = candidate_views(views, points, depth_guided_masking=depth_guided_masking,
                                  depth_mask_ratio=model.cfg.render.depth_mask_ratio)
    pts = points.to(views.K.dtype)
    centres = camera_centers(views.world_from_cam)  # (N, 3)
    dist = torch.cdist(pts, centres)  # (P, N)
    idx, sel = _select(mask, dist, views_per_point)  # (P, k)
    P, k = idx.shape
    feat_dim, ov_dim = views.features.shape[1], views.ov.shape[1]
    rgb = pts.new_zeros(P, k, 3)
    feat = pts.new_zeros(P, k, feat_dim)
    ov = pts.new_zeros(P, k, ov_dim)
    f_wh = (views.features.shape[-1], views.features.shape[-2])
    o_wh = (views.ov.shape[-1], views.ov.shape[-2])
    for n in torch.unique(idx[sel]).tolist():
        rows, slots = torch.nonzero((idx == n) & sel, as_tuple=True)
        uv_n = uv[n, rows]  # (m, 2)
        rgb[rows, slots] = sample_bilinear(views.rgb[n], uv_n)[0]
        feat[rows, slots] = sample_bilinear(views.features[n], scale_uv(uv_n, wh, f_wh))[0]
        ov[rows, slots] = sample_bilinear(views.ov[n], scale_uv(uv_n, wh, o_wh))[0]
    dirs = F.normalize(pts.unsqueeze(1) - centres[idx], dim=-1, eps=1e-9)  # (P, k, 3)
    v, _ = sample_volume(volume, bounds, points.to(volume.dtype))
    fused = model.fusion(rgb, feat, v, dirs, sel, None, dist.gather(1, idx))
    if model.distill is not None:
        out = model.distill(fused.x_att, sel, v) * fused.valid.unsqueeze(-1)
        weights = sel.float() / sel.sum(dim=1, keepdim=True).clamp_min(1)
    else:
        weights = fused.ov_weights
        if view_weight_fn is not None:
            mult = view_weight_fn(points, idx, sel).to(weights.dtype) * sel.to(weights.dtype)
            reweighted = weights * mult
            total = reweighted.sum(dim=1, keepdim=True)
            weights = torch.where(total > 1e-12, reweighted / total.clamp_min(1e-12), weights)
        out = blend(weights, ov)
    return PointBlend(ov=out, valid=fused.valid, num_views=sel.sum(dim=1), view_index=idx, mask=sel,
                      weights=weights)


def nearest_view_selection(points: Tensor, K: Tensor, world_from_cam: Tensor, image_wh: tuple[int, int],
                           k: int, *, border_px: float = AVERAGING_BORDER_PX,
                           depth_m: Tensor | None = None, depth_rel_tol: float = DEPTH_REL_TOL,
                           chunk: int = 16384) -> Tensor:
    """Averaging's view cap: for each point, its ``k`` nearest views among those that pass the
    averaging tests (inside the image with a border cut; with ``depth_m``, the depth test).

    Args:
        points: (P, 3); K: (N, 4); world_from_cam: (N, 4, 4); depth_m: (N, H, W) or None.

    Returns:
        (N, P) bool, the ``view_weights`` argument of ``average_features``.
    """
    if k < 1:
        raise ValueError(f"k {k} out of range: must be >= 1")
    out = torch.zeros(K.shape[0], points.shape[0], dtype=torch.bool)
    centres = camera_centers(world_from_cam)
    for s in range(0, points.shape[0], chunk):
        p = points[s : s + chunk].to(K.dtype)
        ok = _averaging_mask(p, K, world_from_cam, image_wh, depth_m, border_px, depth_rel_tol)  # (m, N)
        idx, sel = _select(ok, torch.cdist(p, centres), k)  # (m, k)
        rows = torch.arange(p.shape[0]).unsqueeze(1).expand_as(idx)
        chosen = torch.zeros(p.shape[0], K.shape[0], dtype=torch.bool)
        chosen[rows[sel], idx[sel]] = True
        out[:, s : s + chunk] = chosen.T
    return out


def gt_visibility(points: Tensor, K: Tensor, world_from_cam: Tensor, depth_m: Tensor,
                  *, tol_m: float = 0.02, tol_rel: float = 0.02) -> tuple[Tensor, Tensor]:
    """Ground-truth visibility as in the simulator's ``n_views`` (inside the image, in front,
    z within max(tol_m, tol_rel x depth) of the rendered depth).

    Args:
        points: (P, 3); K: (N, 4); world_from_cam: (N, 4, 4); depth_m: (N, H, W) rendered depth.

    Returns:
        in_image (P, N) bool, visible (P, N) bool (``in_image & ~visible`` = occluded).
    """
    n, h, w = depth_m.shape
    uv, z = project_points(points.to(K.dtype).unsqueeze(0).expand(n, -1, -1), K, invert_pose(world_from_cam))
    inside = in_view(uv, z, w, h, eps=1e-3)
    d, _ = sample_nearest(depth_m.unsqueeze(1), uv)
    d = d.squeeze(-1)
    vis = inside & (d > 0) & ((d - z).abs() <= torch.clamp(tol_rel * d, min=tol_m))
    return inside.T, vis.T


def render_view(model: GovNeSF, views: SourceViews, volume: Tensor, bounds: VolumeBounds, K: np.ndarray,
                world_from_cam: np.ndarray, image_wh: tuple[int, int], *, pixel_stride: int = 1,
                chunk_rays: int = 1024, **render_kwargs: Any) -> tuple[Tensor, Tensor]:
    """Render the centres of every ``pixel_stride``-th pixel (rows and columns, starting at
    ``pixel_stride // 2``) of a view: rgb (h', w', 3) and OV (h', w', D). Stride 1 = the whole image.

    Args:
        K: (4,) intrinsics for ``image_wh``; world_from_cam: (4, 4).
        render_kwargs: forwarded to ``render_rays`` (n_samples, clip_to_volume, weight_threshold).
    """
    rgb, ov, _, _ = render_view_full(model, views, volume, bounds, K, world_from_cam, image_wh,
                                     pixel_stride=pixel_stride, chunk_rays=chunk_rays, **render_kwargs)
    return rgb, ov


def _strided_rays(K: np.ndarray, world_from_cam: np.ndarray, image_wh: tuple[int, int], pixel_stride: int,
                  device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through the centres of every ``pixel_stride``-th pixel (from ``pixel_stride // 2``):
    origins (h', w', 3), unit directions (h', w', 3), and the float32 pose (4, 4)."""
    if pixel_stride < 1:
        raise ValueError(f"pixel_stride {pixel_stride} out of range: must be >= 1")
    pose = torch.as_tensor(world_from_cam, dtype=torch.float32, device=device)
    origins, dirs = pixel_rays(torch.as_tensor(K, dtype=torch.float32, device=device), pose, *image_wh)
    off = pixel_stride // 2
    return origins[off::pixel_stride, off::pixel_stride], dirs[off::pixel_stride, off::pixel_stride], pose


def render_view_full(model: GovNeSF, views: SourceViews, volume: Tensor, bounds: VolumeBounds, K: np.ndarray,
                     world_from_cam: np.ndarray, image_wh: tuple[int, int], *, pixel_stride: int = 1,
                     chunk_rays: int = 1024, surface_depth_m: np.ndarray | None = None,
                     **render_kwargs: Any) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``render_view`` plus the rendered z-depth (h', w') (m) and, with ``surface_depth_m``
    ((H, W) z-depth of known surfaces at full resolution, 0 = none), rendering as the node's
    ``render`` does at measured surfaces (docs/concepts/rendering.md): a pixel with a surface gets one
    appearance evaluation at that point (depth = the surface's), the others are marched.

    Returns:
        rgb (h', w', 3), OV (h', w', D), z-depth (h', w'), at_surface (h', w') bool.
    """
    dev = views.K.device
    origins, dirs, pose = _strided_rays(K, world_from_cam, image_wh, pixel_stride, dev)
    h, w = origins.shape[:2]
    off = pixel_stride // 2
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    axis = pose[:3, 2]
    cos = (dirs @ axis).clamp_min(1e-6)  # (R,) ray distance -> z-depth
    if surface_depth_m is not None:
        if np.shape(surface_depth_m) != (image_wh[1], image_wh[0]):
            raise ValueError(f"surface_depth_m shape {np.shape(surface_depth_m)}, expected (H, W) = "
                             f"{(image_wh[1], image_wh[0])}")
        z_s = torch.as_tensor(np.asarray(surface_depth_m, np.float32)[off::pixel_stride, off::pixel_stride],
                              device=dev).reshape(-1)
        at_surface = torch.isfinite(z_s) & (z_s > 0)
    else:
        z_s = torch.zeros(origins.shape[0], device=dev)
        at_surface = torch.zeros(origins.shape[0], dtype=torch.bool, device=dev)
    rgb = torch.zeros(origins.shape[0], 3, device=dev)
    ov = torch.zeros(origins.shape[0], views.ov.shape[1], device=dev)
    z = torch.zeros(origins.shape[0], device=dev)
    for sel, surface in ((torch.nonzero(~at_surface)[:, 0], False), (torch.nonzero(at_surface)[:, 0], True)):
        for i in range(0, sel.numel(), chunk_rays):
            idx = sel[i : i + chunk_rays]
            if surface:
                points = origins[idx] + (z_s[idx] / cos[idx]).unsqueeze(-1) * dirs[idx]
                v, _ = sample_volume(volume, bounds, points.to(volume.dtype))
                rgb_k, ov_k, _ = model.appearance(views, v, points, dirs[idx], False)
                rgb[idx], ov[idx], z[idx] = rgb_k.to(rgb.dtype), ov_k.to(ov.dtype), z_s[idx]
            else:
                rays = Rays(origins[idx], dirs[idx])
                out = render_rays(model, views, volume, bounds, rays, **render_kwargs)
                rgb[idx], ov[idx] = out.rgb.to(rgb.dtype), out.ov.to(ov.dtype)
                z[idx] = out.depth_m.to(z.dtype) * cos[idx]
    return rgb.reshape(h, w, 3), ov.reshape(h, w, -1), z.reshape(h, w), at_surface.reshape(h, w)


def seen_by_sources(views: SourceViews, K: np.ndarray, world_from_cam: np.ndarray, image_wh: tuple[int, int],
                    true_depth_m: np.ndarray, *, pixel_stride: int = 1, rel_tol: float = 0.05) -> Tensor:
    """(h', w') bool: the pixels (every ``pixel_stride``-th centre, as ``render_view``) whose true
    surface point (``true_depth_m`` (H, W) z-depth of the view, 0 = none) some source view truly
    sees: inside its image and its measured depth there within ``rel_tol`` of the point's. What
    no source sees, no blend of the sources can know (it renders as "not covered")."""
    if views.depth_m is None:
        raise ValueError("seen_by_sources needs the source views' depth")
    dev = views.K.device
    origins, dirs, pose = _strided_rays(K, world_from_cam, image_wh, pixel_stride, dev)
    off = pixel_stride // 2
    z = torch.as_tensor(np.asarray(true_depth_m, np.float32), device=dev)
    z = z[off::pixel_stride, off::pixel_stride]
    h, w = z.shape
    pts = (origins + (z / (dirs @ pose[:3, 2]).clamp_min(1e-6)).unsqueeze(-1) * dirs).reshape(-1, 3)
    n = len(views)
    uv, zz = project_points(pts.unsqueeze(0).expand(n, -1, -1), views.K, invert_pose(views.world_from_cam))
    d_wh = (views.depth_m.shape[-1], views.depth_m.shape[-2])
    measured, _ = sample_nearest(views.depth_m.unsqueeze(1), scale_uv(uv, views.image_wh, d_wh))
    measured = measured.squeeze(-1)
    sees = in_view(uv, zz, *views.image_wh) & (measured > 0) & ((zz - measured).abs() <= rel_tol * measured)
    return (sees.any(dim=0) & (z.reshape(-1) > 0)).reshape(h, w)


def sources_surface_depth(views: SourceViews, K: np.ndarray, world_from_cam: np.ndarray,
                          image_wh: tuple[int, int], footprint_m: float) -> np.ndarray:
    """(H, W) z-depth of the surfaces the source views' depth maps measured, seen from a new view:
    every source pixel with depth back-projected and splatted as the node splats its map
    (``mapper.node.queries.surface_depth``, the default ``model`` settings; 0 = no surface).
    Sources without depth give zeros."""
    from mapper.geometry.triangulation import backproject
    from mapper.node.queries import surface_depth
    from mapper.runtime.config import ModelRuntimeConfig

    w, h = image_wh
    if views.depth_m is None:
        return np.zeros((h, w), np.float32)
    depth = views.depth_m.detach().cpu().numpy()
    Ks = views.K.detach().cpu().numpy()
    poses = views.world_from_cam.detach().cpu().numpy()
    d_wh = (depth.shape[-1], depth.shape[-2])
    scale = np.array([d_wh[0] / views.image_wh[0], d_wh[1] / views.image_wh[1]] * 2)
    pts = [backproject(depth[n], Ks[n] * scale, poses[n])[2] for n in range(len(depth))]
    xyz = np.concatenate(pts) if pts else np.zeros((0, 3))
    return surface_depth(xyz, footprint_m, np.asarray(K, np.float64), np.asarray(world_from_cam, np.float64),
                         w, h, ModelRuntimeConfig())


# ---- image metrics ------------------------------------------------------------------------------
def _median_rel_err(z: Tensor, true_z: np.ndarray) -> float:
    """Median |z - true| / true over the pixels with a true depth (a pixel rendered without any
    depth counts as 100% off); nan without any true depth."""
    t = torch.as_tensor(np.asarray(true_z, np.float32))
    has = torch.isfinite(t) & (t > 0)
    if not bool(has.any()):
        return float("nan")
    return float(((z.float() - t).abs() / t.clamp_min(1e-6))[has].median())


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1]: (..., 3) each."""
    mse = float(((pred.double() - target.double()) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def ssim(pred: Tensor, target: Tensor, *, window: int = 11, sigma: float = 1.5) -> float:
    """Structural similarity (Wang et al. 2004) of (H, W, C) images in [0, 1]: Gaussian window
    11 / sigma 1.5, constants (0.01, 0.03), per channel over the valid region, averaged."""
    dims = check_shape(pred, "H W C", "ssim pred")
    check_shape(target, "H W C", "ssim target (the shape of pred)", dims)
    if min(pred.shape[:2]) < window:
        raise ValueError(f"images {tuple(pred.shape[:2])} are smaller than the {window} px SSIM window")
    x = pred.double().permute(2, 0, 1).unsqueeze(1)  # (C, 1, H, W)
    y = target.double().permute(2, 0, 1).unsqueeze(1)
    g = torch.exp(-((torch.arange(window, dtype=torch.float64) - (window - 1) / 2) ** 2) / (2 * sigma**2))
    g = g / g.sum()
    kern = (g[:, None] * g[None, :])[None, None]  # (1, 1, w, w)

    def filt(t: Tensor) -> Tensor:
        return F.conv2d(t, kern)

    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s.mean())


def _labels_2d(ov_hw: Tensor, text: Tensor) -> np.ndarray:
    """(H, W, D) features -> (H, W) int labels by argmax cosine."""
    h, w, d = ov_hw.shape
    return np.asarray(predict_labels(ov_hw.reshape(-1, d).float(), text.float())).reshape(h, w)


def upsample_features(ov: np.ndarray | Tensor, image_wh: tuple[int, int]) -> Tensor:
    """(h, w, D) feature map -> (H, W, D) bilinear (pixel centres aligned)."""
    t = torch.as_tensor(np.asarray(ov, dtype=np.float32) if isinstance(ov, np.ndarray) else ov.float())
    up = F.interpolate(t.permute(2, 0, 1)[None], size=(image_wh[1], image_wh[0]), mode="bilinear",
                       align_corners=False)
    return up[0].permute(1, 2, 0)


# ---- the evaluation -----------------------------------------------------------------------------
@dataclass
class EvalSettings:
    """What to evaluate and how (defaults: the protocol in docs/how-to/evaluate.md)."""

    max_points: int | None = 20000
    """3D: evaluate at most this many points per scene (uniform random subset, fixed seed)."""
    views_per_point: int | None = None
    """3D: blend/average at most this many nearest views per point (None: all that see it)."""
    num_source_views: int | None = None
    """2D: source views per novel view (None: the model's ``num_source_views``)."""
    n_samples: int | None = None
    """2D: samples per ray (None: the model's)."""
    max_novel_views: int | None = None
    """2D: evaluate at most this many (evenly spaced) novel views per scene (None: all)."""
    pixel_stride: int = 1
    """2D: evaluate the centres of every s-th pixel (rows and columns); SSIM then compares the
    subsampled images (1 = full resolution)."""
    clip_to_volume: bool = True
    """2D: sample rays only inside the volume (as ``launch/train_cpu_small.toml`` trains)."""
    weight_threshold: float = 0.0
    """2D: skip the appearance pass for samples with a smaller rendering weight (0 = exact)."""
    chunk_rays: int = 1024
    chunk_points: int = 2048
    do_2d: bool = True
    do_3d: bool = True
    averaging_borders_px: tuple[float, ...] = (AVERAGING_BORDER_PX,)
    """3D: image border cuts for the averaging rows (10 px: OpenScene-2D; 0 px: the same
    candidate views as the model). Rows other than 10 px are named with their border."""
    oracle: bool = True
    """3D: also average over the ground-truth visible views (the headroom reference)."""
    no_depth_input: bool = True
    """3D: also the rows that use no input depth anywhere (as the node with an RGB-only robot):
    volume bounds from the stream frames' frusta up to ``frustum_range_m``, and the model's own
    rendered depth (at 1 / ``rendered_depth_stride`` of the image) in place of the measured depth
    for Depth Guided Masking and for the averaging depth test."""
    frustum_range_m: float = 4.0
    rendered_depth_stride: int = 4
    seed: int = 0
    surface_renders: bool = True
    """2D: also each model rendered as the node renders with depth: at the surfaces the source
    views' depth measured (splatted into the novel view), marching only the other pixels
    (``render_view_full``); rows "... at measured surfaces (depth input)"."""
    surface_footprint_m: float = 0.05
    """Footprint of each source depth point in that splat (the node's map voxel, 5 cm)."""
    point_occlusion: bool = True
    """3D: also the rows with a visibility cue from the evaluated points themselves and no input
    depth: each stream frame's z-buffer of those points
    (:func:`mapper.geometry.splat.request_occluder_depths`, each point over
    ``point_occlusion_footprint`` x their median spacing, as the node's
    ``model.point_occlusion``) as the depth of Depth Guided Masking and of the averaging's depth
    test (every averaging border). Rows "... + point occlusion (no depth input)"."""
    point_occlusion_footprint: float = 3.0
    """The node's ``model.point_occlusion_footprint``."""
    rgb_only_node: str | None = None
    """3D: the checkpoint path to serve in an in-process node that the scene is streamed into
    WITHOUT depth, with the plugins ``govnesf serve`` installs; its ``segment_points`` answers
    become the ``Node RGB-only: ...`` rows (:mod:`mapper.training.eval_node`). None: no such rows."""
    node_config: str | None = None
    """The node's TOML config for those rows (None: the shipped ``launch/node.toml``)."""
    node_ov_space: str = "minilm-l6-v2"
    """Embedding space the frames' ``ov`` is sent in to that node (``govnesf sim record``: SimLSeg
    features in the MiniLM space); the node encodes the class names in it."""


@dataclass
class MethodResult:
    """Confusion matrix and extras of one method on one scene."""

    cm: np.ndarray
    extra: dict[str, float] = field(default_factory=dict)

    def scores(self) -> SegmentationScores:
        return segmentation_scores(self.cm)


@dataclass
class ScenePoints:
    """The evaluated ground-truth points of a scene with their true visibility in each stream frame."""

    gt: np.ndarray  # (P,) int labels
    xyz: Tensor  # (P, 3) float32 world points
    K: Tensor  # (N, 4) float32
    world_from_cam: Tensor  # (N, 4, 4) float32
    in_image: Tensor  # (P, N) bool: projects into the frame
    visible: Tensor  # (P, N) bool: the frame truly sees it (ground-truth depth)

    @property
    def occluded(self) -> Tensor:
        """(P, N) bool: projects into the frame but is hidden there."""
        return self.in_image & ~self.visible


def scene_points(scene: EvalScene, settings: EvalSettings) -> ScenePoints:
    """The 3D protocol's points (``_subset``: labelled, seen by > 1 frame, up to ``max_points``)."""
    keep = _subset(scene, settings)
    pts = torch.from_numpy(scene.points_xyz[keep])
    K = torch.from_numpy(scene.K).float()
    poses = torch.from_numpy(scene.world_from_cam).float()
    in_image, visible = gt_visibility(pts, K, poses, torch.from_numpy(scene.gt_depth_m))
    return ScenePoints(scene.points_label[keep], pts, K, poses, in_image, visible)


def occluded_share(pb: PointBlend, occluded: Tensor) -> float:
    """Mean share of a point's blending weight on views that do not truly see it (over the points
    some view took part in; nan when there are none). ``occluded``: (P, N) bool."""
    occ_sel = occluded.to(pb.view_index.device).gather(1, pb.view_index) & pb.mask
    share = (pb.weights * occ_sel).sum(1)[pb.valid]
    return float(share.mean()) if share.numel() else float("nan")


def _uniform_occluded_share(counted: Tensor, occluded: Tensor) -> float:
    """The same for a uniform average over the ``counted`` (P, N) views."""
    occ = (occluded & counted).sum(1).float() / counted.sum(1).clamp_min(1).float()
    return float(occ[counted.any(1)].mean())


def _subset(scene: EvalScene, settings: EvalSettings) -> np.ndarray:
    keep = np.flatnonzero((scene.points_n_views > 1) & (scene.points_label >= 0)
                          & (scene.points_label < NUM_SCANNET_CLASSES))
    if settings.max_points is not None and keep.size > settings.max_points:
        rng = np.random.default_rng([settings.seed, scene.seed])
        keep = np.sort(rng.choice(keep, settings.max_points, replace=False))
    return keep


def _avg_views(scene: EvalScene) -> list[OVView]:
    return [OVView(scene.ov[k], scene.K[k], scene.world_from_cam[k], scene.image_wh,
                   scene.depth_m[k]) for k in range(len(scene))]


def evaluate_scene(
    scene: EvalScene,
    models: dict[str, GovNeSF],
    text_emb: Tensor,
    settings: EvalSettings,
    *,
    log: Callable[[str], None] = lambda s: None,
    device: torch.device | str = "cpu",
) -> dict[str, dict[str, MethodResult]]:
    """All methods on one scene.

    Args:
        models: name -> model, e.g. {"GOV-NeSF": blend model, "Distill": distill model}.
        text_emb: (20, D) class-name embeddings of the ScanNet-20 classes.

    Returns:
        {"3d": {method: MethodResult}, "2d": {method: MethodResult}}; 3D extras: ``seconds``,
        ``occluded_weight`` (mean fraction of the blending weight on views that do not truly see
        the point), ``invalid`` (points no view took part in); 2D extras: ``psnr``, ``ssim``,
        ``seconds``.
    """
    out: dict[str, dict[str, MethodResult]] = {"3d": {}, "2d": {}}
    any_model = next(iter(models.values()), None)
    if settings.do_3d:
        out["3d"] = _evaluate_3d(scene, models, text_emb, settings, log, device)
    if settings.do_2d and scene.novel is not None and any_model is not None:
        out["2d"] = _evaluate_2d(scene, models, text_emb, settings, log, device)
    return out


def _evaluate_3d(scene: EvalScene, models: dict[str, GovNeSF], text_emb: Tensor, settings: EvalSettings,
                 log: Callable[[str], None], device: torch.device | str) -> dict[str, MethodResult]:
    sp = scene_points(scene, settings)
    gt, pts, K, poses, visible, occluded = sp.gt, sp.xyz, sp.K, sp.world_from_cam, sp.visible, sp.occluded
    res: dict[str, MethodResult] = {}
    vpp = settings.views_per_point

    def record(name: str, feats: Tensor, seconds: float, **extra: float) -> None:
        pred = np.asarray(predict_labels(feats.cpu().float(), text_emb))
        res[name] = MethodResult(confusion_matrix(gt, pred),
                                 {"seconds": seconds, "seconds_per_100k": seconds * 1e5 / max(len(gt), 1),
                                  **extra})
        s = res[name].scores()
        log(f"  3d {scene.name} {name:<34} mIoU {100 * s.miou:5.1f}  ({seconds:.1f} s)")

    avg_views = _avg_views(scene)
    depth_t = torch.from_numpy(scene.depth_m)
    for border in settings.averaging_borders_px:
        suffix = "" if border == AVERAGING_BORDER_PX else f", {border:g} px border"
        for use_depth in (False, True):
            t0 = time.perf_counter()
            vw = None
            if vpp is not None:
                vw = nearest_view_selection(pts, K, poses, scene.image_wh, vpp, border_px=border,
                                            depth_m=depth_t if use_depth else None)
            feats, nv = average_features(pts, avg_views, use_depth=use_depth, view_weights=vw, device=device,
                                         border_px=border)
            secs = time.perf_counter() - t0
            # Occluded share of the averaging weight (uniform over the views that counted).
            counted = vw.T if vw is not None else _averaging_mask(pts, K, poses, scene.image_wh,
                                                                  depth_t if use_depth else None, border)
            name = ("Averaging + depth test" if use_depth else "Averaging (no depth)") + suffix
            record(name, feats, secs, occluded_weight=_uniform_occluded_share(counted, occluded),
                   invalid=float((nv == 0).float().mean()))
    if settings.oracle:
        t0 = time.perf_counter()
        feats, nv = average_features(pts, avg_views, use_depth=False, view_weights=visible.T, device=device)
        record("Averaging, GT-visible views (oracle)", feats, time.perf_counter() - t0,
               occluded_weight=0.0, invalid=float((nv == 0).float().mean()))

    point_depth: Tensor | None = None  # (N, H, W) the frames' z-buffers of the evaluated points
    if settings.point_occlusion:
        point_depth = point_occlusion_depths(sp, scene.image_wh, settings.point_occlusion_footprint)
        pd = point_depth.numpy()
        views_pts = [OVView(scene.ov[k], scene.K[k], scene.world_from_cam[k], scene.image_wh, pd[k])
                     for k in range(len(scene))]
        for border in settings.averaging_borders_px:
            t0 = time.perf_counter()
            feats, nv = average_features(pts, views_pts, use_depth=True, device=device, border_px=border)
            counted = _averaging_mask(pts, K, poses, scene.image_wh, point_depth, border)
            suffix = "" if border == AVERAGING_BORDER_PX else f", {border:g} px border"
            record("Averaging + point occlusion (no depth input)" + suffix, feats, time.perf_counter() - t0,
                   occluded_weight=_uniform_occluded_share(counted, occluded),
                   invalid=float((nv == 0).float().mean()))
    for mname, model in models.items():
        t0 = time.perf_counter()
        views, bounds = scene_sources(model, scene, device=device)
        with torch.no_grad():
            volume = model.build_volume(views, bounds)
        t_vol = time.perf_counter() - t0
        for dgm in (False, True):
            t0 = time.perf_counter()
            pb = blend_points(model, views, volume, bounds, pts.to(device), depth_guided_masking=dgm,
                              views_per_point=vpp, chunk_size=settings.chunk_points)
            secs = time.perf_counter() - t0
            record(f"{mname} + DGM" if dgm else f"{mname} (no depth)", pb.ov, secs,
                   occluded_weight=occluded_share(pb, occluded),
                   invalid=float((~pb.valid).float().mean()), volume_seconds=t_vol)
        if settings.no_depth_input:
            _no_depth_input_rows(scene, model, mname, sp, settings, record, device)
        if point_depth is not None:
            t0 = time.perf_counter()
            v = dataclasses.replace(views, depth_m=point_depth.to(views.K.device))
            pb = blend_points(model, v, volume, bounds, pts.to(device), depth_guided_masking=True,
                              views_per_point=vpp, chunk_size=settings.chunk_points)
            record(f"{mname} + point occlusion (no depth input)", pb.ov, time.perf_counter() - t0,
                   occluded_weight=occluded_share(pb, occluded), invalid=float((~pb.valid).float().mean()))
    if settings.rgb_only_node is not None:
        from mapper.training.eval_node import NodeEvalSettings, node_rgb_only_rows

        node_rows = node_rgb_only_rows(scene, settings.rgb_only_node, pts.numpy(), gt, NodeEvalSettings(
            config_path=settings.node_config, device=str(device), ov_space=settings.node_ov_space))
        for name, (cm, extra) in node_rows.items():
            res[name] = r = MethodResult(cm, extra)
            log(f"  3d {scene.name} {name:<34} mIoU {100 * r.scores().miou:5.1f}  "
                f"({r.extra['stream_seconds']:.1f} s stream, {r.extra['seconds']:.1f} s query)")
    return res


def _no_depth_input_rows(scene: EvalScene, model: GovNeSF, mname: str, sp: ScenePoints,
                         settings: EvalSettings, record: Callable[..., None],
                         device: torch.device | str) -> None:
    """Rows without any input depth: frustum bounds; DGM and the averaging depth test with the
    model's rendered depth of the stream frames (see ``EvalSettings.no_depth_input``)."""
    pts, K, poses, occluded = sp.xyz, sp.K, sp.world_from_cam, sp.occluded
    t0 = time.perf_counter()
    views, bounds = scene_sources(model, scene, device=device, frustum_range_m=settings.frustum_range_m)
    views = dataclasses.replace(views, depth_m=None)
    with torch.no_grad():
        volume = model.build_volume(views, bounds)
    t_vol = time.perf_counter() - t0
    w, h = scene.image_wh
    s = settings.rendered_depth_stride
    rw, rh = max(1, w // s), max(1, h // s)
    scale = K.new_tensor([rw / w, rh / h, rw / w, rh / h])
    t0 = time.perf_counter()
    rendered, _ = render_depth_maps(model, volume, bounds, (K * scale).to(device), poses.to(device), rw, rh)
    t_depth = time.perf_counter() - t0
    gt_small = F.interpolate(torch.from_numpy(scene.gt_depth_m)[:, None], size=(rh, rw),
                             mode="nearest")[:, 0]
    gt_small = gt_small.to(rendered.device)
    has = (rendered > 0) & (gt_small > 0)
    rel = ((rendered - gt_small).abs() / gt_small.clamp_min(1e-6))[has]
    depth_stats = {"rendered_depth_seconds": t_depth, "volume_seconds": t_vol,
                   "rendered_depth_coverage": float(has.float().mean()),
                   "rendered_depth_median_rel_err": float(rel.median()) if rel.numel() else float("nan"),
                   "rendered_depth_within_25pct": float((rel <= DEPTH_REL_TOL).float().mean()) if rel.numel()
                   else float("nan")}
    for dgm in (False, True):
        t0 = time.perf_counter()
        v = dataclasses.replace(views, depth_m=rendered) if dgm else views
        pb = blend_points(model, v, volume, bounds, pts.to(device), depth_guided_masking=dgm,
                          views_per_point=settings.views_per_point, chunk_size=settings.chunk_points)
        secs = time.perf_counter() - t0
        name = (f"{mname} + rendered-depth DGM (no depth input)" if dgm
                else f"{mname} (no depth, frustum bounds)")
        record(name, pb.ov, secs, occluded_weight=occluded_share(pb, occluded),
               invalid=float((~pb.valid).float().mean()), **depth_stats)
    t0 = time.perf_counter()
    rd = rendered.cpu().numpy()
    views_avg = [OVView(scene.ov[k], scene.K[k], scene.world_from_cam[k], scene.image_wh, rd[k])
                 for k in range(len(scene))]
    feats, nv = average_features(pts, views_avg, use_depth=True, device=device)
    counted = _averaging_mask(pts, K, poses, scene.image_wh, rendered.cpu())
    record(f"Averaging + {mname} rendered-depth test (no depth input)", feats, time.perf_counter() - t0,
           occluded_weight=_uniform_occluded_share(counted, occluded),
           invalid=float((nv == 0).float().mean()), **depth_stats)


def point_occlusion_depths(sp: ScenePoints, image_wh: tuple[int, int], footprint: float) -> Tensor:
    """(N, H, W) float32: each stream frame's z-buffer of the evaluated points, each point over
    ``footprint`` x their median nearest-neighbour spacing (0 = no point): the depth a point is
    tested against for the rows "... + point occlusion (no depth input)" (the node's
    ``model.point_occlusion`` rule, here with the evaluated points as the request)."""
    from mapper.geometry.splat import request_occluder_depths

    return torch.from_numpy(request_occluder_depths(sp.xyz.numpy(), sp.K.numpy(), sp.world_from_cam.numpy(),
                                                    image_wh[0], image_wh[1], footprint,
                                                    threads=torch.get_num_threads()))


def _averaging_mask(pts: Tensor, K: Tensor, poses: Tensor, image_wh: tuple[int, int],
                    depth_m: Tensor | None, border_px: float = AVERAGING_BORDER_PX,
                    depth_rel_tol: float = DEPTH_REL_TOL) -> Tensor:
    """(P, N) bool: the views ``average_features`` counts for each point."""
    n = K.shape[0]
    uv, z = project_points(pts.unsqueeze(0).expand(n, -1, -1), K, invert_pose(poses))
    ok = in_view(uv, z, image_wh[0], image_wh[1], border_px=border_px)
    if depth_m is not None:
        d_wh = (depth_m.shape[-1], depth_m.shape[-2])
        d, _ = sample_nearest(depth_m.unsqueeze(1), scale_uv(uv, image_wh, d_wh))
        d = d.squeeze(-1)
        ok &= (d > 0) & ((d - z).abs() <= depth_rel_tol * d)
    return ok.T


def _evaluate_2d(scene: EvalScene, models: dict[str, GovNeSF], text_emb: Tensor, settings: EvalSettings,
                 log: Callable[[str], None], device: torch.device | str) -> dict[str, MethodResult]:
    novel = scene.novel
    assert novel is not None
    keep = list(range(novel.K.shape[0]))
    if settings.max_novel_views is not None and settings.max_novel_views < len(keep):
        keep = np.linspace(0, len(keep) - 1, settings.max_novel_views).round().astype(int).tolist()
    wh = scene.image_wh
    res: dict[str, MethodResult] = {}
    cms: dict[str, np.ndarray] = {}
    extras: dict[str, dict[str, list[float]]] = {}

    def add(name: str, gt: np.ndarray, pred: np.ndarray, **extra: float) -> None:
        cms[name] = cms.get(name, 0) + confusion_matrix(gt.reshape(-1), pred.reshape(-1))
        for k, v in extra.items():
            extras.setdefault(name, {}).setdefault(k, []).append(v)

    st = settings.pixel_stride
    off = st // 2
    for v in keep:
        gt = novel.label[v][off::st, off::st]  # (h', w') pixel-centre subgrid, as training validates
        target_rgb = torch.from_numpy(novel.rgb[v][off::st, off::st]).double() / 255.0
        if novel.ov is not None:
            full = _labels_2d(upsample_features(novel.ov[v], wh), text_emb)  # (H, W)
            add("SimLSeg at the GT novel view", gt, full[off::st, off::st])
        for mname, model in models.items():
            t0 = time.perf_counter()
            n_src = settings.num_source_views or model.cfg.num_source_views
            views, bounds = scene_sources(model, scene, novel_view_sources(scene, v, n_src), device=device)
            with torch.no_grad():
                volume = model.build_volume(views, bounds)
            t_volume = time.perf_counter() - t0
            true_z = seen = None
            if novel.depth_m is not None:
                true_z = novel.depth_m[v][off::st, off::st]
                if views.depth_m is not None:  # the same pixels for every row of this model
                    seen = seen_by_sources(views, novel.K[v], novel.world_from_cam[v], wh, novel.depth_m[v],
                                           pixel_stride=st).cpu()
            kinds = [(mname, None)]
            if settings.surface_renders:
                kinds.append((f"{mname} at measured surfaces (depth input)", sources_surface_depth(
                    views, novel.K[v], novel.world_from_cam[v], wh, settings.surface_footprint_m)))
            for name, surface in kinds:
                t0 = time.perf_counter()
                with torch.no_grad():
                    rgb_r, ov_r, z_r, at_surface = render_view_full(
                        model, views, volume, bounds, novel.K[v], novel.world_from_cam[v], wh,
                        pixel_stride=st, chunk_rays=settings.chunk_rays, surface_depth_m=surface,
                        n_samples=settings.n_samples, clip_to_volume=settings.clip_to_volume,
                        weight_threshold=settings.weight_threshold)
                secs = time.perf_counter() - t0 + t_volume
                rgb = rgb_r.clamp(0, 1).cpu().double()
                extra = {"psnr": psnr(rgb, target_rgb), "seconds": secs,
                         "surface_share": float(at_surface.float().mean())}
                if min(rgb.shape[:2]) >= 11:
                    extra["ssim"] = ssim(rgb, target_rgb)
                if true_z is not None:
                    extra["depth_median_rel_err"] = _median_rel_err(z_r.cpu(), true_z)
                if seen is not None:
                    extra["seen_share"] = float(seen.float().mean())
                    if bool(seen.any()):
                        extra["psnr_seen"] = psnr(rgb[seen], target_rgb[seen])
                add(name, gt, _labels_2d(ov_r.cpu(), text_emb), **extra)
    for name, cm in cms.items():
        ex = {k: float(np.mean(v)) for k, v in extras.get(name, {}).items()}
        res[name] = MethodResult(np.asarray(cm), ex)
        log(f"  2d {scene.name} {name:<34} mIoU {100 * res[name].scores().miou:5.1f}"
            + "".join(f"  {k} {val:.3g}" for k, val in ex.items()))
    return res


# ---- reporting ----------------------------------------------------------------------------------
def summarise(per_scene: dict[str, dict[str, dict[str, MethodResult]]], styles: dict[str, str],
              class_names: Sequence[str]) -> dict[str, Any]:
    """Average per-scene scores over the scenes of each style.

    Args:
        per_scene: scene -> {"3d"/"2d": method -> MethodResult}; styles: scene -> style.

    Returns:
        JSON-able {"styles": {style: {"3d"/"2d": {method: {miou, macc, oacc, per_class_iou,
        extras..., scenes}}}}, "scenes": {...}}.
    """
    names = list(class_names[:NUM_SCANNET_CLASSES])

    def pack(items: list[MethodResult]) -> dict[str, Any]:
        s = average_over_scenes([m.scores() for m in items])
        d: dict[str, Any] = {"miou": s.miou, "macc": s.macc, "oacc": s.oacc,
                             "per_class_iou": {n: (None if np.isnan(x) else float(x))
                                               for n, x in zip(names, s.iou, strict=False)},
                             "scenes": len(items)}
        keys = {k for m in items for k in m.extra}
        for k in sorted(keys):
            vals = [m.extra[k] for m in items if k in m.extra and not math.isnan(m.extra[k])]
            d[k] = float(np.mean(vals)) if vals else None
        return d

    out: dict[str, Any] = {"styles": {}, "scenes": {}}
    for style in sorted(set(styles.values())):
        scenes = [s for s in per_scene if styles[s] == style]
        block: dict[str, Any] = {}
        for kind in ("2d", "3d"):
            methods: dict[str, list[MethodResult]] = {}
            for s in scenes:
                for m, r in per_scene[s].get(kind, {}).items():
                    methods.setdefault(m, []).append(r)
            block[kind] = {m: pack(v) for m, v in methods.items()}
        out["styles"][style] = block
    for s, kinds in per_scene.items():
        out["scenes"][s] = {"style": styles[s], **{kind: {m: pack([r]) for m, r in res.items()}
                                                   for kind, res in kinds.items()}}
    return out


def _pct(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.1f}"


def format_report(summary: dict[str, Any], *, training_style: str = "apartment") -> str:
    """Markdown tables in the shape of the paper's Tables 1-3 and its ablation."""
    lines: list[str] = []
    styles = summary["styles"]
    order = sorted(styles, key=lambda s: (s != training_style, s))

    def label(style: str) -> str:
        return f"{style} ({'training style' if style == training_style else 'unseen style'})"

    # Table 1: 2D novel views.
    if any(styles[s]["2d"] for s in order):
        lines += ["### Table 1: 2D semantic segmentation and colour at novel views", "",
                  "| style | method | mIoU | mAcc | oAcc | PSNR (dB) | PSNR where a source sees (dB) | SSIM "
                  "| depth error (median rel.) | pixels at a measured surface | s / view |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for s in order:
            for m, r in styles[s]["2d"].items():
                ps = "-" if r.get("psnr") is None else f"{r['psnr']:.2f}"
                ss = "-" if r.get("ssim") is None else f"{r['ssim']:.3f}"
                sec = "-" if r.get("seconds") is None else f"{r['seconds']:.1f}"
                de = "-" if r.get("depth_median_rel_err") is None else f"{r['depth_median_rel_err']:.3f}"
                sh = _pct(r.get("surface_share")) + ("%" if r.get("surface_share") is not None else "")
                pv = "-" if r.get("psnr_seen") is None else f"{r['psnr_seen']:.2f}"
                lines.append(f"| {label(s)} | {m} | {_pct(r['miou'])} | {_pct(r['macc'])} | "
                             f"{_pct(r['oacc'])} | {ps} | {pv} | {ss} | {de} | {sh} | {sec} |")
        lines.append("")
    # Tables 2-3: 3D.
    for i, s in enumerate(order):
        res = styles[s]["3d"]
        if not res:
            continue
        lines += [f"### Table {2 + i}: 3D semantic segmentation at ground-truth points, {label(s)}", "",
                  "| method | mIoU | mAcc | oAcc | weight on occluded views | s / 100k points |",
                  "|---|---|---|---|---|---|"]
        for m, r in res.items():
            occ = "-" if r.get("occluded_weight") is None else f"{100 * r['occluded_weight']:.1f}%"
            t = "-" if r.get("seconds_per_100k") is None else f"{r['seconds_per_100k']:.1f}"
            lines.append(f"| {m} | {_pct(r['miou'])} | {_pct(r['macc'])} | {_pct(r['oacc'])} | {occ} | {t} |")
        lines.append("")
    # Ablation: learned blending vs Distill, training vs unseen style.
    if len(order) >= 2:
        lines += ["### Ablation: learned blending vs Distill across styles (mIoU)", "",
                  "| method | " + " | ".join(label(s) for s in order)
                  + f" | change {order[0]} -> {order[1]} |",
                  "|---|" + "---|" * (len(order) + 1)]
        methods = [m for m in styles[order[0]]["3d"] if m in styles[order[1]]["3d"]
                   and not m.startswith("Averaging")]
        for kind in ("2d", "3d"):
            for m in (methods if kind == "3d" else [m for m in styles[order[0]]["2d"]
                                                    if m in styles[order[1]]["2d"]]):
                vals = [styles[s][kind][m]["miou"] for s in order]
                lines.append(f"| {kind.upper()} {m} | " + " | ".join(_pct(v) for v in vals)
                             + f" | {100 * (vals[1] - vals[0]):+.1f} |")
        lines.append("")
    # Per-class IoU of the key 3D methods.
    cls_methods = ("Averaging (no depth)", "Averaging + depth test")
    for s in order:
        res = styles[s]["3d"]
        keys = [m for m in res if m in cls_methods or not m.startswith("Averaging")]
        if not keys:
            continue
        classes = [c for c, v in res[keys[0]]["per_class_iou"].items() if v is not None]
        lines += [f"### Per-class 3D IoU, {label(s)}", "",
                  "| class | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
        for c in classes:
            lines.append(f"| {c} | " + " | ".join(_pct(res[m]["per_class_iou"].get(c)) for m in keys) + " |")
        lines.append("")
    return "\n".join(lines)

