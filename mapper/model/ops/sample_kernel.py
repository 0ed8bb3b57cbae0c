"""The per-(point, view) sampling of ``GovNeSF.sample_views_indexed`` as one compiled CPU kernel.

For P points, each with its own N source views (``view_idx``; padding slots masked), the point
answers need every pair's projection, visibility mask (inside the image, in front of the camera,
optionally the depth test of Depth-Guided Masking), bilinear colour and 2D-feature samples, the
unit direction and distance from the camera. The torch path builds these from (N*P, 4, 4)
gathers of the cameras and one ``blend_from_maps`` pass per map; here each pair is done in one
go, in parallel over blocks of pairs, with the cameras read in place.

Arithmetic follows the torch path in float32 (``project_points``: ``R p + t``, ``x / z * f + c``,
the clamp to +-6e4; ``in_view``; the depth test's nearest pixel; the bilinear corners and weights
of ``bilinear_corners`` as in :func:`mapper.kernels.average_kernel.blend_kernel`), so the masks
are the same and the samples agree to float rounding (tests/mapper/model/ops/test_sample_kernel.py). One
difference: a masked pair's colour and features are 0 here (the network never reads them: masked
views carry no key in the attention and no weight in the blends).
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from mapper.kernels.average_kernel import corners, launch
from mapper.model.ops.geometry import _UV_LIMIT as UV_LIMIT

__all__ = ["PairArgs", "pair_args", "sample_pair", "sample_pairs", "warm_up"]

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_UV_LIMIT = np.float32(UV_LIMIT)  # project_points' clamp of pixel coordinates


@numba.njit(cache=True, boundscheck=False, inline="always")
def _taps(maps, view, u, v, out, i):  # pragma: no cover - compiled
    """out[c, i] = the bilinear sample of ``view``'s map of ``maps`` (table, w, h, sx, sy) at image
    pixel (u, v), the corners and weights of ``blend_kernel``
    (:func:`mapper.kernels.average_kernel.corners`)."""
    table, map_w, map_h, sx, sy = maps
    base = view * map_w * map_h
    r00, r01, r10, r11, tx, ty = corners(u * sx, v * sy, map_w, map_h)
    w00, w01 = (_F1 - tx) * (_F1 - ty), tx * (_F1 - ty)
    w10, w11 = (_F1 - tx) * ty, tx * ty
    a, b, c, d = table[base + r00], table[base + r01], table[base + r10], table[base + r11]
    for k in range(table.shape[1]):
        out[k, i] = _F0 + (w00 * a[k] + w01 * b[k] + w10 * c[k] + w11 * d[k])


@numba.njit(cache=True, boundscheck=False, inline="always")
def sample_pair(
    x, y, z,  # float32 world point
    view,  # int: its view
    slot_ok,  # bool: False for a padding slot
    cameras,  # (cam_from_world (M, 4, 4), K (M, 4), centres (M, 3), width, height, eps) float32
    rgb,  # (table (M * h * w, 3), w, h, sx, sy): the colour maps, their size, map / image scale
    rgb_out,  # out (3, *) float32: colour, pair i's column
    feat,  # (table (M * h * w, F), w, h, sx, sy): the 2D feature maps
    feat_out,  # out (F, *) float32
    depth,  # (use_depth, (M * dh * dw,) float32 or (0,), dw, dh, sx, sy, ratio): the DGM test
    mask,  # out (*,) bool
    dirs,  # out (3, *) float32 unit directions from the camera
    dist,  # out (*,) float32 distances from the camera
    uv,  # out (*, 2) float32 pixel coordinates
    i,  # int: the pair's column in the outputs
):  # pragma: no cover - compiled
    """One (point, view) pair (see the module docstring) into column ``i`` of the outputs (the
    argument groups as tuples: a call of more than 30 arguments is not inlined)."""
    cam_from_world, K, centres, width, height, eps = cameras
    use_depth, depth_t, d_w, d_h, d_sx, d_sy, depth_ratio = depth
    R = cam_from_world[view]
    cx = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + R[0, 3]
    cy = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + R[1, 3]
    cz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + R[2, 3]
    zs = cz if cz > eps else eps
    u = min(max(cx / zs * K[view, 0] + K[view, 2], -_UV_LIMIT), _UV_LIMIT)
    v = min(max(cy / zs * K[view, 1] + K[view, 3], -_UV_LIMIT), _UV_LIMIT)
    uv[i, 0] = u
    uv[i, 1] = v
    seen = slot_ok and cz > eps and u >= _F0 and u <= width and v >= _F0 and v <= height
    if seen and use_depth:
        col = np.int64(min(max(np.floor(u * d_sx), _F0), np.float32(d_w - 1)))
        row = np.int64(min(max(np.floor(v * d_sy), _F0), np.float32(d_h - 1)))
        measured = depth_t[view * (d_w * d_h) + row * d_w + col]
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
        _taps(rgb, view, u, v, rgb_out, i)
        _taps(feat, view, u, v, feat_out, i)
    else:
        for c in range(rgb_out.shape[0]):
            rgb_out[c, i] = _F0
        for c in range(feat_out.shape[0]):
            feat_out[c, i] = _F0


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _sample_kernel(
    pts,  # (P, 3) float32 world points
    view_idx,  # (N, P) int64: slot-major, the view behind each pair
    slot_mask,  # (N, P) bool: False for padding slots
    cameras,  # (cam_from_world (M, 4, 4), K (M, 4) fx fy cx cy, centres (M, 3), width, height, eps)
    rgb,  # (table (M * h * w, 3), w, h, sx, sy)
    feat,  # (table (M * h * w, F), w, h, sx, sy)
    depth,  # (use_depth, (M * dh * dw,) or (0,), dw, dh, sx, sy, ratio)
    rgb_out,  # out (3, N * P) float32 colour, pair n * P + p
    feat_out,  # out (F, N * P) float32 features
    mask,  # out (N * P,) bool
    dirs,  # out (3, N * P) float32 (channel-first: the point kernel's layout)
    dist,  # out (N * P,) float32
    uv,  # out (N * P, 2) float32
    block,  # int: pairs per parallel task
):  # pragma: no cover - compiled
    n_slots, n_pts = view_idx.shape
    n_pairs = n_slots * n_pts
    n_blocks = (n_pairs + block - 1) // block
    for blk in numba.prange(n_blocks):
        for i in range(blk * block, min(n_pairs, (blk + 1) * block)):
            n = i // n_pts
            p = i - n * n_pts
            sample_pair(pts[p, 0], pts[p, 1], pts[p, 2], view_idx[n, p], slot_mask[n, p], cameras,
                        rgb, rgb_out, feat, feat_out, depth, mask, dirs, dist, uv, i)


class PairArgs(NamedTuple):
    """:func:`sample_pair`'s argument groups (:func:`pair_args` makes them)."""

    cameras: tuple  # (cam_from_world, K, centres, width, height, eps)
    rgb: tuple  # (table, w, h, sx, sy)
    feat: tuple  # (table, w, h, sx, sy)
    depth: tuple  # (use_depth, flat depths, dw, dh, sx, sy, ratio)


def pair_args(
    cam_from_world: np.ndarray,  # (M, 4, 4) float32
    K: np.ndarray,  # (M, 4) float32
    centres: np.ndarray,  # (M, 3) float32
    image_wh: tuple[int, int],
    eps: float,
    rgb: tuple[np.ndarray, tuple[int, int]],  # (M * h * w, 3) channel-last table, its map (w, h)
    features: tuple[np.ndarray, tuple[int, int]],  # (M * h * w, F), its map (w, h)
    depth: tuple[np.ndarray, tuple[int, int]] | None,  # (M, dh, dw) depth maps, (dw, dh); None: no test
    depth_ratio: float,
) -> PairArgs:
    """:func:`sample_pair`'s ``cameras``, ``rgb``, ``feat`` and ``depth`` groups, contiguous
    float32."""
    W, H = image_wh

    def scale(to: int, frm: int) -> np.float32:
        return np.float32(to / frm)  # scale_uv's factor (a float32 of the ratio)

    def maps(m: tuple[np.ndarray, tuple[int, int]]) -> tuple[np.ndarray, int, int, np.float32, np.float32]:
        table, (w, h) = m
        return np.ascontiguousarray(table, np.float32), int(w), int(h), scale(w, W), scale(h, H)

    if depth is None:
        d_flat, (dw, dh) = np.zeros(0, np.float32), (1, 1)
    else:
        d_flat, (dw, dh) = np.ascontiguousarray(depth[0], np.float32).reshape(-1), depth[1]
    cameras = (np.ascontiguousarray(cam_from_world, np.float32), np.ascontiguousarray(K, np.float32),
               np.ascontiguousarray(centres, np.float32), np.float32(W), np.float32(H), np.float32(eps))
    depth_args = (depth is not None, d_flat, int(dw), int(dh), scale(dw, W), scale(dh, H),
                  np.float32(depth_ratio))
    return PairArgs(cameras, maps(rgb), maps(features), depth_args)


def sample_pairs(
    pts: np.ndarray,  # (P, 3) float32
    view_idx: np.ndarray,  # (N, P) int64, slot-major
    slot_mask: np.ndarray,  # (N, P) bool
    pairs: PairArgs,  # the cameras and maps (pair_args)
    *,
    threads: int,
    block: int = 1024,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every (point, slot) pair's samples, pair n * P + p (slot-major, as ``view_idx``):
    samples (3 + F, N * P) float32 (colour, then features; 0 where masked), mask (N * P,) bool,
    dirs (3, N * P), dist (N * P,), uv (N * P, 2) in the image's pixels. Arguments are checked by
    the caller (``GovNeSF.sample_views_indexed``)."""
    N, P = view_idx.shape
    samples = np.empty((3 + pairs.feat[0].shape[1], N * P), np.float32)  # colour rows, then feature rows
    mask = np.empty(N * P, np.bool_)
    dirs = np.empty((3, N * P), np.float32)
    dist = np.empty(N * P, np.float32)
    uv = np.empty((N * P, 2), np.float32)
    if N * P:
        with launch(threads):
            _sample_kernel(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(view_idx, np.int64),
                           np.ascontiguousarray(slot_mask, np.bool_), *pairs, samples[:3], samples[3:], mask,
                           dirs, dist, uv, int(block))
    return samples, mask, dirs, dist, uv


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now, on a one-pair problem."""
    one = np.zeros((1, 1), np.int64)
    pairs = pair_args(np.eye(4, dtype=np.float32)[None], np.ones((1, 4), np.float32),
                      np.zeros((1, 3), np.float32), (1, 1), 1e-6, (np.zeros((1, 3), np.float32), (1, 1)),
                      (np.zeros((1, 2), np.float32), (1, 1)), (np.ones((1, 1, 1), np.float32), (1, 1)), 0.1)
    sample_pairs(np.zeros((1, 3), np.float32), one, np.ones((1, 1), np.bool_), pairs, threads=1)
