"""OpenScene-2D style baselines: plain multi-view averaging of OV features at 3D points.

For every point, the OV features of the views it projects into (10 px border cut) are sampled
bilinearly and averaged; with ``use_depth`` only views whose measured depth at that pixel agrees
with the point's depth (|depth - z| <= 0.25 * depth, nearest-pixel lookup) count. The mapper's
``average`` and ``average_depth`` segmentation methods call ``average_features``.

Chunked over points (views are streamed per chunk), so 100k points x 100 views stays within a
few hundred MB.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.model.ops.checks import check_shape
from mapper.model.ops.geometry import (
    in_view,
    invert_pose,
    project_points,
    sample_bilinear,
    sample_nearest,
    scale_uv,
)

__all__ = ["OVView", "average_features"]


class OVView(NamedTuple):
    """One view for averaging (a plain tuple in this order works too)."""

    ov: np.ndarray | Tensor
    """(h, w, D) OV feature map (any resolution; it covers the whole image)."""
    K: np.ndarray | Tensor
    """(4,) [fx, fy, cx, cy] for the full image of size ``image_wh``."""
    world_from_cam: np.ndarray | Tensor
    """(4, 4) camera-to-world pose."""
    image_wh: tuple[int, int]
    """(W, H) of the image ``K`` refers to."""
    depth_m: np.ndarray | Tensor | None
    """(H', W') z-depth in metres (0 = unknown), any resolution covering the image; or None."""


def _as_tensor(x: np.ndarray | Tensor, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(x, Tensor):
        return x.to(device=device, dtype=dtype)
    # read-only arrays (e.g. the protocol's decoded frames) are copied: torch needs writable memory
    return torch.from_numpy(np.require(x, requirements=["C", "W"])).to(device=device, dtype=dtype)


def average_features(
    points: np.ndarray | Tensor,
    views: Sequence[OVView | tuple],
    *,
    use_depth: bool,
    border_px: float = 10.0,
    depth_rel_tol: float = 0.25,
    chunk: int = 16384,
    distance_power: float = 0.0,
    view_weights: np.ndarray | Tensor | None = None,
    device: str | torch.device = "cpu",
) -> tuple[Tensor, Tensor]:
    """Multi-view average of OV features at 3D points (OpenScene-2D baseline).

    Args:
        points: (N, 3) world points (m).
        views: V views, each ``OVView`` or a tuple ``(ov (h, w, D), K (4,), world_from_cam
            (4, 4), (W, H), depth_m (H', W') | None)``; all ``ov`` share D.
        use_depth: keep a view only where |depth - z| <= depth_rel_tol * depth at the point's
            pixel (nearest pixel; depth 0 = unknown fails the test). Views without depth are
            then skipped entirely.
        border_px: points projecting closer than this (full-image pixels) to the edge are out.
        depth_rel_tol: relative depth tolerance of the depth test (0.25 in OpenScene/GOV-NeSF).
        chunk: points per chunk (bounds memory: about chunk x D x 8 bytes per view sample).
        distance_power: weight each view by z ** -distance_power (0 = plain mean); the
            "visible views weighted by distance" oracle of the reference numbers uses > 0.
        view_weights: optional (V, N) float >= 0 (or bool): multiplies view v's weight for point
            n; 0 / False excludes it on top of the other tests (e.g. a ray-cast visibility
            oracle, or an oracle weighting by known view quality). Rows follow ``views``.
        device: torch device for the computation.

    Returns:
        features: (N, D) float32, L2-normalised weighted mean (zero rows where no view counts).
        n_views: (N,) int64, number of views that counted for each point.
    """
    if depth_rel_tol < 0:
        raise ValueError(f"depth_rel_tol {depth_rel_tol} must be >= 0")
    if chunk < 1:
        raise ValueError(f"chunk {chunk} must be >= 1")
    if border_px < 0:
        raise ValueError(f"border_px {border_px} must be >= 0")
    device = torch.device(device)
    pts = _as_tensor(points, torch.float32, device)
    check_shape(pts, "N 3", "points must have shape (N points, xyz)")
    parsed = [OVView(*v) for v in views]
    for i, v in enumerate(parsed):
        check_shape(v.ov, "h w D", f"view {i}: ov")
        if len(v.image_wh) != 2 or min(v.image_wh) < 1:
            raise ValueError(f"view {i}: image_wh must be (W, H) >= 1, got {v.image_wh}")
    dims = {int(v.ov.shape[-1]) for v in parsed}
    if len(dims) > 1:
        raise ValueError(f"views have OV features of different dimensions {sorted(dims)}")
    dim = dims.pop() if dims else 0
    n_pts = pts.shape[0]
    feats = torch.zeros(n_pts, dim, dtype=torch.float32, device=device)
    n_views = torch.zeros(n_pts, dtype=torch.int64, device=device)
    view_ids = [i for i, v in enumerate(parsed) if not use_depth or v.depth_m is not None]
    vw = None
    if view_weights is not None:
        vw = _as_tensor(view_weights, torch.float32, device)
        check_shape(vw, "V N", "view_weights must have shape (V views, N points)",
                    {"V": len(parsed), "N": n_pts})
        if not bool((vw >= 0).all()):
            raise ValueError("view_weights must be >= 0")
        vw = vw[view_ids]
    parsed = [parsed[i] for i in view_ids]
    if not parsed or n_pts == 0:
        return feats, n_views

    # Per-view constants once (small): poses, intrinsics; maps are converted per chunk.
    cam_from_world = invert_pose(torch.stack([_as_tensor(v.world_from_cam, torch.float32, device)
                                              for v in parsed]))  # (V, 4, 4)
    Ks = torch.stack([_as_tensor(v.K, torch.float32, device) for v in parsed])  # (V, 4)

    for start in range(0, n_pts, chunk):
        p = pts[start:start + chunk]  # (n, 3)
        acc = torch.zeros(p.shape[0], dim, dtype=torch.float32, device=device)
        wsum = torch.zeros(p.shape[0], dtype=torch.float32, device=device)
        count = torch.zeros(p.shape[0], dtype=torch.int64, device=device)
        uv_all, z_all = project_points(p, Ks, cam_from_world)  # (V, n, 2), (V, n)
        for i, v in enumerate(parsed):
            width, height = int(v.image_wh[0]), int(v.image_wh[1])
            uv, z = uv_all[i], z_all[i]
            ok = in_view(uv, z, width, height, border_px=border_px)  # (n,)
            if vw is not None:
                ok &= vw[i, start:start + chunk] > 0
            if not bool(ok.any()):
                continue
            idx = ok.nonzero().squeeze(1)
            uv_ok, z_ok = uv[idx], z[idx]
            if use_depth:
                assert v.depth_m is not None  # checked when the views were parsed
                depth = _as_tensor(v.depth_m, torch.float32, device)  # (H', W')
                duv = scale_uv(uv_ok, (width, height), (depth.shape[1], depth.shape[0]))
                d, _ = sample_nearest(depth[None], duv)  # (m, 1)
                d = d[:, 0]
                keep = (d > 0) & ((d - z_ok).abs() <= depth_rel_tol * d)
                idx, uv_ok, z_ok = idx[keep], uv_ok[keep], z_ok[keep]
                if idx.numel() == 0:
                    continue
            ov = _as_tensor(v.ov, torch.float32, device).permute(2, 0, 1)  # (D, h, w)
            fuv = scale_uv(uv_ok, (width, height), (ov.shape[2], ov.shape[1]))
            vals, _ = sample_bilinear(ov, fuv)  # (m, D)
            w = z_ok.clamp_min(1e-6) ** (-distance_power) if distance_power else torch.ones_like(z_ok)
            if vw is not None:
                w = w * vw[i, start:start + chunk][idx]
            acc.index_add_(0, idx, vals * w[:, None])
            wsum.index_add_(0, idx, w)
            count.index_add_(0, idx, torch.ones_like(idx))
        seen = count > 0
        acc[seen] /= wsum[seen, None]
        feats[start:start + chunk] = F.normalize(acc, dim=1) * seen[:, None]
        n_views[start:start + chunk] = count
    return feats, n_views
