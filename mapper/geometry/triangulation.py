"""Sparse 3D points from posed RGB: features matched across keyframes with known poses, triangulated.

A robot without a depth camera still knows where each keyframe was taken. A surface seen from two
known poses is triangulated; this module does it for one new keyframe against a few earlier ones
(numpy float64 and OpenCV, no torch):

1. :meth:`FeatureExtractor.detect`: SIFT (default) or ORB keypoints and descriptors on the
   grayscale image (optionally upscaled, ``detect_upscale``). Keypoint positions follow
   docs/concepts/conventions.md: pixel (i, j) has its centre at ``(i + 0.5, j + 0.5)``; OpenCV puts pixel
   centres at integers, so ``uv = (pt + 0.5) / detect_upscale``.
2. :func:`select_partners`: earlier views whose frustum overlaps the new one (the fraction of a
   pixel grid of the new view, placed at three probe depths, that projects into the candidate in
   front of it) and whose camera centre lies at least ``min_baseline_m`` away (a pure rotation has
   no parallax and gives no partner); ranked by overlap times min(1, parallax / target).
3. :func:`match_pair`: mutual nearest neighbours with Lowe's ratio test, then the epipolar check
   with the fundamental matrix the known poses give (:func:`fundamental_from_poses`): both points
   within ``max_epipolar_px`` of their epipolar lines.
4. :func:`triangulate_pair`: ``cv2.triangulatePoints`` with ``P = K [R | t]``; a point is kept when
   it lies in front of both cameras (cheirality, ``min_depth_m``), reprojects within
   ``max_reprojection_px`` in both, and the rays meet at ``min_parallax_deg`` or more. Its 1-sigma
   uncertainty is ``range * (sigma_px / f) / sin(parallax)`` (the two-view depth error for an
   angular ray error ``sigma_px / f``), with ``sigma_px = max(pixel_sigma_px, reprojection error)``.
5. :func:`triangulate_keyframe`: one estimate per new-view keypoint and partner; the estimates of a
   keypoint that agree with its most certain one (within ``agree_sigmas``) are fused by
   inverse-variance weighting; ``n_views`` counts the views that agree. Points above
   ``max_sigma_m`` or with fewer than ``min_views`` views are dropped.

Example (two views of known points; see tests/mapper/geometry/test_triangulation.py)::

    >>> import numpy as np
    >>> from mapper.geometry.config import TriangulationConfig
    >>> K = np.array([100.0, 100.0, 80.0, 60.0])
    >>> a, b = np.eye(4), np.eye(4)
    >>> b[0, 3] = 0.5                                   # second camera 0.5 m to the right
    >>> xyz = np.array([[0.2, -0.1, 3.0], [-0.4, 0.3, 2.0]])
    >>> uv_a, uv_b = project(K, a, xyz)[0], project(K, b, xyz)[0]
    >>> pts = triangulate_pair(PosedView(K, a, 160, 120), PosedView(K, b, 160, 120), uv_a, uv_b,
    ...                        TriangulationConfig(max_sigma_m=1.0))
    >>> bool(np.allclose(pts.xyz, xyz))
    True
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from mapper.geometry.config import TriangulationConfig

__all__ = [
    "TwoViewRays",
    "triangulate_rays",
    "FeatureExtractor",
    "detection_size",
    "Features",
    "PairPoints",
    "PosedView",
    "SparsePoints",
    "backproject",
    "frustum_points",
    "fundamental_from_poses",
    "intrinsics_matrix",
    "match_pair",
    "photo_consistent",
    "project",
    "select_partners",
    "triangulate_keyframe",
    "triangulate_pair",
]


@dataclass(frozen=True)
class PosedView:
    """A camera with a known pose: intrinsics for an image of ``width`` x ``height``."""

    K: np.ndarray  # (4,) [fx, fy, cx, cy] pixels
    world_from_cam: np.ndarray  # (4, 4) camera-to-world, OpenCV optical frame
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in the world."""
        return np.asarray(self.world_from_cam, np.float64)[:3, 3]

    @property
    def cam_from_world(self) -> np.ndarray:
        """(4, 4) world-to-camera (rigid inverse)."""
        w = np.asarray(self.world_from_cam, np.float64)
        out = np.eye(4)
        out[:3, :3] = w[:3, :3].T
        out[:3, 3] = -w[:3, :3].T @ w[:3, 3]
        return out


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image."""

    uv: np.ndarray  # (N, 2) float64 pixel coordinates, centres at +0.5
    descriptors: np.ndarray  # (N, D) float32 (SIFT) or uint8 (ORB)
    gray: np.ndarray | None = None  # (h, w) uint8 the image grayscale for photometric checks, at most
    # detect_max_side on its longer side (a 4096 x 4096 frame kept whole was 64 MB per candidate)
    gray_scale: tuple[float, float] = (1.0, 1.0)  # gray's pixels per image pixel, (x, y)

    def __len__(self) -> int:
        return int(self.uv.shape[0])


@dataclass(frozen=True)
class PairPoints:
    """Points triangulated from one pair (new view ``a``, partner ``b``)."""

    xyz: np.ndarray  # (N, 3) float64 world, metres
    sigma_m: np.ndarray  # (N,) float64 1-sigma position uncertainty, metres
    parallax_deg: np.ndarray  # (N,) float64 angle between the two rays at the point
    reprojection_px: np.ndarray  # (N,) float64 larger of the two reprojection errors
    index: np.ndarray  # (N,) int64 row of the kept points in the input correspondences

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class SparsePoints:
    """Points triangulated for one keyframe (see the module docstring)."""

    xyz: np.ndarray  # (N, 3) float64 world, metres
    sigma_m: np.ndarray  # (N,) float64 1-sigma position uncertainty, metres
    parallax_deg: np.ndarray  # (N,) float64 largest parallax among the fused estimates
    reprojection_px: np.ndarray  # (N,) float64 reprojection error of the most certain estimate
    n_views: np.ndarray  # (N,) int32 views that agree on the point (the keyframe included), >= 2
    uv: np.ndarray  # (N, 2) float64 keypoint in the keyframe, centres at +0.5
    depth_m: np.ndarray  # (N,) float64 z-depth in the keyframe's camera
    partners: int = 0
    """Partner views matched."""
    matches: int = 0
    """Correspondences that passed the ratio and epipolar tests, summed over the partners."""
    feature_index: np.ndarray | None = None
    """(N,) int64 the points' keypoints in the keyframe's :class:`Features` (None: not known)."""

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @staticmethod
    def empty(partners: int = 0, matches: int = 0) -> SparsePoints:
        z = np.zeros(0, np.float64)
        return SparsePoints(np.zeros((0, 3)), z, z, z, np.zeros(0, np.int32), np.zeros((0, 2)), z,
                            partners, matches, np.zeros(0, np.int64))


# -- camera maths --------------------------------------------------------------------------------


def intrinsics_matrix(K: np.ndarray) -> np.ndarray:
    """(3, 3) float64 camera matrix from ``K = [fx, fy, cx, cy]`` (pixel centres at +0.5)."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(K, np.float64).reshape(4))
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _check_pose(world_from_cam: np.ndarray) -> np.ndarray:
    pose = np.asarray(world_from_cam, np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ValueError(f"world_from_cam must be a finite (4, 4) matrix, got shape {pose.shape}")
    return pose


def project(K: np.ndarray, world_from_cam: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points: ``(uv (N, 2), z (N,))`` float64, z = depth in the camera (may be <= 0)."""
    pose = _check_pose(world_from_cam)
    pts = np.asarray(xyz, np.float64).reshape(-1, 3)
    cam = (pts - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - c), row-wise
    z = cam[:, 2]
    fx, fy, cx, cy = (float(v) for v in np.asarray(K, np.float64).reshape(4))
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * cam[:, 0] / z + cx, fy * cam[:, 1] / z + cy], axis=-1)
    return uv, z


def backproject(
    depth_m: np.ndarray,  # (H, W) z-depth (m), 0 / non-finite = none
    K: np.ndarray,  # (4,) [fx, fy, cx, cy]
    world_from_cam: np.ndarray,  # (4, 4)
    mask: np.ndarray | None = None,  # (H, W) bool: only these pixels (None = all)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse of :func:`project` for a depth map: the pixels with a depth (finite, > 0, and
    in ``mask``) as ``(rows (M,), cols (M,), world points (M, 3) float64)``, rays through the pixel
    centres (+0.5)."""
    pose = _check_pose(world_from_cam)
    depth = np.asarray(depth_m)
    has = np.isfinite(depth) & (depth > 0)
    rows, cols = np.nonzero(has if mask is None else has & mask)
    z = depth[rows, cols].astype(np.float64)
    fx, fy, cx, cy = (float(v) for v in np.asarray(K, np.float64).reshape(4))
    cam = np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], axis=-1)
    return rows, cols, cam @ pose[:3, :3].T + pose[:3, 3]


def fundamental_from_poses(a: PosedView, b: PosedView) -> np.ndarray:
    """(3, 3) fundamental matrix with ``[u_b, v_b, 1] F [u_a, v_a, 1]^T = 0`` for a world point
    seen at ``uv_a`` in ``a`` and ``uv_b`` in ``b`` (pixel centres at +0.5). Zero when the camera
    centres coincide (no epipolar geometry)."""
    b_from_a = b.cam_from_world @ _check_pose(a.world_from_cam)
    R, t = b_from_a[:3, :3], b_from_a[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ R
    return np.linalg.inv(intrinsics_matrix(b.K)).T @ E @ np.linalg.inv(intrinsics_matrix(a.K))


def _epipolar_distance(F: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(N,) larger of the two point-to-epipolar-line distances (pixels)."""
    xa = np.concatenate([uv_a, np.ones((len(uv_a), 1))], axis=1)
    xb = np.concatenate([uv_b, np.ones((len(uv_b), 1))], axis=1)
    lb = xa @ F.T  # lines in b: F x_a
    la = xb @ F  # lines in a: F^T x_b
    alg = np.abs(np.sum(xb * lb, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        db = alg / np.hypot(lb[:, 0], lb[:, 1])
        da = alg / np.hypot(la[:, 0], la[:, 1])
    return np.nan_to_num(np.maximum(da, db), nan=np.inf)


# -- features ------------------------------------------------------------------------------------


def detection_size(width: int, height: int, upscale: int, max_side: int) -> tuple[int, int]:
    """(w, h) of the image features are detected on: ``upscale`` times the image while that fits in
    ``max_side`` pixels (longer side), else the largest integer factor that fits, else the image
    downscaled to ``max_side``.

    >>> detection_size(160, 120, 2, 1280), detection_size(640, 480, 2, 1280)
    ((320, 240), (1280, 960))
    >>> detection_size(1000, 750, 2, 1280), detection_size(4096, 2048, 2, 1280)
    ((1000, 750), (1280, 640))
    """
    longest = max(width, height)
    for factor in range(max(1, upscale), 0, -1):
        if longest * factor <= max_side:
            return width * factor, height * factor
    shrink = max_side / longest
    return max(1, round(width * shrink)), max(1, round(height * shrink))


class FeatureExtractor:
    """SIFT or ORB keypoints (``config.detector``) in the pixel-centre convention."""

    def __init__(self, config: TriangulationConfig) -> None:
        self.config = config
        if config.detector == "sift":
            self._detector = cv2.SIFT_create(  # type: ignore[attr-defined]
                nfeatures=config.max_features, contrastThreshold=config.sift_contrast_threshold
            )
            self._norm = cv2.NORM_L2
        elif config.detector == "orb":
            self._detector = cv2.ORB_create(  # type: ignore[attr-defined]
                nfeatures=config.max_features, edgeThreshold=15, patchSize=15
            )
            self._norm = cv2.NORM_HAMMING
        else:
            raise ValueError(f"unknown detector {config.detector!r}")
        self._matcher = cv2.BFMatcher(self._norm)

    def detect(self, rgb: np.ndarray) -> Features:
        """Features of an ``(H, W, 3)`` uint8 RGB (or ``(H, W)`` gray) image."""
        image = np.asarray(rgb)
        if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
            raise ValueError(f"rgb must be (H, W, 3) or (H, W) uint8, got {image.shape} {image.dtype}")
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        height, width = gray.shape
        kept, kept_scale = np.ascontiguousarray(gray), (1.0, 1.0)
        kw, kh = detection_size(width, height, 1, self.config.detect_max_side)  # photometric: no more
        if (kw, kh) != (width, height):
            kept = cv2.resize(gray, (kw, kh), interpolation=cv2.INTER_AREA)
            kept_scale = (kw / width, kh / height)
        size = detection_size(width, height, self.config.detect_upscale, self.config.detect_max_side)
        if size != (width, height):
            grow = size[0] > width
            gray = cv2.resize(gray, size, interpolation=cv2.INTER_CUBIC if grow else cv2.INTER_AREA)
        keypoints, descriptors = self._detector.detectAndCompute(np.ascontiguousarray(gray), None)
        if descriptors is None or not keypoints:
            dim, dtype = (128, np.float32) if self.config.detector == "sift" else (32, np.uint8)
            return Features(np.zeros((0, 2)), np.zeros((0, dim), dtype), kept, kept_scale)
        scale = np.array([size[0] / width, size[1] / height])  # per axis (a downscale rounds)
        uv = (np.array([kp.pt for kp in keypoints], np.float64) + 0.5) / scale
        return Features(uv, descriptors, kept, kept_scale)

    def match(self, a: Features, b: Features) -> np.ndarray:
        """(M, 2) int64 index pairs ``(i_a, i_b)``: mutual best matches passing the ratio test."""
        if len(a) < 2 or len(b) < 2:
            return np.zeros((0, 2), np.int64)
        ab = self._matcher.knnMatch(a.descriptors, b.descriptors, k=2)
        ba = self._matcher.match(b.descriptors, a.descriptors)
        back = np.full(len(b), -1, np.int64)
        for m in ba:
            back[m.queryIdx] = m.trainIdx
        pairs = [
            (m[0].queryIdx, m[0].trainIdx)
            for m in ab
            if len(m) == 2 and m[0].distance < self.config.ratio * m[1].distance
            and back[m[0].trainIdx] == m[0].queryIdx
        ]
        return np.array(pairs, np.int64).reshape(-1, 2)


# -- partners ------------------------------------------------------------------------------------


def _probe_points(view: PosedView, config: TriangulationConfig) -> np.ndarray:
    """(P, 3) world points: a 6 x 5 pixel grid of ``view`` at three depths from near to far."""
    us = (np.arange(6) + 0.5) * view.width / 6
    vs = (np.arange(5) + 0.5) * view.height / 5
    u, v = np.meshgrid(us, vs)
    fx, fy, cx, cy = (float(x) for x in np.asarray(view.K, np.float64).reshape(4))
    rays = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], axis=-1)
    depths = np.linspace(config.probe_near_m, config.probe_far_m, 3)
    cam = (rays[None] * depths[:, None, None]).reshape(-1, 3)
    pose = np.asarray(view.world_from_cam, np.float64)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def frustum_points(view: PosedView, near_m: float, far_m: float) -> np.ndarray:
    """(200, 3) world points: a 5 x 5 pixel grid over ``view``'s image (corners included) at 8
    depths from ``near_m`` to ``far_m`` (z-depth)."""
    us, vs = np.linspace(0.0, view.width, 5), np.linspace(0.0, view.height, 5)
    u, v = np.meshgrid(us, vs)
    fx, fy, cx, cy = (float(x) for x in np.asarray(view.K, np.float64).reshape(4))
    rays = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], axis=-1)
    cam = (rays[None] * np.linspace(near_m, far_m, 8)[:, None, None]).reshape(-1, 3)
    pose = np.asarray(view.world_from_cam, np.float64)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def view_overlap(new: PosedView, other: PosedView, config: TriangulationConfig) -> float:
    """Fraction of ``new``'s probe points that ``other`` sees (inside its image, in front)."""
    uv, z = project(other.K, other.world_from_cam, _probe_points(new, config))
    inside = (z > config.min_depth_m) & (uv[:, 0] >= 0) & (uv[:, 0] <= other.width) \
        & (uv[:, 1] >= 0) & (uv[:, 1] <= other.height)
    return float(inside.mean())


def select_partners(
    new: PosedView, candidates: Sequence[PosedView], config: TriangulationConfig
) -> list[int]:
    """Indices of up to ``max_partners`` candidates to match ``new`` against, best first (see the
    module docstring); candidates closer than ``min_baseline_m`` or overlapping less than
    ``min_overlap`` are never chosen."""
    mid = 0.5 * (config.probe_near_m + config.probe_far_m)
    target = math.radians(config.target_parallax_deg)
    scored = []
    for i, cand in enumerate(candidates):
        baseline = float(np.linalg.norm(cand.center - new.center))
        if baseline < config.min_baseline_m:
            continue
        overlap = view_overlap(new, cand, config)
        if overlap < max(config.min_overlap, 1e-9):
            continue
        parallax = 2.0 * math.atan(0.5 * baseline / mid)
        scored.append((overlap * min(1.0, parallax / target), i))
    scored.sort(key=lambda s: (-s[0], s[1]))
    return [i for _, i in scored[: config.max_partners]]


# -- two views -----------------------------------------------------------------------------------


def match_pair(
    extractor: FeatureExtractor, a: PosedView, fa: Features, b: PosedView, fb: Features,
    config: TriangulationConfig, pairs: np.ndarray | None = None,
) -> np.ndarray:
    """(M, 2) int64 ``(i_a, i_b)``: descriptor matches (mutual, ratio test; ``pairs`` when they
    were matched already) consistent with the poses' epipolar geometry (both points within
    ``max_epipolar_px`` of their epipolar lines). Empty when the camera centres coincide (no
    epipolar geometry)."""
    F = fundamental_from_poses(a, b)
    if not np.any(F):
        return np.zeros((0, 2), np.int64)
    if pairs is None:
        pairs = extractor.match(fa, fb)
    if not len(pairs):
        return pairs
    dist = _epipolar_distance(F, fa.uv[pairs[:, 0]], fb.uv[pairs[:, 1]])
    return pairs[dist <= config.max_epipolar_px]


@dataclass(frozen=True)
class TwoViewRays:
    """Linear two-view triangulation of N correspondences and what the checks read (float64)."""

    xyz: np.ndarray  # (N, 3) world points (NaN where the solution is at infinity)
    finite: np.ndarray  # (N,) bool: not at infinity
    reprojection_px: np.ndarray  # (N,) the larger of the two views' reprojection errors
    depth_a: np.ndarray  # (N,) z in view a
    depth_b: np.ndarray  # (N,) z in view b
    range_m: np.ndarray  # (N,) the larger of the distances to the two camera centres
    parallax_deg: np.ndarray  # (N,) the angle between the two rays at the point
    focal_px: float  # the two views' mean focal length


def triangulate_rays(a: PosedView, b: PosedView, uv_a: np.ndarray, uv_b: np.ndarray) -> TwoViewRays:
    """``cv2.triangulatePoints`` with ``P = K [R | t]`` for ``uv_a`` / ``uv_b`` (N, 2) float64 (pixel
    centres at +0.5), and per point its reprojection error, depths, range and parallax (the shared
    part of the sparse and the dense flow triangulation; each applies its own checks)."""
    Pa = intrinsics_matrix(a.K) @ a.cam_from_world[:3]
    Pb = intrinsics_matrix(b.K) @ b.cam_from_world[:3]
    hom = cv2.triangulatePoints(Pa, Pb, uv_a.T.copy(), uv_b.T.copy()).T.astype(np.float64)  # (N, 4)
    w = hom[:, 3]
    scale = np.abs(hom[:, :3]).max(axis=1)
    finite = np.abs(w) > 1e-12 * np.maximum(scale, 1e-300)
    xyz = np.where(finite[:, None], hom[:, :3] / np.where(finite, w, 1.0)[:, None], np.nan)
    pa, za = project(a.K, a.world_from_cam, xyz)
    pb, zb = project(b.K, b.world_from_cam, xyz)
    reproj = np.maximum(np.linalg.norm(pa - uv_a, axis=1), np.linalg.norm(pb - uv_b, axis=1))
    ra, rb = xyz - a.center, xyz - b.center
    na, nb = np.linalg.norm(ra, axis=1), np.linalg.norm(rb, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.clip(np.sum(ra * rb, axis=1) / (na * nb), -1.0, 1.0)
    parallax = np.degrees(np.arccos(cos))
    focal = 0.5 * (float(np.mean(np.asarray(a.K)[:2])) + float(np.mean(np.asarray(b.K)[:2])))
    return TwoViewRays(xyz, finite, reproj, za, zb, np.maximum(na, nb), parallax, focal)


def triangulate_pair(
    a: PosedView, b: PosedView, uv_a: np.ndarray, uv_b: np.ndarray, config: TriangulationConfig
) -> PairPoints:
    """Triangulate correspondences ``uv_a`` (N, 2) in ``a`` and ``uv_b`` (N, 2) in ``b`` (pixel
    centres at +0.5) and keep those passing the cheirality, depth, reprojection, parallax and
    uncertainty checks (see the module docstring)."""
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    if uv_a.shape != uv_b.shape:
        raise ValueError(f"uv_a {uv_a.shape} and uv_b {uv_b.shape} must have the same shape")
    if uv_a.shape[0] == 0:
        z0 = np.zeros(0, np.float64)
        return PairPoints(np.zeros((0, 3)), z0, z0, z0, np.zeros(0, np.int64))
    r = triangulate_rays(a, b, uv_a, uv_b)
    sigma_px = np.maximum(config.pixel_sigma_px, r.reprojection_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma = r.range_m * (sigma_px / r.focal_px) / np.sin(np.radians(r.parallax_deg))
    keep = (
        r.finite
        & np.isfinite(r.xyz).all(axis=1)
        & (r.depth_a >= config.min_depth_m) & (r.depth_b >= config.min_depth_m)  # cheirality
        & (r.depth_a <= config.max_depth_m)
        & (r.reprojection_px <= config.max_reprojection_px)
        & (r.parallax_deg >= config.min_parallax_deg)
        & (sigma <= config.max_sigma_m)
    )
    keep &= np.isfinite(sigma)
    idx = np.flatnonzero(keep)
    return PairPoints(r.xyz[idx], sigma[idx], r.parallax_deg[idx], r.reprojection_px[idx],
                      idx.astype(np.int64))


# -- one keyframe against its partners -----------------------------------------------------------


def triangulate_keyframe(
    extractor: FeatureExtractor,
    new: PosedView,
    new_features: Features,
    partners: Sequence[tuple[PosedView, Features]],
    config: TriangulationConfig,
    matched: Sequence[np.ndarray] | None = None,
) -> SparsePoints:
    """Match ``new`` against each partner, triangulate, and fuse the estimates per keypoint.
    ``matched``: the descriptor matches with each partner when they were found already
    (:meth:`FeatureExtractor.match`; the epipolar check is still applied)."""
    rows: list[np.ndarray] = []  # per estimate: keypoint, x, y, z, sigma, parallax, reproj, partner
    matches = 0
    for p, (view, feats) in enumerate(partners):
        pairs = match_pair(extractor, new, new_features, view, feats, config,
                           None if matched is None else matched[p])
        matches += len(pairs)
        if not len(pairs):
            continue
        pts = triangulate_pair(new, view, new_features.uv[pairs[:, 0]], feats.uv[pairs[:, 1]], config)
        if not len(pts):
            continue
        kp = pairs[pts.index, 0].astype(np.float64)
        rows.append(np.column_stack([kp, pts.xyz, pts.sigma_m, pts.parallax_deg, pts.reprojection_px,
                                     np.full(len(pts), float(p))]))
    if not rows:
        return SparsePoints.empty(len(partners), matches)
    est = np.concatenate(rows)
    est = est[np.lexsort((est[:, 4], est[:, 0]))]  # by keypoint, most certain first
    keys, starts = np.unique(est[:, 0], return_index=True)
    ends = np.append(starts[1:], len(est))
    out = []
    for key, s, e in zip(keys, starts, ends, strict=True):
        group = est[s:e]
        best = group[0]
        combined = np.sqrt(group[:, 4] ** 2 + best[4] ** 2)
        agree = group[np.linalg.norm(group[:, 1:4] - best[1:4], axis=1) <= config.agree_sigmas * combined]
        w = 1.0 / agree[:, 4] ** 2
        xyz = (agree[:, 1:4] * w[:, None]).sum(axis=0) / w.sum()
        agree_bits = sum(1 << int(q) for q in set(agree[:, 7].tolist()))
        out.append([key, *xyz, 1.0 / math.sqrt(float(w.sum())), agree[:, 5].max(), best[6], agree_bits])
    res = np.array(out, np.float64).reshape(-1, 8)
    xyz = res[:, 1:4]
    uv = new_features.uv[res[:, 0].astype(np.int64)]
    _, depth = project(new.K, new.world_from_cam, xyz)
    seen = np.array([int(m) for m in res[:, 7]], dtype=np.int64)  # bit p: partner p agrees
    for p, (view, feats) in enumerate(partners):
        if config.min_ncc < 1.0 and new_features.gray is not None and feats.gray is not None:
            ok = photo_consistent(new, new_features.gray, view, feats.gray, uv, depth, config,
                                  scale_a=new_features.gray_scale, scale_b=feats.gray_scale)
            seen |= ok.astype(np.int64) << p
    n_views = 1 + np.array([bin(int(m)).count("1") for m in seen], np.int32)
    keep = n_views >= config.min_views
    return SparsePoints(
        xyz=xyz[keep], sigma_m=res[keep, 4], parallax_deg=res[keep, 5], reprojection_px=res[keep, 6],
        n_views=n_views[keep], uv=uv[keep], depth_m=depth[keep], partners=len(partners), matches=matches,
        feature_index=res[keep, 0].astype(np.int64),
    )


def _sample(gray: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``gray`` (H, W) at ``uv`` (..., 2) pixel coordinates (centres at +0.5)."""
    flat = uv.reshape(-1, 2).astype(np.float32) - 0.5  # OpenCV: pixel centres at integers
    n, cols = flat.shape[0], 1024  # maps laid out as rows of 1024 (OpenCV limits a side to 32767)
    padded = np.zeros((-(-n // cols) * cols, 2), np.float32)
    padded[:n] = flat
    maps = padded.reshape(-1, cols, 2)
    out = cv2.remap(np.ascontiguousarray(gray, np.float32), maps[..., 0].copy(), maps[..., 1].copy(),
                    interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1)[:n].reshape(uv.shape[:-1])


def photo_consistent(
    a: PosedView, gray_a: np.ndarray, b: PosedView, gray_b: np.ndarray,
    uv_a: np.ndarray, depth_a: np.ndarray, config: TriangulationConfig,
    *, scale_a: tuple[float, float] = (1.0, 1.0), scale_b: tuple[float, float] = (1.0, 1.0),
) -> np.ndarray:
    """(N,) bool: the ``ncc_patch_px`` square patch around ``uv_a`` (N, 2) in ``a``, taken as a
    fronto-parallel plane at ``depth_a`` (N,), has a normalised cross-correlation of at least
    ``min_ncc`` with its image in ``b`` (and lies inside ``b``, in front of it). ``gray_a`` /
    ``gray_b`` may be the images resized by ``scale_a`` / ``scale_b`` (their pixels per image pixel,
    x and y; :class:`Features` keeps at most ``detect_max_side``): the patch is ``ncc_patch_px``
    of ``gray_a``'s pixels."""
    n = len(uv_a)
    if n == 0:
        return np.zeros(0, bool)
    half = config.ncc_patch_px // 2
    offs = np.arange(-half, half + 1, dtype=np.float64)
    du, dv = np.meshgrid(offs, offs)
    sa, sb = np.asarray(scale_a, np.float64), np.asarray(scale_b, np.float64)
    grid = uv_a[:, None, :] + np.stack([du.ravel(), dv.ravel()], axis=-1)[None] / sa  # (N, P, 2) a's px
    fx, fy, cx, cy = (float(v) for v in np.asarray(a.K, np.float64).reshape(4))
    z = depth_a[:, None]
    cam = np.stack([(grid[..., 0] - cx) / fx * z, (grid[..., 1] - cy) / fy * z,
                    np.broadcast_to(z, grid.shape[:2])], axis=-1)
    pose = np.asarray(a.world_from_cam, np.float64)
    world = cam.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    uv_b, z_b = project(b.K, b.world_from_cam, world)
    uv_b, z_b = uv_b.reshape(n, -1, 2), z_b.reshape(n, -1)
    inside = ((z_b > config.min_depth_m) & (uv_b[..., 0] >= 0) & (uv_b[..., 0] <= b.width)
              & (uv_b[..., 1] >= 0) & (uv_b[..., 1] <= b.height)).all(axis=1)
    pa = _sample(gray_a, grid * sa)
    pb = _sample(gray_b, np.where(np.isfinite(uv_b), uv_b, 0.0) * sb)
    pa = pa - pa.mean(axis=1, keepdims=True)
    pb = pb - pb.mean(axis=1, keepdims=True)
    denom = np.sqrt((pa**2).sum(axis=1) * (pb**2).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = np.where(denom > 1e-6, (pa * pb).sum(axis=1) / denom, 0.0)
    return inside & (ncc >= config.min_ncc)
