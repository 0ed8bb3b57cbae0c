"""Visibility carving of the global map: what a depth image sees through is no longer there.

A keyframe with input depth measures, at every pixel, the first surface along the pixel's ray.
A map point that projects into the image in front of that surface (``z_point < depth - margin``)
lies in space the camera has just seen through: whatever was there moved away, or was noise.
Each such point loses evidence: its confidence (``weight``, and the feature weight with it) is
multiplied by ``1 - (1 - carve_decay) * q``, ``q`` the quality weight an observation at the point's
distance would have (1 up to ``near_m``, ``exp(-(d - near_m) / falloff_m)`` beyond: a far ray
proves less). A voxel whose confidence falls below ``carve_min_weight`` is removed. A voxel seen
many times needs proportionally more see-throughs (``log(weight / carve_min_weight) /
-log(carve_decay)``: 9 for a weight of 20 at the defaults), and a surface that is seen again gains
its weight back, so occasional noise does not erode a static scene.

What is never carved:

- points on or behind the measured surface: the margin is ``max(carve_margin_voxels *
  voxel_size_m, carve_margin_rel * depth)`` (the voxel mean lies up to half a voxel off the
  surface; depth noise grows with depth);
- points at a depth edge or next to a pixel without valid depth: the test uses the smallest depth
  of the pixel's 3 x 3 neighbourhood, and a pixel with an invalid neighbour (no return, outside
  ``[min_depth_m, max_depth_m]``) or on the image's outer row or column carves nothing, so the
  rim of a foreground object is not eaten into by the background next to it;
- points outside the frustum or beyond the farthest valid depth: only the voxels in the bounding
  box of the frustum up to that depth are candidates (:func:`mapper.map.voxels.box_rows`, a
  binary search per grid column of the map's sorted keys), so the cost follows the frustum, not
  the map.

Rendered and triangulated depth (keyframes without input depth) do not carve: their errors are
not independent of the map they were made from. Features fused later into a voxel
(``integrate_features``) are not scaled by the see-throughs before them.

Removed rows are refilled by the map's last rows (:func:`remove_rows`), whose feature stamps are
renewed, so a snapshot renormalises only those rows' features, not every row after the first hole.

>>> import numpy as np
>>> from types import SimpleNamespace
>>> depth = np.full((24, 32), 3.0, np.float32)                  # a wall 3 m ahead, seen through
>>> kf = SimpleNamespace(K=np.array([30.0, 30.0, 16.0, 12.0]), world_from_cam=np.eye(4), depth_m=depth)
>>> z = see_through_depths(depth, 0.1, 8.0)
>>> idx, dist = points_seen_through(np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 2.95]]), z, kf, 0.1, 0.1, 0.05)
>>> idx.tolist()                                                   # 1.5 m is carved, 2.95 m is on it
[0]
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from scipy.ndimage import minimum_filter

from mapper.map.voxels import box_rows

# The keyframe (``mapper.map.global_map.KeyframeLike``) and the config (``GlobalMapConfig``) are
# typed ``Any`` here: global_map imports this module, and naming its types would close a cycle.
KeyframeLike = Any
GlobalMapConfig = Any

__all__ = ["carve", "changed_region", "frustum_box", "points_seen_through", "remove_rows", "see_through",
           "see_through_depths", "warm_up"]

EDGE_PX = 1
"""A pixel carves with the smallest depth within this many pixels of it (and not at all when one of
them has no valid depth or lies outside the image)."""


def see_through_depths(depth: np.ndarray, min_depth_m: float, max_depth_m: float) -> np.ndarray:
    """(H, W) float64: per pixel the smallest depth of its ``(2 * EDGE_PX + 1)**2`` neighbourhood,
    0 (carves nothing) where one of those pixels is invalid (non-finite, outside ``[min_depth_m,
    max_depth_m]``) or outside the image."""
    z = np.asarray(depth, np.float64)
    valid = np.isfinite(z) & (z >= min_depth_m) & (z <= max_depth_m)
    return minimum_filter(np.where(valid, z, 0.0), size=2 * EDGE_PX + 1, mode="constant", cval=0.0)


def frustum_box(
    K: np.ndarray,  # noqa: N803 - (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray,  # (4, 4)
    width: int,
    height: int,
    far_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned bounding box (min (3,), max (3,)) of the camera's frustum up to z-depth
    ``far_m``: the camera centre and the image corners at that depth."""
    fx, fy, cx, cy = (float(v) for v in K)
    u = np.array([0.0, width, 0.0, width])
    v = np.array([0.0, 0.0, height, height])
    corners = np.stack([(u - cx) / fx * far_m, (v - cy) / fy * far_m, np.full(4, far_m)], axis=1)
    pose = np.asarray(world_from_cam, np.float64)
    world = np.concatenate([corners @ pose[:3, :3].T + pose[:3, 3], pose[None, :3, 3]])
    return world.min(axis=0), world.max(axis=0)


def changed_region(
    K: np.ndarray,  # noqa: N803 - (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray,  # (4, 4)
    width: int,
    height: int,
    depth_m: np.ndarray | None,  # (H, W) metres, or None
    min_depth_m: float,
    max_depth_m: float,
    *,
    include_camera: bool = False,
    stride: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """World axis-aligned box (min (3,), max (3,)) of what a keyframe can change in the map: its
    valid depth pixels (every ``stride``-th, in ``[min_depth_m, max_depth_m]``) back-projected, with
    ``include_camera`` (carving clears the space in front of them) the camera centre too; without
    depth, or with no valid pixel, its frustum up to ``max_depth_m`` (:func:`frustum_box`).

    >>> K, depth = np.array([10., 10., 2., 2.]), np.full((4, 4), 2.0)
    >>> lo, hi = changed_region(K, np.eye(4), 4, 4, depth, 0.1, 8.0, stride=1)
    >>> lo.round(2).tolist(), hi.round(2).tolist()
    ([-0.3, -0.3, 2.0], [0.3, 0.3, 2.0])
    """
    pose = np.asarray(world_from_cam, np.float64)
    if depth_m is not None:
        z = np.asarray(depth_m, np.float64)[::stride, ::stride]
        rows, cols = np.nonzero(np.isfinite(z) & (z >= min_depth_m) & (z <= max_depth_m))
        if rows.size:
            fx, fy, cx, cy = (float(v) for v in K)
            d = z[rows, cols]
            u, v = cols * stride + 0.5, rows * stride + 0.5
            cam = np.stack([(u - cx) / fx * d, (v - cy) / fy * d, d], axis=1)
            world = cam @ pose[:3, :3].T + pose[:3, 3]
            if include_camera:
                world = np.concatenate([world, pose[None, :3, 3]])
            return world.min(axis=0), world.max(axis=0)
    return frustum_box(K, pose, width, height, max_depth_m)


@numba.njit(boundscheck=False, cache=True, nogil=True)
def _seen_through(xyz, rows, rot, trans, intr, safe_depth, min_depth_m, margin_m,
                  margin_rel):  # pragma: no cover - compiled
    """Compiled core of :func:`points_seen_through` over ``xyz[rows]``: (a mask over ``rows``, the
    distances of the rows it marks, 0 elsewhere)."""
    height, width = safe_depth.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    mask = np.zeros(rows.shape[0], np.bool_)
    dist = np.zeros(rows.shape[0], np.float64)
    for k in range(rows.shape[0]):
        r = rows[k]
        px, py, pz = xyz[r, 0] - trans[0], xyz[r, 1] - trans[1], xyz[r, 2] - trans[2]
        z = px * rot[0, 2] + py * rot[1, 2] + pz * rot[2, 2]  # R^T (p - t)
        if not z >= min_depth_m:
            continue
        x = px * rot[0, 0] + py * rot[1, 0] + pz * rot[2, 0]
        y = px * rot[0, 1] + py * rot[1, 1] + pz * rot[2, 1]
        u = np.floor(fx * x / z + cx)
        v = np.floor(fy * y / z + cy)
        if not (u >= 0 and u < width and v >= 0 and v < height):
            continue
        d = safe_depth[int(v), int(u)]
        if d > 0 and z < d - max(margin_m, margin_rel * d):
            mask[k] = True
            dist[k] = np.sqrt(x * x + y * y + z * z)
    return mask, dist


def warm_up() -> None:
    """Compile (or load from numba's cache) the see-through kernel on a one-point problem (float32
    positions, as the map holds them)."""
    _seen_through(np.zeros((1, 3), np.float32), np.zeros(1, np.int64), np.eye(3), np.zeros(3), np.ones(4),
                  np.ones((1, 1)), 0.1, 0.1, 0.05)


def points_seen_through(
    xyz: np.ndarray,  # (n, 3) world metres
    safe_depth: np.ndarray,  # (H, W) from see_through_depths
    keyframe: KeyframeLike,
    min_depth_m: float,
    margin_m: float,
    margin_rel: float,
    rows: np.ndarray | None = None,  # (m,) int64 the rows of xyz to test; None: all
) -> tuple[np.ndarray, np.ndarray]:
    """Of the points ``xyz[rows]``, those the keyframe sees through: (their indices into ``rows``
    (k,) int64, their distances from the camera (k,) float64). A point is seen through when it is
    at least ``min_depth_m`` in front of the camera, projects into a pixel (pixel ``i`` covers
    ``[i, i + 1)`` in the protocol's pixel-centre-at-+0.5 convention) whose ``safe_depth`` is
    valid, and its z-depth is below that depth minus ``max(margin_m, margin_rel * depth)``. One
    compiled pass over the rows (no (m, 3) temporaries)."""
    pose = np.asarray(keyframe.world_from_cam, np.float64)
    rows = np.arange(xyz.shape[0], dtype=np.int64) if rows is None else np.asarray(rows, np.int64)
    mask, dist = _seen_through(np.asarray(xyz), rows, np.ascontiguousarray(pose[:3, :3]),
                               np.ascontiguousarray(pose[:3, 3]), np.asarray(keyframe.K, np.float64),
                               np.asarray(safe_depth, np.float64), float(min_depth_m), float(margin_m),
                               float(margin_rel))
    idx = np.flatnonzero(mask)
    return idx, dist[idx]


def see_through(
    config: GlobalMapConfig,
    keyframe: KeyframeLike,
    sorted_keys: np.ndarray,  # (n,) int64 the map's sorted voxel keys
    sorted_rows: np.ndarray,  # (n,) int64 their rows
    xyz: np.ndarray,  # (>= n, 3) the map's positions by row
) -> tuple[np.ndarray, np.ndarray]:
    """The map rows a keyframe with input depth sees through and the factor (float32, in
    ``[carve_decay, 1)``) their confidence is multiplied by (module docstring). No depth: none."""
    none = np.zeros(0, np.int64), np.zeros(0, np.float32)
    if keyframe.depth_m is None or sorted_keys.shape[0] == 0:
        return none
    depth = see_through_depths(keyframe.depth_m, config.min_depth_m, config.max_depth_m)
    far = float(depth.max())
    if far <= 0:
        return none
    height, width = depth.shape
    box_min, box_max = frustum_box(keyframe.K, keyframe.world_from_cam, width, height, far)
    rows = box_rows(sorted_keys, sorted_rows, box_min, box_max, config.voxel_size_m)
    margin_m = config.carve_margin_voxels * config.voxel_size_m
    idx, dist = points_seen_through(xyz, depth, keyframe, config.min_depth_m, margin_m,
                                    config.carve_margin_rel, rows)
    quality = np.exp(-np.maximum(dist - config.near_m, 0.0) / config.falloff_m)
    return rows[idx], (1.0 - (1.0 - config.carve_decay) * quality).astype(np.float32)


def remove_rows(
    arrays: list[np.ndarray | None],  # per-row arrays (None: skipped), the first n rows in use
    keys: np.ndarray,  # one of them: each row's voxel key
    n: int,
    rows: np.ndarray,  # rows to remove (distinct, < n)
    sorted_keys: np.ndarray,
    sorted_rows: np.ndarray,
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Remove ``rows`` in place: the last rows that stay move into their places (so only the moved
    rows change, not every row after the first removed one, as a compaction would), the freed
    tail is zeroed. Returns (rows in use, the rows that received a moved row, the sorted keys and
    their rows without the removed keys)."""
    rows = np.unique(np.asarray(rows, np.int64))
    new_n = n - rows.shape[0]
    holes = rows[rows < new_n]
    tail = np.arange(new_n, n, dtype=np.int64)
    sources = tail[~np.isin(tail, rows, assume_unique=True)]  # as many as holes
    removed_keys, moved_keys = keys[rows], keys[sources]
    for arr in arrays:
        if arr is not None:
            arr[holes] = arr[sources]
            arr[new_n:n] = 0
    at = np.searchsorted(sorted_keys, removed_keys)
    sorted_keys, sorted_rows = np.delete(sorted_keys, at), np.delete(sorted_rows, at)
    sorted_rows[np.searchsorted(sorted_keys, moved_keys)] = holes
    return new_n, holes, sorted_keys, sorted_rows


def carve(
    config: GlobalMapConfig,
    keyframe: KeyframeLike,
    arrays: dict[str, np.ndarray | None],  # the map's per-row arrays by field name, the first n in use
    n: int,
    sorted_keys: np.ndarray,
    sorted_rows: np.ndarray,
    version: int,
) -> tuple[int, np.ndarray, np.ndarray, int]:
    """Carve what ``keyframe`` sees through from a map's per-row arrays, in place
    (:class:`mapper.map.global_map.GlobalSemanticMap`'s ``_xyz``, ``_weight``, ``_feat_weight``,
    ``_keys``, ``_feat_stamp``, ...): the rows seen through are multiplied by their factor
    (:func:`see_through`), those below ``carve_min_weight`` removed (:func:`remove_rows`); the rows
    that received a moved row get feature stamp ``version`` (their features changed). Returns (rows
    in use, sorted keys, their rows, rows removed)."""
    weight, feat_weight, xyz = arrays["_weight"], arrays["_feat_weight"], arrays["_xyz"]
    keys, stamp = arrays["_keys"], arrays["_feat_stamp"]
    assert weight is not None and feat_weight is not None and xyz is not None
    assert keys is not None and stamp is not None
    rows, factor = see_through(config, keyframe, sorted_keys, sorted_rows, xyz)
    weight[rows] *= factor
    feat_weight[rows] *= factor
    gone = rows[weight[rows] < config.carve_min_weight]
    if gone.size == 0:
        return n, sorted_keys, sorted_rows, 0
    new_n, holes, sorted_keys, sorted_rows = remove_rows(list(arrays.values()), keys, n, gone,
                                                         sorted_keys, sorted_rows)
    stamp[holes] = version
    return new_n, sorted_keys, sorted_rows, int(gone.size)
