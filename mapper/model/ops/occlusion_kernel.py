"""Depth Guided Masking against a request's own points, as compiled CPU kernels (numba).

Two stages of ``segment_points`` with a depth test on keyframes without input depth
(``model.point_occlusion``, ``queries.point_occlusion``; docs/concepts/rgb-only.md):

* :func:`zbuffer_views`: every view's z-buffer of the points, the depth of
  :func:`mapper.geometry.splat.splat_points` (each point in front of the camera covers a square of
  half width ``round(0.5 * fx * footprint / z)`` pixels, at most ``MAX_REACH_PX``; a pixel keeps the
  smallest z), in parallel over views, float64 arithmetic as the numpy reference;
* :func:`depth_test_matrix`: for every (point, view), whether the point projects into the view and
  passes the DGM test against a depth map (the view's depth at the point's nearest pixel agrees
  within ``ratio`` of it, or there is none), in parallel over blocks of points: the kernel of
  :func:`mapper.kernels.average_kernel.in_view_matrix` (which is it without depth).

Neither materialises anything of size (points, views) beyond the boolean answer. The numpy / torch
paths they replace spent 8 ms a view on 100k points (z-buffers) and 0.35 s on 106k points x 84
views (the test); tests/mapper/model/ops/test_occlusion_kernel.py checks both against them.
"""

from __future__ import annotations

import numba
import numpy as np

from mapper.kernels.average_kernel import depth_test_launch, launch

__all__ = ["depth_test_matrix", "warm_up", "zbuffer_views"]


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _zbuffer_kernel(pts, cam_from_world, K, footprint, max_reach, out):  # pragma: no cover - compiled
    # pts (N, 3) float64; cam_from_world (M, 4, 4) float64; K (M, 4) float64; out (M, H, W) float64 (inf)
    n_views, height, width = out.shape
    for v in numba.prange(n_views):
        R = cam_from_world[v]
        fx, fy, cx, cy = K[v, 0], K[v, 1], K[v, 2], K[v, 3]
        zb = out[v]
        for i in range(pts.shape[0]):
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            cz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + R[2, 3]
            if not cz > 1e-3:
                continue
            px = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + R[0, 3]
            py = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + R[1, 3]
            u = fx * px / cz + cx
            vv = fy * py / cz + cy
            if not (u > -max_reach - 1 and u < width + max_reach + 1
                    and vv > -max_reach - 1 and vv < height + max_reach + 1):
                continue
            reach_f = np.rint(0.5 * fx * footprint / cz)
            reach = int(min(max(reach_f, 0.0), float(max_reach)))
            col = int(np.floor(u))
            row = int(np.floor(vv))
            for dy in range(-reach, reach + 1):
                r = row + dy
                if r < 0 or r >= height:
                    continue
                for dx in range(-reach, reach + 1):
                    c = col + dx
                    if c < 0 or c >= width:
                        continue
                    if cz < zb[r, c]:
                        zb[r, c] = cz


def zbuffer_views(
    pts: np.ndarray,  # (N, 3) world points
    cam_from_world: np.ndarray,  # (M, 4, 4)
    K: np.ndarray,  # (M, 4) [fx, fy, cx, cy] for width x height
    width: int,
    height: int,
    footprint_m: float,
    max_reach_px: int,
    *,
    threads: int,
) -> np.ndarray:  # (M, H, W) float32 z-depth, 0 = no point
    """Every view's z-buffer of ``pts`` (the depth :func:`mapper.geometry.splat.splat_points` gives
    with the same footprint, for each view), one compiled launch for all views on ``threads``
    threads (0: numba's current count)."""
    out = np.full((cam_from_world.shape[0], height, width), np.inf)
    pts = np.ascontiguousarray(pts, np.float64)
    keep = np.isfinite(pts).all(axis=1)
    with launch(threads):
        _zbuffer_kernel(np.ascontiguousarray(pts[keep]), np.ascontiguousarray(cam_from_world, np.float64),
                        np.ascontiguousarray(K, np.float64), float(footprint_m), int(max_reach_px), out)
    out[~np.isfinite(out)] = 0.0
    return out.astype(np.float32)


def depth_test_matrix(
    pts: np.ndarray,  # (P, 3) float32 world points
    cam_from_world: np.ndarray,  # (M, 4, 4) float32
    K: np.ndarray,  # (M, 4) float32, for image_wh
    image_wh: tuple[int, int],
    eps: float,
    depth_m: np.ndarray,  # (M, H, W) float32 at image_wh, 0 = none
    ratio: float,
    *,
    threads: int,
    block: int = 256,
) -> np.ndarray:  # (P, M) bool
    """In view (:func:`mapper.kernels.average_kernel.in_view_matrix`) and passing the DGM test of
    ``GovNeSF.sample_views`` against ``depth_m`` (nearest pixel; a pixel without depth passes)."""
    return depth_test_launch(pts, cam_from_world, K, image_wh, eps, depth_m, ratio, threads, block)


def warm_up() -> None:
    """Compile (or load from numba's cache) both kernels now, on one-point problems."""
    eye = np.eye(4)[None]
    zbuffer_views(np.zeros((1, 3)), eye, np.ones((1, 4)), 1, 1, 0.0, 2, threads=1)
    depth_test_matrix(np.zeros((1, 3), np.float32), eye.astype(np.float32), np.ones((1, 4), np.float32),
                      (1, 1), 1e-6, np.zeros((1, 1, 1), np.float32), 0.25, threads=1)
