"""The per-(point, view) sampling of ``GovNeSF.sample_views_indexed`` as one compiled CPU kernel.

For P points, each with its own N source views (``view_idx``; padding slots masked), the point
answers need every pair's projection, visibility mask (inside the image, in front of the camera,
optionally the depth test of Depth-Guided Masking), bilinear colour and 2D-feature samples, the
unit direction and distance from the camera. The torch path builds these from (N*P, 4, 4)
gathers of the cameras and one ``blend_from_maps`` pass per map; here each pair is done in one
go, in parallel over blocks of pairs, with the cameras read in place.

Arithmetic follows the torch path in float32 (``project_points``: ``R p + t``, ``x / z * f + c``,
the clamp to +-6e4; ``in_view``; the depth test's nearest pixel; the bilinear corners and weights
of ``bilinear_corners`` as in :func:`mapper.model.ops.average_kernel.blend_kernel`), so the masks
are the same and the samples agree to float rounding (tests/mapper/test_sample_kernel.py). One
difference: a masked pair's colour and features are 0 here (the network never reads them: masked
views carry no key in the attention and no weight in the blends).
"""

from __future__ import annotations

import numba
import numpy as np

from mapper.model.ops.average_kernel import corners, launch
from mapper.model.ops.geometry import _UV_LIMIT as UV_LIMIT

__all__ = ["sample_pairs", "warm_up"]

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_UV_LIMIT = np.float32(UV_LIMIT)  # project_points' clamp of pixel coordinates


@numba.njit(cache=True, boundscheck=False, inline="always")
def _taps(table, base, map_w, map_h, u, v, out, c0, i):  # pragma: no cover - compiled
    """out[c0 + c, i] = the bilinear sample of ``table``'s map at (u, v) (that map's pixels), the
    corners and weights of ``blend_kernel`` (:func:`mapper.model.ops.average_kernel.corners`)."""
    r00, r01, r10, r11, tx, ty = corners(u, v, map_w, map_h)
    w00, w01 = (_F1 - tx) * (_F1 - ty), tx * (_F1 - ty)
    w10, w11 = (_F1 - tx) * ty, tx * ty
    a, b, c, d = table[base + r00], table[base + r01], table[base + r10], table[base + r11]
    for k in range(table.shape[1]):
        out[c0 + k, i] = _F0 + (w00 * a[k] + w01 * b[k] + w10 * c[k] + w11 * d[k])


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _sample_kernel(
    pts,  # (P, 3) float32 world points
    view_idx,  # (N, P) int64: slot-major, the view behind each pair
    slot_mask,  # (N, P) bool: False for padding slots
    cam_from_world,  # (M, 4, 4) float32
    K,  # (M, 4) float32 fx, fy, cx, cy
    centres,  # (M, 3) float32 camera centres (world)
    width,  # float32 image width (pixels the uv refer to)
    height,  # float32
    eps,  # float32: smallest depth in front of the camera
    rgb_table, rgb_w, rgb_h, rgb_sx, rgb_sy,  # (M * h * w, 3), its map size, map / image scale
    feat_table, feat_w, feat_h, feat_sx, feat_sy,  # (M * h * w, F), ...
    use_depth,  # bool
    depth,  # (M * dh * dw,) float32, or (0,) without
    d_w, d_h, d_sx, d_sy,  # depth map size and scale
    depth_ratio,  # float32: |z - d| <= ratio * d agrees
    samples,  # out (3 + F, N * P) float32: colour then features, pair n * P + p
    mask,  # out (N * P,) bool
    dirs,  # out (3, N * P) float32 (channel-first: the point kernel's layout)
    dist,  # out (N * P,) float32
    uv,  # out (N * P, 2) float32
    block,  # int: pairs per parallel task
):  # pragma: no cover - compiled
    n_slots, n_pts = view_idx.shape
    n_pairs = n_slots * n_pts
    n_blocks = (n_pairs + block - 1) // block
    n_feat = feat_table.shape[1]
    for blk in numba.prange(n_blocks):
        for i in range(blk * block, min(n_pairs, (blk + 1) * block)):
            n = i // n_pts
            p = i - n * n_pts
            view = view_idx[n, p]
            x, y, z = pts[p, 0], pts[p, 1], pts[p, 2]
            R = cam_from_world[view]
            cx = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + R[0, 3]
            cy = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + R[1, 3]
            cz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + R[2, 3]
            zs = cz if cz > eps else eps
            u = min(max(cx / zs * K[view, 0] + K[view, 2], -_UV_LIMIT), _UV_LIMIT)
            v = min(max(cy / zs * K[view, 1] + K[view, 3], -_UV_LIMIT), _UV_LIMIT)
            uv[i, 0] = u
            uv[i, 1] = v
            seen = slot_mask[n, p] and cz > eps and u >= _F0 and u <= width and v >= _F0 and v <= height
            if seen and use_depth:
                col = np.int64(min(max(np.floor(u * d_sx), _F0), np.float32(d_w - 1)))
                row = np.int64(min(max(np.floor(v * d_sy), _F0), np.float32(d_h - 1)))
                measured = depth[view * (d_w * d_h) + row * d_w + col]
                if np.isfinite(measured) and measured > _F0:
                    seen = abs(cz - measured) <= depth_ratio * measured
            mask[i] = seen
            ox, oy, oz = x - centres[view, 0], y - centres[view, 1], z - centres[view, 2]
            d = np.sqrt(ox * ox + oy * oy + oz * oz)
            dist[i] = d
            dd = max(d, np.float32(1e-9))
            dirs[0, i] = ox / dd
            dirs[1, i] = oy / dd
            dirs[2, i] = oz / dd
            if seen:
                _taps(rgb_table, view * rgb_w * rgb_h, rgb_w, rgb_h, u * rgb_sx, v * rgb_sy, samples, 0, i)
                fb = view * feat_w * feat_h
                _taps(feat_table, fb, feat_w, feat_h, u * feat_sx, v * feat_sy, samples, 3, i)
            else:
                for c in range(3 + n_feat):
                    samples[c, i] = _F0


def sample_pairs(
    pts: np.ndarray,  # (P, 3) float32
    view_idx: np.ndarray,  # (N, P) int64, slot-major
    slot_mask: np.ndarray,  # (N, P) bool
    cam_from_world: np.ndarray,  # (M, 4, 4) float32
    K: np.ndarray,  # (M, 4) float32
    centres: np.ndarray,  # (M, 3) float32
    image_wh: tuple[int, int],
    eps: float,
    rgb: tuple[np.ndarray, tuple[int, int]],  # (M * h * w, 3) channel-last table, its map (w, h)
    features: tuple[np.ndarray, tuple[int, int]],  # (M * h * w, F), its map (w, h)
    depth: tuple[np.ndarray, tuple[int, int]] | None,  # (M, dh, dw) depth maps, (dw, dh); None: no test
    depth_ratio: float,
    *,
    threads: int,
    block: int = 1024,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every (point, slot) pair at once (see the module docstring). Returns, pair ``n * P + p``:
    samples (3 + F, N * P) float32 (colour, then features; 0 where masked), mask (N * P,) bool,
    dirs (3, N * P), dist (N * P,), uv (N * P, 2) in ``image_wh`` pixels. Arguments are checked by
    the caller (``GovNeSF.sample_views_indexed``)."""
    N, P = view_idx.shape
    W, H = image_wh
    (rgb_t, (rw, rh)), (feat_t, (fw, fh)) = rgb, features
    n_feat = feat_t.shape[1]
    samples = np.empty((3 + n_feat, N * P), np.float32)
    mask = np.empty(N * P, np.bool_)
    dirs = np.empty((3, N * P), np.float32)
    dist = np.empty(N * P, np.float32)
    uv = np.empty((N * P, 2), np.float32)
    if depth is None:
        d_flat, (dw, dh) = np.zeros(0, np.float32), (1, 1)
    else:
        d_flat, (dw, dh) = np.ascontiguousarray(depth[0], np.float32).reshape(-1), depth[1]

    def scale(to: int, frm: int) -> np.float32:
        return np.float32(to / frm)  # scale_uv's factor (a float32 of the ratio)

    if N * P:
        with launch(threads):
            _sample_kernel(
                np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(view_idx, np.int64),
                np.ascontiguousarray(slot_mask, np.bool_), np.ascontiguousarray(cam_from_world, np.float32),
                np.ascontiguousarray(K, np.float32), np.ascontiguousarray(centres, np.float32),
                np.float32(W), np.float32(H), np.float32(eps),
                np.ascontiguousarray(rgb_t, np.float32), int(rw), int(rh), scale(rw, W), scale(rh, H),
                np.ascontiguousarray(feat_t, np.float32), int(fw), int(fh), scale(fw, W), scale(fh, H),
                depth is not None, d_flat, int(dw), int(dh), scale(dw, W), scale(dh, H),
                np.float32(depth_ratio), samples, mask, dirs, dist, uv, int(block),
            )
    return samples, mask, dirs, dist, uv


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now, on a one-pair problem."""
    one = np.zeros((1, 1), np.int64)
    sample_pairs(np.zeros((1, 3), np.float32), one, np.ones((1, 1), np.bool_),
                 np.eye(4, dtype=np.float32)[None], np.ones((1, 4), np.float32), np.zeros((1, 3), np.float32),
                 (1, 1), 1e-6,
                 (np.zeros((1, 3), np.float32), (1, 1)), (np.zeros((1, 2), np.float32), (1, 1)),
                 (np.ones((1, 1, 1), np.float32), (1, 1)), 0.1, threads=1)
