"""Z-buffered splats of world points into a camera, and the see-through test of a splat.

Pure numpy functions (no torch, no node state): the node's ``render`` uses them to find the
surface each pixel sees among measured points (:func:`mapper.node.queries.surface_depth`: the
global map's, or an RGB-only window's triangulated and plane-sweep points), and its map labels
use :func:`splat_points` for pixels the render found no surface in. :func:`fill_holes` closes
small gaps between point footprints.

Conventions (docs/concepts/conventions.md): ``K = [fx, fy, cx, cy]`` for a ``width x height`` image,
``world_from_cam`` camera-to-world in the OpenCV optical frame, z-depth along the optical axis.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = [
    "MAX_REACH_PX", "REF_DEPTH_M", "check_camera", "fill_holes", "fill_nearest", "occluder_depths",
    "point_spacing", "remove_speckles", "request_occluder_depths", "scaled_camera", "see_through",
    "splat_points", "splat_scale", "upsample_nearest",
]

MAX_REACH_PX = 2
"""A point covers at most (2 * MAX_REACH_PX + 1)^2 pixels (its footprint's half width, clipped)."""

REF_DEPTH_M = 2.0
"""A room-scale viewing distance: :func:`splat_scale` picks the splat's resolution so that a
point's footprint there is about ``MAX_REACH_PX`` pixels (the regime the hole filling of
``mapper.node.queries.surface_depth`` was measured in, 160 x 120 images)."""


def splat_scale(K: np.ndarray, footprint_m: float) -> int:
    """The integer factor s >= 1 by which to shrink an image before splatting points of
    ``footprint_m`` so that their footprint at :data:`REF_DEPTH_M` is not clipped by
    ``MAX_REACH_PX`` (a 640 x 480 camera with fx = 525 and 5 cm voxels: s = 3). Without it a
    high-resolution camera sees the points as dots with gaps that no hole filling closes.

    >>> splat_scale(np.array([144.0, 144.0, 80.0, 60.0]), 0.05)
    1
    >>> splat_scale(np.array([525.0, 525.0, 320.0, 240.0]), 0.05)
    3
    """
    f = float(max(K[0], K[1]))
    if not (np.isfinite(f) and f > 0 and np.isfinite(footprint_m) and footprint_m > 0):
        return 1
    return max(1, int(0.5 * f * footprint_m / (MAX_REACH_PX * REF_DEPTH_M) + 0.5))


def upsample_nearest(a: np.ndarray, scale: int, height: int, width: int) -> np.ndarray:
    """(height, width): pixel (j, i) takes ``a[j // scale, i // scale]`` (``a`` covers the image
    at 1 / ``scale``, ``ceil(height / scale) x ceil(width / scale)``)."""
    if scale == 1:
        return a[:height, :width]
    return a[(np.arange(height) // scale)[:, None], (np.arange(width) // scale)[None, :]]


def scaled_camera(K: np.ndarray, width: int, height: int, scale: int) -> tuple[np.ndarray, int, int]:
    """``(K, width, height)`` of the image shrunk by ``scale`` (pixel edges kept: u -> u / scale)."""
    K = np.asarray(K, np.float64)
    return K / scale, -(-width // scale), -(-height // scale)


def check_camera(
    K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """``(K (4,), world_from_cam (4, 4))`` as float64, or ``ValueError`` naming what is wrong:
    non-finite or misshapen arrays, fx or fy <= 0, an image size below 1 x 1."""
    K = np.asarray(K, np.float64).reshape(-1)
    pose = np.asarray(world_from_cam, np.float64)
    if K.shape != (4,) or pose.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(pose).all()):
        raise ValueError(
            f"K must be 4 finite numbers and world_from_cam a finite (4, 4), got {K.shape}, {pose.shape}"
        )
    if not (K[0] > 0 and K[1] > 0):
        raise ValueError(f"K: fx, fy must be > 0, got {K[:2].tolist()}")
    if not (width >= 1 and height >= 1):
        raise ValueError(f"image size {width}x{height} out of range: width and height must be >= 1")
    return K, pose


def splat_points(
    xyz: np.ndarray,  # (N, 3) world points (m)
    K: np.ndarray,  # (4,) [fx, fy, cx, cy]
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
    width: int,
    height: int,
    footprint_m: float,  # each point's size: it covers about this many metres at its depth
) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer splat: the nearest point that covers each pixel.

    Each point in front of the camera (z > 1 mm) covers a square of half width
    ``round(0.5 * fx * footprint_m / z)`` pixels (0..``MAX_REACH_PX``) around the pixel it
    projects into; a pixel takes the covering point with the smallest z (of equally near ones, the
    highest row).

    Returns:
        index: (H, W) int64 row of ``xyz`` that each pixel shows, -1 where none;
        z: (H, W) float32 that point's z-depth (m), 0 where none.
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    K, pose = check_camera(K, world_from_cam, width, height)
    if not (np.isfinite(footprint_m) and footprint_m >= 0):
        raise ValueError(f"footprint_m must be finite and >= 0, got {footprint_m}")
    index = np.full(height * width, -1, np.int64)
    depth = np.zeros(height * width, np.float32)
    if xyz.shape[0] == 0:
        return index.reshape(height, width), depth.reshape(height, width)
    fx, fy, cx, cy = (float(v) for v in K)
    p_cam = (xyz.astype(np.float64) - pose[:3, 3]) @ pose[:3, :3]  # world -> camera: R^T (x - t)
    z = p_cam[:, 2]
    rows = np.flatnonzero(np.isfinite(z) & (z > 1e-3))
    p_cam, z = p_cam[rows], z[rows]
    u = fx * p_cam[:, 0] / z + cx
    v = fy * p_cam[:, 1] / z + cy
    reach = np.clip(np.rint(0.5 * fx * footprint_m / z), 0, MAX_REACH_PX).astype(np.int64)
    pad = MAX_REACH_PX + 1
    inside = (u > -pad) & (u < width + pad) & (v > -pad) & (v < height + pad)
    rows, z, reach = rows[inside], z[inside], reach[inside]
    col, lin = np.floor(u[inside]).astype(np.int64), np.floor(v[inside]).astype(np.int64)
    # Of the points that fall into the same pixel only the nearest can show anywhere: a farther one
    # has the same or a smaller footprint (the reach falls with z) around the same pixel.
    cell = (lin + pad) * (width + 2 * pad) + (col + pad)
    nearest = np.full((width + 2 * pad) * (height + 2 * pad), np.inf)
    np.minimum.at(nearest, cell, z)
    keep = z <= nearest[cell]
    rows, z, reach, col, lin = rows[keep], z[keep], reach[keep], col[keep], lin[keep]
    pix_parts, z_parts, row_parts = [], [], []
    for dy in range(-MAX_REACH_PX, MAX_REACH_PX + 1):
        for dx in range(-MAX_REACH_PX, MAX_REACH_PX + 1):
            m = reach >= max(abs(dx), abs(dy))
            cc, ll = col[m] + dx, lin[m] + dy
            ok = (cc >= 0) & (cc < width) & (ll >= 0) & (ll < height)
            pix_parts.append(ll[ok] * width + cc[ok])
            z_parts.append(z[m][ok])
            row_parts.append(rows[m][ok])
    pix = np.concatenate(pix_parts)
    if pix.size == 0:
        return index.reshape(height, width), depth.reshape(height, width)
    zz, rr = np.concatenate(z_parts), np.concatenate(row_parts)
    zbuf = np.full(height * width, np.inf)
    np.minimum.at(zbuf, pix, zz)  # the nearest covering point's z per pixel
    win = zz <= zbuf[pix]
    np.maximum.at(index, pix[win], rr[win])  # among equally near points, the highest row
    covered = np.isfinite(zbuf)
    depth[covered] = zbuf[covered]
    return index.reshape(height, width), depth.reshape(height, width)


def point_spacing(xyz: np.ndarray, sample: int = 4096, seed: int = 0) -> float:  # xyz (N, 3)
    """The median distance from a point of ``xyz`` to its nearest other point (m), over up to
    ``sample`` points drawn at random (seeded: the same cloud gives the same answer); 0 for fewer
    than two points or a cloud whose points all coincide. Non-finite rows are ignored."""
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if xyz.shape[0] < 2:
        return 0.0
    probe = xyz
    if xyz.shape[0] > sample:
        probe = xyz[np.random.default_rng(seed).choice(xyz.shape[0], sample, replace=False)]
    dist, _ = cKDTree(xyz, balanced_tree=False, compact_nodes=False).query(probe, k=2)  # a quick build
    return float(np.median(dist[:, 1]))


def occluder_depths(
    xyz: np.ndarray,  # (N, 3) world points (m): the occluders
    K: np.ndarray,  # (M, 4) [fx, fy, cx, cy] per view, for width x height
    world_from_cam: np.ndarray,  # (M, 4, 4) camera-to-world per view
    width: int,
    height: int,
    footprint_m: float,
    *,
    threads: int = 1,
    compiled: bool = True,
) -> np.ndarray:  # (M, H, W) float32 z-depth, 0 = no point
    """Each view's z-buffer of the points ``xyz`` (:func:`splat_points` with ``footprint_m``; a
    high-resolution camera is splatted at the lower resolution :func:`splat_scale` picks and
    upsampled, as ``render`` does): the depth of the nearest of them at every pixel. A point's
    own pixel always holds it or a nearer point, so testing a point against it as Depth Guided
    Masking tests against a depth map tells whether another of the points hides it in that view.
    ``compiled``: the views of one resolution in one launch of
    :func:`mapper.model.ops.occlusion_kernel.zbuffer_views` on ``threads`` threads (the same
    depths); False: :func:`splat_points` view by view (the reference)."""
    K = np.asarray(K, np.float64).reshape(-1, 4)
    poses = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    if K.shape[0] != poses.shape[0]:
        raise ValueError(f"K has {K.shape[0]} views and world_from_cam {poses.shape[0]}")
    if not (np.isfinite(footprint_m) and footprint_m >= 0):
        raise ValueError(f"footprint_m must be finite and >= 0, got {footprint_m}")
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    for m in range(K.shape[0]):
        check_camera(K[m], poses[m], width, height)
    out = np.zeros((K.shape[0], height, width), np.float32)
    scales = np.array([splat_scale(K[m], footprint_m) for m in range(K.shape[0])], np.int64)
    for scale in np.unique(scales).tolist():
        views = np.flatnonzero(scales == scale)
        K_s, width_s, height_s = scaled_camera(K[views], width, height, scale)  # (m, 4)
        if compiled:
            from mapper.model.ops.occlusion_kernel import zbuffer_views

            z = zbuffer_views(xyz, np.linalg.inv(poses[views]), K_s, width_s, height_s, footprint_m,
                              MAX_REACH_PX, threads=threads)
        else:
            z = np.stack([splat_points(xyz, K_s[i], poses[v], width_s, height_s, footprint_m)[1]
                          for i, v in enumerate(views.tolist())])
        for i, v in enumerate(views.tolist()):
            out[v] = upsample_nearest(z[i], scale, height, width)
    return out


def request_occluder_depths(
    xyz: np.ndarray,  # (N, 3) world points (m): the request's points
    K: np.ndarray,  # (M, 4) [fx, fy, cx, cy] per view, for width x height
    world_from_cam: np.ndarray,  # (M, 4, 4) camera-to-world per view
    width: int,
    height: int,
    spacings: float,
    *,
    threads: int = 1,
) -> np.ndarray:  # (M, H, W) float32 z-depth, 0 = no point
    """:func:`occluder_depths` of a request's own points, each covering ``spacings`` times their
    median nearest-neighbour spacing (:func:`point_spacing`): the depth Depth Guided Masking tests
    those points against without input depth (``model.point_occlusion``,
    ``queries.point_occlusion``, the evaluation's point-occlusion rows)."""
    return occluder_depths(xyz, K, world_from_cam, width, height, spacings * point_spacing(xyz),
                           threads=threads)


def _shifted(n: int, k: int, axis: int, step: int) -> tuple[tuple[slice, ...], tuple[slice, ...]]:
    """(source, destination) index tuples that put, at each pixel, the pixel ``k`` further along
    ``axis`` in direction ``step`` (+1 / -1) of an (H, W) image whose ``axis`` has ``n`` pixels."""
    src, dst = [slice(None)] * 2, [slice(None)] * 2
    if step > 0:
        src[axis], dst[axis] = slice(k, None), slice(None, n - k)
    else:
        src[axis], dst[axis] = slice(None, n - k), slice(k, None)
    return tuple(src), tuple(dst)


def _first_along(z: np.ndarray, window_px: int, axis: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel, the first depth > 0 met going ``step`` (+1 / -1) along ``axis`` within
    ``window_px`` pixels (the pixel itself excluded): (depth (H, W), 0 = none; distance in pixels)."""
    found = np.zeros(z.shape, z.dtype)
    dist = np.zeros(z.shape, np.int32)
    n = z.shape[axis]
    for k in range(1, min(window_px, n - 1) + 1):
        src, dst = _shifted(n, k, axis, step)
        shifted = np.zeros_like(z)
        shifted[dst] = z[src]
        new = (found == 0) & (shifted > 0)
        found[new] = shifted[new]
        dist[new] = k
    return found, dist


def _min_along(z: np.ndarray, window_px: int, axis: int, step: int) -> np.ndarray:
    """For each pixel, the smallest depth > 0 within ``window_px`` pixels going ``step`` along
    ``axis`` (the pixel itself excluded); 0 = none."""
    z_inf = np.where(z > 0, z, np.inf).astype(np.float32)
    best = np.full(z.shape, np.inf, np.float32)
    n = z.shape[axis]
    for k in range(1, min(window_px, n - 1) + 1):
        src, dst = _shifted(n, k, axis, step)
        np.minimum(best[dst], z_inf[src], out=best[dst])
    return np.where(np.isfinite(best), best, np.float32(0))


def see_through(
    z: np.ndarray,  # (H, W) z-depth (m), 0 = nothing
    window_px: int,
    rel: float,
) -> np.ndarray:  # (H, W) bool
    """Pixels of a splat that show a point seen THROUGH a hole in a nearer surface: within
    ``window_px`` pixels on BOTH sides (left and right, or above and below) some depth is nearer
    than this pixel's by more than ``rel`` of it. The far side of a depth edge (a nearer
    surface on one side only) is not flagged; pixels without depth never are; ``window_px = 0``
    flags nothing."""
    z = np.asarray(z)
    if z.ndim != 2:
        raise ValueError(f"z must have shape (H, W), got {z.shape}")
    if window_px < 0 or not (np.isfinite(rel) and rel >= 0):
        raise ValueError(f"window_px must be >= 0 and rel finite and >= 0, got {window_px}, {rel}")
    have = z > 0
    if window_px == 0 or not have.any():
        return np.zeros(z.shape, bool)
    z = z.astype(np.float32)

    def nearer(found: np.ndarray) -> np.ndarray:
        return (found > 0) & (z > (1.0 + rel) * found)

    flagged = np.zeros(z.shape, bool)
    for axis in (0, 1):
        flagged |= nearer(_min_along(z, window_px, axis, -1)) & nearer(_min_along(z, window_px, axis, +1))
    return have & flagged


def fill_holes(
    z: np.ndarray,  # (H, W) z-depth (m), 0 = nothing
    window_px: int,
    rel: float,
) -> np.ndarray:  # (H, W) float32
    """Small holes of a splat filled: a pixel without depth whose first depths within
    ``window_px`` pixels on both sides (left and right, else above and below) agree within
    ``rel`` takes their linear interpolation (a surface continues across the hole). Other pixels
    are returned unchanged; ``window_px = 0`` fills nothing."""
    z = np.asarray(z)
    if z.ndim != 2:
        raise ValueError(f"z must have shape (H, W), got {z.shape}")
    if window_px < 0 or not (np.isfinite(rel) and rel >= 0):
        raise ValueError(f"window_px must be >= 0 and rel finite and >= 0, got {window_px}, {rel}")
    out = z.astype(np.float32).copy()
    if window_px == 0 or not (z > 0).any():
        return out
    src = z.astype(np.float32)
    for axis in (1, 0):
        before, d_before = _first_along(src, window_px, axis, -1)
        after, d_after = _first_along(src, window_px, axis, +1)
        both = (out == 0) & (before > 0) & (after > 0)
        agree = both & (np.abs(before - after) <= rel * np.minimum(before, after))
        span = np.maximum(d_before + d_after, 1).astype(np.float32)
        interp = (before * d_after + after * d_before) / span
        out[agree] = interp[agree]
    return out


def fill_nearest(
    z: np.ndarray,  # (H, W) z-depth (m), 0 = nothing
    max_px: float,
) -> np.ndarray:  # (H, W) float32
    """Pixels without depth within ``max_px`` pixels (Euclidean) of a pixel with depth take the
    depth of the nearest such pixel; other pixels are returned unchanged; ``max_px = 0`` fills
    nothing. Unlike :func:`fill_holes` it extends a surface past its edge (a wall up into an
    unseen ceiling), so it is a last resort for pixels nothing else covers."""
    from scipy.ndimage import distance_transform_edt

    z = np.asarray(z)
    if z.ndim != 2:
        raise ValueError(f"z must have shape (H, W), got {z.shape}")
    if not (np.isfinite(max_px) and max_px >= 0):
        raise ValueError(f"max_px must be finite and >= 0, got {max_px}")
    out = z.astype(np.float32).copy()
    empty = ~(out > 0)
    if max_px == 0 or not empty.any() or empty.all():
        return out
    dist, (rows, cols) = distance_transform_edt(empty, return_indices=True)
    fill = empty & (dist <= max_px)
    out[fill] = out[rows[fill], cols[fill]]
    return out


_INVALID = np.int16(-32768)


def remove_speckles(
    z: np.ndarray,  # (H, W) z-depth (m), 0 = nothing
    max_size_px: int,
    rel: float,
) -> np.ndarray:  # (H, W) float32
    """Small islands of a splat removed: 4-connected regions of pixels whose neighbours' depths
    differ by at most ``rel`` (relative) that hold at most ``max_size_px`` pixels get depth 0
    (``cv2.filterSpeckles`` on the log depth in steps of 1e-3). An isolated point (its footprint)
    floating in front of or behind the surfaces around it is such an island. ``max_size_px = 0``
    removes nothing."""
    z = np.asarray(z)
    if z.ndim != 2:
        raise ValueError(f"z must have shape (H, W), got {z.shape}")
    if max_size_px < 0 or not (np.isfinite(rel) and 0 <= rel <= 10):
        raise ValueError(f"max_size_px must be >= 0 and rel in 0..10, got {max_size_px}, {rel}")
    out = z.astype(np.float32).copy()
    have = out > 0
    if max_size_px == 0 or not have.any():
        return out
    log_z = np.clip(np.log(np.where(have, out, 1.0)), -30.0, 30.0)  # |log z| * 1000 fits int16
    img = np.where(have, np.round(log_z * 1000.0), _INVALID).astype(np.int16)
    cv2.filterSpeckles(img, int(_INVALID), int(max_size_px), max(1, int(round(1000.0 * np.log1p(rel)))))
    out[img == _INVALID] = 0.0
    return out
