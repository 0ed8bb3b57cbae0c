"""Planes fitted to measured points, and the depth a camera sees on them.

RGB-only robots measure geometry only where the image has texture (triangulated features,
plane-sweep stereo), so the flat-shaded walls and floors of a room are covered by few points,
scattered over them. Indoor rooms are mostly large planes; this module fits them to the measured
points (sequential RANSAC + a least-squares refit) and keeps, for each plane, the region of it
that its points support (a grid of cells on the plane, closed over small gaps), so that a plane
never extends past the evidence for it. :func:`plane_depth` is the z-depth a camera sees on the
nearest supported plane: the node's ``render`` can take it where no measured point covers a pixel.

Pure numpy + OpenCV (no torch, no node state). Conventions (docs/concepts/conventions.md): ``K = [fx, fy,
cx, cy]``, ``world_from_cam`` camera-to-world in the OpenCV optical frame, rays through pixel
centres (+0.5), z-depth along the optical axis.

>>> rng = np.random.default_rng(0)
>>> floor = np.c_[rng.random((500, 2)) * 4, np.zeros(500)]  # a 4 x 4 m floor at z = 0
>>> planes = fit_planes(floor, inlier_m=0.02, min_inliers=100, cell_m=0.25, seed=0)
>>> len(planes), bool(abs(abs(planes[0].normal[2]) - 1) < 1e-6), planes[0].inliers
(1, True, 500)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mapper.geometry.splat import check_camera

__all__ = ["Plane", "fit_planes", "plane_depth", "point_normals"]


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . x + offset = 0`` (world, metres) and the region of it its points support."""

    normal: np.ndarray
    """(3,) float64 unit normal."""
    offset: float
    """Signed offset: ``normal . x + offset = 0`` on the plane."""
    origin: np.ndarray
    """(3,) float64 a point on the plane; in-plane coordinates are measured from it."""
    axes: np.ndarray
    """(2, 3) float64 orthonormal in-plane axes (both orthogonal to ``normal``)."""
    cell_m: float
    """Side of the support grid's cells (m)."""
    cell0: tuple[int, int]
    """In-plane cell index (along ``axes[0]``, ``axes[1]``) of ``support[0, 0]``."""
    support: np.ndarray
    """(A, B) bool: cells of the plane its points support (``support[a, b]`` is the cell
    ``cell0 + (a, b)``)."""
    inliers: int
    """Points within the inlier distance at the final fit."""

    def supports(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each world point (on or near the plane) falls in a supported cell."""
        local = (np.asarray(xyz, np.float64).reshape(-1, 3) - self.origin) @ self.axes.T  # (N, 2)
        cell = np.floor(local / self.cell_m).astype(np.int64) - np.asarray(self.cell0, np.int64)
        ok = ((cell[:, 0] >= 0) & (cell[:, 0] < self.support.shape[0])
              & (cell[:, 1] >= 0) & (cell[:, 1] < self.support.shape[1]))
        out = np.zeros(len(local), bool)
        out[ok] = self.support[cell[ok, 0], cell[ok, 1]]
        return out


def _plane_from(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Least-squares plane of (M >= 3, 3) points: (unit normal, offset, centroid), None if degenerate."""
    centroid = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - centroid, full_matrices=False)
    if s.shape[0] < 3 or s[1] <= 1e-9 * max(s[0], 1e-300):
        return None  # collinear (or coincident) points define no plane
    normal = vt[2]
    return normal, -float(normal @ centroid), centroid


def _in_plane_axes(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal axes orthogonal to ``normal`` (deterministic)."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(normal, a)])


def point_normals(
    xyz: np.ndarray,  # (N, 3) world points (m)
    neighbours: int = 12,
) -> tuple[np.ndarray, np.ndarray]:
    """Local surface normals: the least-squares plane of each point's ``neighbours`` nearest points.

    Returns:
        normals: (N, 3) float64 unit normals (sign arbitrary; zero rows where fewer than 3 points);
        flatness: (N,) float64 in [0, 1]: 1 - 3 * (smallest eigenvalue / sum of eigenvalues) of the
            neighbourhood's covariance (1 = all neighbours on a plane, 0 = isotropic).
    """
    from scipy.spatial import cKDTree  # noqa: PLC0415 (SciPy is heavy; only the fit needs it)

    pts = np.asarray(xyz, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.isfinite(pts).all():
        raise ValueError(f"xyz must be finite with shape (N, 3), got {pts.shape}")
    if int(neighbours) != neighbours or neighbours < 3:
        raise ValueError(f"neighbours must be an integer >= 3, got {neighbours}")
    n = len(pts)
    normals = np.zeros((n, 3))
    flatness = np.zeros(n)
    if n < 3:
        return normals, flatness
    k = min(int(neighbours), n)
    _, idx = cKDTree(pts).query(pts, k=k)  # (N, k)
    nb = pts[idx] - pts[idx].mean(axis=1, keepdims=True)  # (N, k, 3)
    cov = np.einsum("nki,nkj->nij", nb, nb) / k  # (N, 3, 3)
    evals, evecs = np.linalg.eigh(cov)  # ascending
    total = evals.sum(axis=1)
    ok = total > 1e-18
    normals[ok] = evecs[ok, :, 0]
    flatness[ok] = np.clip(1.0 - 3.0 * evals[ok, 0] / total[ok], 0.0, 1.0)
    return normals, flatness


def fit_planes(
    xyz: np.ndarray,  # (N, 3) world points (m)
    *,
    inlier_m: float,
    normals: np.ndarray | None = None,  # (N, 3) unit local normals (point_normals), or None
    max_normal_deg: float = 25.0,
    min_inliers: int,
    cell_m: float,
    max_planes: int = 12,
    min_cell_points: int = 2,
    close_cells: int = 2,
    min_support_cells: int = 4,
    iterations: int = 256,
    seed: int = 0,
) -> list[Plane]:
    """Sequential RANSAC: the largest planes of a point set, each with its supported region.

    Each round draws ``iterations`` triples of the points not yet explained, keeps the plane with
    the most points within ``inlier_m``, refits it to those points by least squares (twice), and
    removes them. A cell of the plane's grid (side ``cell_m``) is supported when it holds at least
    ``min_cell_points`` inliers; the support is then closed (dilation then erosion, ``close_cells``
    cells) so that gaps between scattered points are bridged but the region does not grow past
    its outermost points. Rounds stop at ``max_planes`` planes, or when the best plane has fewer
    than ``min_inliers`` points or fewer than ``min_support_cells`` supported cells.

    Args:
        xyz: (N, 3) points; non-finite rows are ignored.
        inlier_m: distance (m) within which a point belongs to a plane (> 0).
        normals: optional (N, 3) local normals (:func:`point_normals`; zero rows = unknown): a
            point then belongs to a plane only when its normal is within ``max_normal_deg`` of
            the plane's, so that a slab through several surfaces at an angle (their points within
            ``inlier_m`` of it only along the lines where they cross it) is no plane.
        max_normal_deg: see ``normals`` (0..90).
        min_inliers: smallest plane kept, in points (>= 3).
        cell_m: side (m) of the support grid's cells (> 0).
        max_planes: most planes returned (>= 0).
        min_cell_points: inliers that make a cell supported (>= 1).
        close_cells: morphological closing of the support, in cells (>= 0).
        min_support_cells: smallest support kept, in cells (>= 1).
        iterations: RANSAC hypotheses per plane (>= 1).
        seed: the random generator's seed (the result is deterministic for a seed).

    Returns:
        Planes, largest first (by inliers at their round).
    """
    pts = np.asarray(xyz, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {pts.shape}")
    if not (np.isfinite(inlier_m) and inlier_m > 0):
        raise ValueError(f"inlier_m must be finite and > 0, got {inlier_m}")
    if not (np.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"cell_m must be finite and > 0, got {cell_m}")
    for name, value, low in (("min_inliers", min_inliers, 3), ("max_planes", max_planes, 0),
                             ("min_cell_points", min_cell_points, 1), ("close_cells", close_cells, 0),
                             ("min_support_cells", min_support_cells, 1), ("iterations", iterations, 1)):
        if int(value) != value or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value}")
    if not (0.0 <= max_normal_deg <= 90.0):
        raise ValueError(f"max_normal_deg must be in [0, 90], got {max_normal_deg}")
    if normals is None:
        nrm = np.zeros((len(pts), 3))
        use_normals = False
    else:
        nrm = np.asarray(normals, np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals must have the shape of xyz {pts.shape}, got {nrm.shape}")
        use_normals = True
    finite = np.isfinite(pts).all(axis=1) & np.isfinite(nrm).all(axis=1)
    pts, nrm = pts[finite], nrm[finite]
    cos_min = float(np.cos(np.deg2rad(max_normal_deg)))
    rng = np.random.default_rng(seed)
    planes: list[Plane] = []
    left, left_n = pts, nrm

    def members_of(normal: np.ndarray, offset: float) -> np.ndarray:
        inside = np.abs(left @ normal + offset) <= inlier_m
        if use_normals:
            inside &= np.abs(left_n @ normal) >= cos_min
        return inside

    while len(planes) < max_planes and len(left) >= max(min_inliers, 3):
        # hypotheses: `iterations` random triples, scored on (a sample of) the remaining points
        tri = left[rng.integers(0, len(left), (iterations, 3))]  # (I, 3, 3)
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (I, 3)
        length = np.linalg.norm(normals, axis=1)
        good = length > 1e-12
        if not good.any():
            break
        normals = normals[good] / length[good, None]
        offsets = -np.einsum("ij,ij->i", normals, tri[good, 0])
        pick = slice(None) if len(left) <= 4096 else rng.choice(len(left), 4096, replace=False)
        near = np.abs(left[pick] @ normals.T + offsets) <= inlier_m  # (P, I')
        if use_normals:
            near &= np.abs(left_n[pick] @ normals.T) >= cos_min
        best = int(np.argmax(near.sum(axis=0)))
        normal, offset = normals[best], float(offsets[best])
        inside = members_of(normal, offset)
        for _ in range(2):  # least-squares refits on the inliers
            fit = _plane_from(left[inside]) if inside.sum() >= 3 else None
            if fit is None:
                break
            normal, offset, _ = fit
            inside = members_of(normal, offset)
        if inside.sum() < min_inliers:
            break
        members = left[inside]
        left, left_n = left[~inside], left_n[~inside]
        plane = _support(members, normal, offset, cell_m=cell_m, min_cell_points=min_cell_points,
                         close_cells=close_cells)
        if plane is None or int(plane.support.sum()) < min_support_cells:
            continue  # a plane of scattered points (no dense region): its points are dropped
        planes.append(plane)
    return planes


def _support(
    members: np.ndarray, normal: np.ndarray, offset: float, *, cell_m: float, min_cell_points: int,
    close_cells: int,
) -> Plane | None:
    """The plane's grid of supported cells from its (M, 3) inliers (None when no cell is supported)."""
    normal = normal / np.linalg.norm(normal)
    origin = -offset * normal  # the plane's point nearest the world origin
    axes = _in_plane_axes(normal)
    cell = np.floor(((members - origin) @ axes.T) / cell_m).astype(np.int64)  # (M, 2)
    lo = cell.min(axis=0) - close_cells
    hi = cell.max(axis=0) + close_cells
    shape = (int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    counts = np.zeros(shape, np.int64)
    np.add.at(counts, (cell[:, 0] - lo[0], cell[:, 1] - lo[1]), 1)
    support = counts >= min_cell_points
    if not support.any():
        return None
    if close_cells > 0:
        kernel = np.ones((2 * close_cells + 1, 2 * close_cells + 1), np.uint8)
        support = cv2.morphologyEx(support.astype(np.uint8), cv2.MORPH_CLOSE, kernel,
                                   borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    return Plane(normal=normal, offset=float(offset), origin=origin, axes=axes, cell_m=float(cell_m),
                 cell0=(int(lo[0]), int(lo[1])), support=support, inliers=int(len(members)))


def plane_depth(
    planes: list[Plane],
    K: np.ndarray,  # (4,) [fx, fy, cx, cy]
    world_from_cam: np.ndarray,  # (4, 4) camera-to-world
    width: int,
    height: int,
    *,
    min_depth_m: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Z-depth of the nearest supported plane along each pixel's ray (through its centre).

    A plane counts at a pixel when the ray meets it in front of the camera (z >= ``min_depth_m``)
    inside its supported region (:meth:`Plane.supports`).

    Returns:
        depth: (H, W) float32 z-depth (m), 0 where no plane is hit;
        index: (H, W) int64 index into ``planes`` of the plane hit, -1 where none.
    """
    K, pose = check_camera(K, world_from_cam, width, height)
    fx, fy, cx, cy = K
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)], axis=-1).reshape(-1, 3)  # z = 1
    rays_w = rays @ pose[:3, :3].T  # (P, 3) world direction per unit z-depth
    centre = pose[:3, 3]
    depth = np.zeros(height * width, np.float64)
    index = np.full(height * width, -1, np.int64)
    for i, plane in enumerate(planes):
        denom = rays_w @ plane.normal  # (P,)
        num = -(plane.normal @ centre + plane.offset)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = num / denom
        hit = np.isfinite(z) & (z >= min_depth_m) & ((depth == 0) | (z < depth))
        if not hit.any():
            continue
        idx = np.flatnonzero(hit)
        ok = plane.supports(centre + rays_w[idx] * z[idx, None])
        idx = idx[ok]
        depth[idx] = z[idx]
        index[idx] = i
    return depth.reshape(height, width).astype(np.float32), index.reshape(height, width)
