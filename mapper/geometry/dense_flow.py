"""Dense points from posed RGB: DIS optical flow between keyframes, triangulated with the known poses.

Sparse features give a few points per 160 x 120 keyframe; most pixels of a room's image still
move consistently between two nearby keyframes. This module matches every textured pixel of a new
keyframe into one or two partner keyframes and triangulates it (numpy float64 and OpenCV, no torch):

1. :func:`select_flow_partners`: earlier views that see at least ``min_overlap`` of the new view's
   probe grid and lie at least ``min_baseline_m`` away, ranked by overlap times
   min(1, parallax / ``target_parallax_deg``) (:func:`mapper.geometry.triangulation.select_partners`).
2. :func:`flow_matches`: OpenCV's DIS optical flow (``cv2.DISOpticalFlow``, preset ``preset``) from the
   new image to the partner and back; a pixel is kept when its 5 x 5 patch is textured
   (``min_texture``), its match lands inside the partner and the round trip returns within
   ``fb_sigmas * sqrt(2) * flow_sigma_px``. Pixel centres at +0.5 (docs/concepts/conventions.md).
3. :func:`triangulate_flow`: ``cv2.triangulatePoints`` (linear) with ``P = K [R | t]``. The expected
   angular error of a ray, ``sigma_ray(r) = sqrt((flow_sigma_px / f)^2 + 2 sigma_rot^2 +
   2 (pose_sigma_m / r)^2)`` (two views' independent pose errors), sets every test: the point lies
   in front of both cameras and within ``max_depth_m``, reprojects within ``reprojection_sigmas *
   f * sigma_ray`` in both, its rays meet at ``min_parallax_deg`` or more, and its 1-sigma depth
   error ``r * sigma_ray / sin(parallax)`` is at most ``max_sigma_rel`` of its depth (so the
   parallax a point needs grows with the expected pose error).
4. :func:`flow_depth`: the estimates of a pixel from several partners are fused by inverse variance
   when they agree within ``agree_sigmas`` combined sigmas, and the pixel is dropped when they do
   not; a pixel needs ``min_views`` views (the keyframe included).

A textureless pair or a pair that does not overlap gives no points (no texture, no flow inside the
partner, or no parallax), not a guess.

Example (a textured plane seen from two poses; tests/mapper/geometry/test_dense_flow.py)::

    view = flow_view(rgb, K, world_from_cam, config.max_width)        # the new keyframe
    out = flow_depth(view, [partner_view], config)                    # out.depth_m (h, w), 0 = none
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from mapper.geometry.config import DenseFlowConfig, TriangulationConfig
from mapper.geometry.triangulation import PosedView, select_partners, triangulate_rays

__all__ = [
    "FlowDepth",
    "FlowPairPoints",
    "FlowView",
    "dis_flow",
    "flow_depth",
    "flow_matches",
    "flow_view",
    "ray_sigma",
    "select_flow_partners",
    "triangulate_flow",
]

_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass(frozen=True)
class FlowView:
    """A keyframe at the flow's working size."""

    K: np.ndarray  # (4,) [fx, fy, cx, cy] at the working size, pixel centres at +0.5
    world_from_cam: np.ndarray  # (4, 4) camera-to-world, OpenCV optical frame
    gray: np.ndarray  # (h, w) uint8

    @property
    def posed(self) -> PosedView:
        """The view as a :class:`PosedView` (for partner selection and projection)."""
        h, w = self.gray.shape
        return PosedView(np.asarray(self.K, np.float64), np.asarray(self.world_from_cam, np.float64), w, h)


@dataclass(frozen=True)
class FlowPairPoints:
    """Pixels of the new view triangulated against one partner."""

    pixel: np.ndarray  # (N,) int64 flat index into the new view's (h, w) image
    depth_m: np.ndarray  # (N,) float64 z-depth in the new view
    sigma_m: np.ndarray  # (N,) float64 1-sigma depth uncertainty along the ray
    parallax_deg: np.ndarray  # (N,) float64
    reprojection_px: np.ndarray  # (N,) float64 larger of the two reprojection errors

    def __len__(self) -> int:
        return int(self.pixel.shape[0])


@dataclass(frozen=True)
class FlowDepth:
    """A keyframe's dense points as maps of its working size (0 / NaN where no point)."""

    depth_m: np.ndarray  # (h, w) float32 z-depth, 0 = none
    sigma_m: np.ndarray  # (h, w) float32 1-sigma depth uncertainty, 0 = none
    n_views: np.ndarray  # (h, w) int8 views that agree (the keyframe included), 0 = none
    matched: int = 0
    """Pixels that passed the texture and forward-backward checks, summed over the partners."""
    partners: int = 0

    def __len__(self) -> int:
        return int(np.count_nonzero(self.depth_m))


def flow_view(rgb: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, max_width: int) -> FlowView:
    """``rgb`` (H, W, 3) uint8 (or (H, W) gray) at most ``max_width`` wide (area downscale, ``K``
    scaled with it) as a :class:`FlowView`."""
    img = np.asarray(rgb)
    if img.ndim == 3:
        gray = cv2.cvtColor(np.ascontiguousarray(img[..., :3], np.uint8), cv2.COLOR_RGB2GRAY)
    elif img.ndim == 2:
        gray = np.ascontiguousarray(img, np.uint8)
    else:
        raise ValueError(f"rgb must be (H, W, 3) or (H, W), got shape {img.shape}")
    k = np.asarray(K, np.float64).reshape(4)
    height, width = gray.shape
    if width > max_width:
        w, h = max_width, max(1, round(height * max_width / width))
        gray = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA)
        k = k * np.array([w / width, h / height, w / width, h / height])
    pose = np.asarray(world_from_cam, np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ValueError(f"world_from_cam must be a finite (4, 4) matrix, got shape {pose.shape}")
    return FlowView(k, pose, np.asarray(gray, np.uint8))


def _at_size(view: FlowView, shape: tuple[int, int]) -> FlowView:
    """``view`` resized to ``shape`` (h, w) with its K scaled (partners of another resolution)."""
    h, w = view.gray.shape
    if (h, w) == shape:
        return view
    gray = cv2.resize(view.gray, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    k = np.asarray(view.K, np.float64) * np.array([shape[1] / w, shape[0] / h, shape[1] / w, shape[0] / h])
    return replace(view, K=k, gray=gray)


def select_flow_partners(
    new: PosedView, candidates: Sequence[PosedView], config: DenseFlowConfig
) -> list[int]:
    """Indices of up to ``max_partners`` candidates, best first (overlap x baseline, see above)."""
    tri = TriangulationConfig(max_partners=config.max_partners, min_baseline_m=config.min_baseline_m,
                              min_overlap=config.min_overlap, target_parallax_deg=config.target_parallax_deg,
                              min_depth_m=config.min_depth_m)
    return select_partners(new, candidates, tri)


def dis_flow(a: np.ndarray, b: np.ndarray, preset: str) -> np.ndarray:
    """(h, w, 2) float32 DIS optical flow from ``a`` to ``b`` ((h, w) uint8 each): pixel (r, c) of
    ``a`` moves to ``(c, r) + flow[r, c]`` in ``b``."""
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"images must be (h, w) of one shape, got {a.shape} and {b.shape}")
    dis = cv2.DISOpticalFlow_create(_PRESETS[preset])  # type: ignore[attr-defined]
    return np.asarray(dis.calc(a, b, None), np.float32)


def _texture(gray: np.ndarray) -> np.ndarray:
    """(h, w) float32 standard deviation of each 5 x 5 patch (intensities on a 0..1 scale)."""
    g = gray.astype(np.float32) / 255.0
    mean = cv2.blur(g, (5, 5), borderType=cv2.BORDER_REFLECT)
    sq = cv2.blur(g * g, (5, 5), borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(sq - mean * mean, 0.0))


def flow_matches(
    a: FlowView, b: FlowView, config: DenseFlowConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense correspondences of ``a``'s pixels (every ``stride_px``) in ``b`` (same image size):
    ``(pixel (N,) int64 flat index in a, uv_a (N, 2), uv_b (N, 2))`` float64 pixel coordinates
    (centres at +0.5), those passing the texture, inside and forward-backward checks."""
    h, w = a.gray.shape
    forward = dis_flow(a.gray, b.gray, config.preset)
    backward = dis_flow(b.gray, a.gray, config.preset)
    rows, cols = np.mgrid[0:h:config.stride_px, 0:w:config.stride_px]
    rows, cols = rows.ravel(), cols.ravel()
    fwd = forward[rows, cols].astype(np.float64)
    xb = cols + fwd[:, 0]  # OpenCV coordinates (integer centres)
    yb = rows + fwd[:, 1]
    inside = (xb >= 0) & (xb <= w - 1) & (yb >= 0) & (yb <= h - 1)
    back = cv2.remap(backward, xb.astype(np.float32)[:, None], yb.astype(np.float32)[:, None],
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2).astype(np.float64)
    round_trip = np.hypot(fwd[:, 0] + back[:, 0], fwd[:, 1] + back[:, 1])
    fb_max = config.fb_sigmas * math.sqrt(2.0) * config.flow_sigma_px
    keep = inside & (round_trip <= fb_max) & (_texture(a.gray)[rows, cols] >= config.min_texture)
    keep &= np.isfinite(fwd).all(axis=1)
    rows, cols = rows[keep], cols[keep]
    uv_a = np.stack([cols + 0.5, rows + 0.5], axis=-1).astype(np.float64)
    uv_b = np.stack([xb[keep] + 0.5, yb[keep] + 0.5], axis=-1)
    return (rows * w + cols).astype(np.int64), uv_a, uv_b


def ray_sigma(range_m: np.ndarray, focal_px: float, config: DenseFlowConfig) -> np.ndarray:
    """(N,) expected angular error (radians, 1 sigma) of a ray to a point ``range_m`` away: the flow's
    pixel error plus both views' pose errors (rotation, and the centre's shift seen from the point)."""
    rot = math.radians(config.pose_sigma_deg)
    with np.errstate(divide="ignore"):
        shift = config.pose_sigma_m / np.maximum(np.asarray(range_m, np.float64), 1e-9)
    return np.sqrt((config.flow_sigma_px / focal_px) ** 2 + 2.0 * rot**2 + 2.0 * shift**2)


def triangulate_flow(
    a: FlowView, b: FlowView, uv_a: np.ndarray, uv_b: np.ndarray, config: DenseFlowConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate correspondences ``uv_a`` (N, 2) / ``uv_b`` (N, 2) and test them (module docstring):
    ``(keep (N,) bool, depth_m (N,), sigma_m (N,), parallax_deg (N,), reprojection_px (N,))``
    float64, the last four meaningful where ``keep``."""
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    if uv_a.shape != uv_b.shape:
        raise ValueError(f"uv_a {uv_a.shape} and uv_b {uv_b.shape} must have the same shape")
    if uv_a.shape[0] == 0:
        empty = np.zeros(0)
        return np.zeros(0, bool), empty, empty, empty, empty
    r = triangulate_rays(a.posed, b.posed, uv_a, uv_b)
    za, parallax, reproj = r.depth_a, r.parallax_deg, r.reprojection_px
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = ray_sigma(r.range_m, r.focal_px, config)
        sigma = r.range_m * ray / np.sin(np.radians(parallax))
        keep = (
            r.finite
            & np.isfinite(r.xyz).all(axis=1)
            & (za >= config.min_depth_m) & (r.depth_b >= config.min_depth_m)
            & (za <= config.max_depth_m)
            & (reproj <= config.reprojection_sigmas * r.focal_px * ray)
            & (parallax >= config.min_parallax_deg)
            & (sigma <= config.max_sigma_rel * za)
        )
    keep &= np.isfinite(sigma)
    return keep, za, sigma, parallax, reproj


def flow_pair(a: FlowView, b: FlowView, config: DenseFlowConfig) -> tuple[FlowPairPoints, int]:
    """``a``'s pixels triangulated against ``b`` (resized to ``a``'s size when it differs) and the
    number of pixels matched before triangulation."""
    b = _at_size(b, a.gray.shape)
    pixel, uv_a, uv_b = flow_matches(a, b, config)
    keep, depth, sigma, parallax, reproj = triangulate_flow(a, b, uv_a, uv_b, config)
    return FlowPairPoints(pixel[keep], depth[keep], sigma[keep], parallax[keep], reproj[keep]), len(pixel)


def flow_depth(new: FlowView, partners: Sequence[FlowView], config: DenseFlowConfig) -> FlowDepth:
    """``new``'s dense points against ``partners`` (see the module docstring), as maps of its size."""
    h, w = new.gray.shape
    size = h * w
    total_w = np.zeros(size)  # sum of inverse variances of the agreeing estimates
    total_wd = np.zeros(size)
    views = np.zeros(size, np.int64)
    best_d = np.zeros(size)
    best_s = np.full(size, np.inf)
    conflict = np.zeros(size, bool)
    matched = 0
    estimates: list[FlowPairPoints] = []
    for partner in partners:
        pts, n = flow_pair(new, partner, config)
        matched += n
        estimates.append(pts)
        better = pts.sigma_m < best_s[pts.pixel]
        best_s[pts.pixel[better]] = pts.sigma_m[better]
        best_d[pts.pixel[better]] = pts.depth_m[better]
    for pts in estimates:  # each estimate against the pixel's most certain one
        ref_d, ref_s = best_d[pts.pixel], best_s[pts.pixel]
        agree = np.abs(pts.depth_m - ref_d) <= config.agree_sigmas * np.hypot(pts.sigma_m, ref_s)
        conflict[pts.pixel[~agree]] = True
        inv = 1.0 / np.maximum(pts.sigma_m[agree], 1e-9) ** 2
        np.add.at(total_w, pts.pixel[agree], inv)
        np.add.at(total_wd, pts.pixel[agree], inv * pts.depth_m[agree])
        np.add.at(views, pts.pixel[agree], 1)
    ok = (views + 1 >= config.min_views) & ~conflict & (total_w > 0)
    depth = np.zeros(size, np.float32)
    sigma = np.zeros(size, np.float32)
    depth[ok] = total_wd[ok] / total_w[ok]
    sigma[ok] = 1.0 / np.sqrt(total_w[ok])
    n_views = np.where(ok, views + 1, 0).astype(np.int8)
    return FlowDepth(depth.reshape(h, w), sigma.reshape(h, w), n_views.reshape(h, w), matched, len(partners))
