"""Dense depth from posed RGB: plane-sweep stereo against a few partner keyframes.

Triangulated features (:mod:`mapper.geometry.triangulation`) are accurate but sparse (tens of
points a 160x120 keyframe). Where the image has texture, the known poses give a depth for most
pixels: for every pixel of the reference view and every depth hypothesis, the source views are
sampled where that 3D point projects, and the hypothesis whose patches look most alike wins
(the plane sweep of Collins 1996, with the ZNCC photo-consistency of COLMAP / MVSNet-style
multi-view stereo, here in numpy + OpenCV, no learning, no torch):

1. **hypotheses**: ``planes`` z-depths uniform in inverse depth on ``[near_m, far_m]`` (equal
   disparity steps: the depth resolution a pixel of parallax gives);
2. **warp**: for hypothesis z, the pixel's ray ``z * K^-1 (u, v, 1)`` goes to the world and into
   each source (``cv2.remap``, bilinear); samples outside a source or behind it are invalid;
3. **photo-consistency**: zero-mean normalised cross-correlation (ZNCC) of ``patch_px`` square
   patches (box filters of the products), per source and hypothesis; a source whose sample is
   invalid anywhere in the patch does not count;
4. **aggregation**: the mean of the ``top_k`` best sources' ZNCC (occlusion robust: a source that
   does not see the surface does not veto it); fewer valid sources than ``top_k`` = no score;
5. **winner-take-all + refinement**: the best hypothesis, then a second sweep of
   ``refine_steps`` hypotheses per pixel spanning the coarse steps on either side, and a parabola
   through the best refined score and its neighbours (sub-step depth);
6. **filters** (the pixel gets no depth, 0): score below ``min_ncc``; the reference patch's
   standard deviation below ``min_texture`` (no texture, no stereo); the coarse winner on the
   first or last hypothesis (the surface is outside the range); another coarse hypothesis more
   than ``uniqueness_planes`` steps away scores within ``uniqueness_margin`` (repetitive texture).

Conventions (docs/concepts/conventions.md): pixel (i, j) has its centre at ``(i + 0.5, j + 0.5)``; depth is
z-depth along the optical axis; poses are camera-to-world in the OpenCV optical frame.

Example (a textured wall 2 m in front of two cameras 20 cm apart; tests/mapper/geometry/test_plane_sweep.py)::

    >>> import numpy as np
    >>> from mapper.geometry.config import StereoConfig
    >>> from mapper.geometry.plane_sweep import StereoView, sweep_depth
    >>> rng = np.random.default_rng(0)
    >>> K = np.array([100.0, 100.0, 40.0, 30.0])
    >>> texture = rng.random((60, 80)).astype(np.float32)       # the wall's albedo, seen head-on
    >>> a, b = np.eye(4), np.eye(4)
    >>> b[0, 3] = 0.2
    >>> # camera b sees the wall shifted by f * 0.2 / 2 = 10 px to the left
    >>> gray_b = np.roll(texture, -10, axis=1)
    >>> out = sweep_depth(StereoView(K, a, texture), [StereoView(K, b, gray_b)], 1.0, 4.0,
    ...                   StereoConfig(top_k=1))
    >>> bool(abs(np.median(out.depth_m[out.depth_m > 0]) - 2.0) < 0.02)
    True
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from mapper.geometry.config import StereoConfig
from mapper.geometry.triangulation import backproject

__all__ = [
    "DenseDepth", "StereoView", "agreeing_views", "depth_range", "fill_depth", "gray_image", "sweep_depth",
]


@dataclass(frozen=True)
class StereoView:
    """A posed grayscale image."""

    K: np.ndarray  # (4,) [fx, fy, cx, cy] pixels for this image
    world_from_cam: np.ndarray  # (4, 4) camera-to-world, OpenCV optical frame
    gray: np.ndarray  # (H, W) float32 intensity in [0, 1]


@dataclass(frozen=True)
class DenseDepth:
    """The reference view's depth from the sweep."""

    depth_m: np.ndarray  # (H, W) float32 z-depth, 0 where no depth passed the filters
    score: np.ndarray  # (H, W) float32 aggregated ZNCC of the chosen depth (-1 where none)
    sources: int  # source views used

    @property
    def valid(self) -> np.ndarray:  # (H, W) bool
        return self.depth_m > 0

    @property
    def density(self) -> float:
        """Fraction of the pixels with a depth."""
        return float(np.count_nonzero(self.depth_m > 0)) / max(1, self.depth_m.size)


def gray_image(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W) float32 luminance in [0, 1]."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0


def depth_range(depths_m: np.ndarray, config: StereoConfig) -> tuple[float, float] | None:
    """``(near, far)`` for the sweep from known z-depths of the view (triangulated points): their
    ``range_quantile`` and ``1 - range_quantile`` quantiles widened by ``range_margin``, clamped to
    ``[min_depth_m, max_depth_m]``; None with fewer than ``min_range_points`` depths."""
    d = np.asarray(depths_m, np.float64).reshape(-1)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size < config.min_range_points:
        return None
    lo, hi = np.quantile(d, [config.range_quantile, 1.0 - config.range_quantile])
    near = max(config.min_depth_m, float(lo) / config.range_margin)
    far = min(config.max_depth_m, float(hi) * config.range_margin)
    if far <= near * 1.05:
        far = min(config.max_depth_m, near * 1.5)
    return (near, far) if far > near else None


def _check_view(view: StereoView, name: str) -> None:
    K = np.asarray(view.K, np.float64)
    pose = np.asarray(view.world_from_cam, np.float64)
    if K.shape != (4,) or not np.isfinite(K).all() or K[0] <= 0 or K[1] <= 0:
        raise ValueError(f"{name}: K must be 4 finite numbers with fx, fy > 0, got {K.tolist()}")
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ValueError(f"{name}: world_from_cam must be a finite (4, 4) matrix")
    if view.gray.ndim != 2 or min(view.gray.shape) < 1:
        raise ValueError(f"{name}: gray must have shape (H, W), got {view.gray.shape}")


def _rows_per_call(h: int) -> int:
    """Planes of height ``h`` stacked into one OpenCV image (its sides stay below 32 767)."""
    return max(1, 32_000 // max(1, h))


def _box(images: np.ndarray, patch: int) -> np.ndarray:
    """Mean over ``patch`` x ``patch`` windows of each (H, W) plane of (n, H, W) float32 (reflected
    borders, OpenCV's ``BORDER_REFLECT``). The planes are padded by reflection above and below,
    stacked into one tall image and filtered in one call; the padding rows, where the planes would
    mix, are cut off."""
    n, h, w = images.shape
    r = patch // 2
    out = np.empty_like(images)
    step = _rows_per_call(h + 2 * r)
    for s in range(0, n, step):
        block = np.pad(images[s : s + step], ((0, 0), (r, r), (0, 0)), mode="symmetric")
        m = block.shape[0]
        tall = cv2.boxFilter(
            block.reshape(m * (h + 2 * r), w), -1, (patch, patch), borderType=cv2.BORDER_REFLECT
        )
        out[s : s + m] = tall.reshape(m, h + 2 * r, w)[:, r : r + h]
    return out


def _zncc(
    ref: StereoView,
    source: StereoView,
    depth: np.ndarray,  # (D, H, W) float32 hypotheses
    ref_stats: tuple[np.ndarray, np.ndarray],  # (H, W) patch mean and standard deviation
    rays: np.ndarray,  # (3, H, W) K^-1 (u, v, 1) of the reference pixels
    patch: int,
) -> np.ndarray:  # (D, H, W) float32 ZNCC, NaN where the source does not count
    """ZNCC between the reference patches and the source sampled at each hypothesis."""
    D, H, W = depth.shape
    hs, ws = source.gray.shape
    ref_pose = np.asarray(ref.world_from_cam, np.float64)
    src_pose = np.asarray(source.world_from_cam, np.float64)
    rot_s = src_pose[:3, :3].T
    A = (rot_s @ ref_pose[:3, :3]).astype(np.float32)  # source <- reference rotation
    b = (rot_s @ (ref_pose[:3, 3] - src_pose[:3, 3])).astype(np.float32)
    a = np.einsum("ij,jhw->ihw", A, rays)  # (3, H, W)
    x = depth * a[0] + b[0]
    y = depth * a[1] + b[1]
    z = depth * a[2] + b[2]
    front = z > 1e-6
    z_safe = np.where(front, z, 1.0)
    fx, fy, cx, cy = (float(v) for v in source.K)
    u = fx * x / z_safe + cx  # pixel coordinates, centres at +0.5
    v = fy * y / z_safe + cy
    inside = front & (u >= 0.5) & (u <= ws - 0.5) & (v >= 0.5) & (v <= hs - 0.5)
    map_x = (u - 0.5).astype(np.float32)
    map_y = (v - 0.5).astype(np.float32)
    warped = np.empty((D, H, W), np.float32)
    step = _rows_per_call(H)
    for s in range(0, D, step):  # the planes' maps stacked into one tall map: one call
        m = min(step, D - s)
        warped[s : s + m] = cv2.remap(
            source.gray, map_x[s : s + m].reshape(m * H, W), map_y[s : s + m].reshape(m * H, W),
            cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE,
        ).reshape(m, H, W)  # fmt: skip
    valid_frac = _box(inside.astype(np.float32), patch)
    mean_b = _box(warped, patch)
    mean_bb = _box(warped * warped, patch)
    mean_ab = _box(warped * ref.gray[None], patch)
    mean_a, std_a = ref_stats
    var_b = np.maximum(mean_bb - mean_b * mean_b, 0.0)
    cov = mean_ab - mean_a[None] * mean_b
    ncc = cov / np.sqrt(np.maximum(var_b, 1e-8) * np.maximum(std_a * std_a, 1e-8)[None])
    ncc = np.clip(ncc, -1.0, 1.0)
    return np.where(valid_frac > 1.0 - 1e-4, ncc, np.nan).astype(np.float32)


def _aggregate(scores: np.ndarray, top_k: int) -> np.ndarray:
    """(S, D, H, W) per-source ZNCC (NaN = not counted) -> (D, H, W) mean of the ``top_k`` best,
    -inf where fewer than ``top_k`` sources count."""
    k = min(top_k, scores.shape[0])
    filled = np.where(np.isnan(scores), -np.inf, scores)
    if k == scores.shape[0]:
        best = list(filled)
    elif k <= 4:  # insertion into k running maxima: O(S k) elementwise, no sort along the sources
        best = [np.full(filled.shape[1:], -np.inf, np.float32) for _ in range(k)]
        for x in filled:
            x = x.copy()
            for j in range(k):  # best[0] >= best[1] >= ...: carry the smaller value down
                hi = np.maximum(best[j], x)
                np.minimum(best[j], x, out=x)
                best[j] = hi
    else:
        best = list(-np.partition(-filled, k - 1, axis=0)[:k])
    out = np.sum(best, axis=0) / k
    return np.where(np.isfinite(out), out, -np.inf).astype(np.float32)


def _scores(
    ref: StereoView,
    sources: Sequence[StereoView],
    depth: np.ndarray,
    ref_stats: tuple[np.ndarray, np.ndarray],
    rays: np.ndarray,
    config: StereoConfig,
) -> np.ndarray:  # (D, H, W)
    per_source = np.stack([_zncc(ref, s, depth, ref_stats, rays, config.patch_px) for s in sources])
    return _aggregate(per_source, config.top_k)


def sweep_depth(
    ref: StereoView,
    sources: Sequence[StereoView],
    near_m: float,
    far_m: float,
    config: StereoConfig | None = None,
) -> DenseDepth:
    """Dense z-depth of ``ref`` from ``sources`` by plane sweep (module docstring).

    Args:
        ref: the view whose depth is estimated.
        sources: posed views overlapping it (each may have its own size and intrinsics).
        near_m, far_m: the depth range swept (z-depth, metres, 0 < near < far).
        config: sweep settings (defaults: ``StereoConfig()``).

    Returns:
        :class:`DenseDepth` of ``ref``'s size; without sources every pixel has no depth.
    """
    cfg = config or StereoConfig()
    _check_view(ref, "ref")
    for i, s in enumerate(sources):
        _check_view(s, f"source {i}")
    if not (np.isfinite(near_m) and np.isfinite(far_m) and 0 < near_m < far_m):
        raise ValueError(f"depth range must satisfy 0 < near < far, got near={near_m}, far={far_m}")
    H, W = ref.gray.shape
    none = DenseDepth(np.zeros((H, W), np.float32), np.full((H, W), -1.0, np.float32), len(sources))
    if not sources or len(sources) < cfg.top_k:
        return none
    ref = StereoView(ref.K, ref.world_from_cam, np.ascontiguousarray(ref.gray, np.float32))
    sources = [StereoView(s.K, s.world_from_cam, np.ascontiguousarray(s.gray, np.float32)) for s in sources]
    fx, fy, cx, cy = (float(v) for v in ref.K)
    cols, rows = np.meshgrid(np.arange(W, dtype=np.float32) + 0.5, np.arange(H, dtype=np.float32) + 0.5)
    rays = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)])  # (3, H, W)
    mean_a = _box(ref.gray[None], cfg.patch_px)[0]
    std_a = np.sqrt(np.maximum(_box((ref.gray * ref.gray)[None], cfg.patch_px)[0] - mean_a * mean_a, 0.0))

    # coarse sweep: planes uniform in inverse depth
    inv = np.linspace(1.0 / near_m, 1.0 / far_m, cfg.planes, dtype=np.float64)
    step = float(inv[0] - inv[1])
    planes = np.broadcast_to((1.0 / inv).astype(np.float32)[:, None, None], (cfg.planes, H, W))
    coarse = _scores(ref, sources, planes, (mean_a, std_a), rays, cfg)  # (D, H, W)
    best = np.argmax(coarse, axis=0)  # (H, W)
    best_score = np.take_along_axis(coarse, best[None], 0)[0]
    ok = np.isfinite(best_score) & (best > 0) & (best < cfg.planes - 1)
    if cfg.uniqueness_planes > 0:
        idx = np.arange(cfg.planes)[:, None, None]
        far_away = np.abs(idx - best[None]) > cfg.uniqueness_planes
        rival = np.where(far_away, coarse, -np.inf).max(axis=0)
        ok &= rival < best_score - cfg.uniqueness_margin

    # refinement: refine_steps hypotheses per pixel across one coarse step on either side
    inv_best = inv[best]  # (H, W)
    if cfg.refine_steps > 1:
        offsets = np.linspace(-1.0, 1.0, cfg.refine_steps) * step  # (R,)
        inv_fine = np.maximum(inv_best[None] + offsets[:, None, None], 1e-6)  # (R, H, W)
        fine = _scores(ref, sources, (1.0 / inv_fine).astype(np.float32), (mean_a, std_a), rays, cfg)
        j = np.argmax(fine, axis=0)
        fine_step = float(offsets[1] - offsets[0])
    else:
        fine, j, fine_step = coarse, best, -step
        inv_fine = np.broadcast_to(inv[:, None, None], coarse.shape)
    n = fine.shape[0]
    jc = np.clip(j, 1, n - 2)
    c0 = np.take_along_axis(fine, jc[None], 0)[0]
    cm = np.take_along_axis(fine, (jc - 1)[None], 0)[0]
    cp = np.take_along_axis(fine, (jc + 1)[None], 0)[0]
    with np.errstate(invalid="ignore", divide="ignore"):  # -inf scores (no source) give NaN here
        denom = cm - 2.0 * c0 + cp
        shift = np.where((denom < 0) & np.isfinite(denom) & (j == jc), 0.5 * (cm - cp) / denom, 0.0)
    shift = np.clip(np.nan_to_num(shift), -0.5, 0.5)
    inv_j = np.take_along_axis(inv_fine, j[None], 0)[0]
    # fine_step: the inverse-depth change from one hypothesis index to the next
    inv_sub = np.where(j == jc, np.take_along_axis(inv_fine, jc[None], 0)[0] + shift * fine_step, inv_j)
    score = np.take_along_axis(fine, j[None], 0)[0]
    ok &= np.isfinite(score) & (score >= cfg.min_ncc) & (std_a >= cfg.min_texture) & (inv_sub > 0)
    depth = np.where(ok, 1.0 / np.maximum(inv_sub, 1e-9), 0.0).astype(np.float32)
    return DenseDepth(depth, np.where(ok, score, -1.0).astype(np.float32), len(sources))


def agreeing_views(
    K: np.ndarray,  # (4,) the reference view's intrinsics
    world_from_cam: np.ndarray,  # (4, 4) its pose
    depth_m: np.ndarray,  # (H, W) its z-depth, 0 = none
    others: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],  # (K (4,), pose (4, 4), depth (h, w))
    rel_tol: float,
) -> tuple[np.ndarray, np.ndarray]:  # (H, W) int32 agreeing, (H, W) int32 checked
    """Multi-view geometric consistency of a depth map: each pixel's 3D point is projected into the
    other views' depth maps (nearest pixel); a view *checks* the pixel when it has a depth there
    and the point is in front of it, and *agrees* when that depth is within ``rel_tol`` (relative)
    of the point's z-depth in that view. Returns (agreeing views, checking views) per pixel."""
    d = np.asarray(depth_m, np.float32)
    H, W = d.shape
    agree = np.zeros((H, W), np.int32)
    checked = np.zeros((H, W), np.int32)
    rows, cols, world = backproject(d, K, world_from_cam)
    if rows.size == 0 or not others:
        return agree, checked
    for K_o, pose_o, depth_o in others:
        pose_o = np.asarray(pose_o, np.float64)
        p = (world - pose_o[:3, 3]) @ pose_o[:3, :3]  # (n, 3) in the other camera
        h, w = depth_o.shape
        front = p[:, 2] > 1e-6
        zz = np.where(front, p[:, 2], 1.0)
        u = np.floor(float(K_o[0]) * p[:, 0] / zz + float(K_o[2])).astype(np.int64)
        v = np.floor(float(K_o[1]) * p[:, 1] / zz + float(K_o[3])).astype(np.int64)
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        measured = np.zeros(rows.size, np.float64)
        measured[inside] = depth_o[v[inside], u[inside]]
        has = inside & (measured > 0)
        ok = has & (np.abs(p[:, 2] - measured) <= rel_tol * measured)
        checked[rows[has], cols[has]] += 1
        agree[rows[ok], cols[ok]] += 1
    return agree, checked


def fill_depth(
    gray: np.ndarray,  # (H, W) float32 intensity in [0, 1]
    depth_m: np.ndarray,  # (H, W) float32 z-depth, 0 = none
    radius_px: int,
    *,
    sigma_gray: float = 0.05,
    min_weight: float = 0.5,
    max_spread: float = 0.1,
    step_px: int = 1,
) -> np.ndarray:  # (H, W) float32, 0 where still none
    """Fill the holes of a sparse depth map along the image (joint bilateral interpolation in
    inverse depth): a pixel without depth takes the weighted mean inverse depth of the depths within
    ``radius_px`` (every ``step_px``-th offset), weighted by a Gaussian of the intensity difference
    (``sigma_gray``) and of the distance (sigma ``radius_px / 2``). It stays empty when the weights
    sum below ``min_weight`` (too few similar neighbours) or the neighbours' inverse depths spread
    more than ``max_spread`` of their mean (relative standard deviation: a depth edge). Pixels with a
    depth keep it. Surfaces of one colour carry the depths found at their texture and borders."""
    g = np.asarray(gray, np.float32)
    d = np.asarray(depth_m, np.float32)
    if g.shape != d.shape or g.ndim != 2:
        raise ValueError(f"gray {g.shape} and depth {d.shape} must be the same (H, W)")
    if radius_px < 0 or step_px < 1 or sigma_gray <= 0:
        raise ValueError("radius_px must be >= 0, step_px >= 1 and sigma_gray > 0")
    have = d > 0
    if radius_px == 0 or not have.any():
        return d.copy()
    H, W = d.shape
    r = radius_px
    inv = np.where(have, 1.0 / np.maximum(d, 1e-9), 0.0).astype(np.float32)
    pad = ((r, r), (r, r))
    inv_p = np.pad(inv, pad)
    have_p = np.pad(have.astype(np.float32), pad)
    g_p = np.pad(g, pad, mode="edge")
    sw = np.zeros((H, W), np.float32)
    s1 = np.zeros((H, W), np.float32)
    s2 = np.zeros((H, W), np.float32)
    k_gray = -0.5 / (sigma_gray * sigma_gray)
    k_dist = -0.5 / (0.25 * r * r)
    for dy in range(-r, r + 1, step_px):
        for dx in range(-r, r + 1, step_px):
            if dx * dx + dy * dy > r * r:
                continue
            sl = (slice(r + dy, r + dy + H), slice(r + dx, r + dx + W))
            diff = g_p[sl] - g
            w = have_p[sl] * np.exp(k_gray * diff * diff + k_dist * (dx * dx + dy * dy))
            v = inv_p[sl]
            sw += w
            s1 += w * v
            s2 += w * v * v
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / sw
        spread = np.sqrt(np.maximum(s2 / sw - mean * mean, 0.0)) / mean
    ok = ~have & (sw >= min_weight) & (mean > 0) & (spread <= max_spread)
    out = d.copy()
    out[ok] = 1.0 / mean[ok]
    return out
