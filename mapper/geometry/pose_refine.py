"""A keyframe's pose refined against points triangulated from other keyframes (robust PnP with a prior).

A robot's odometry poses carry centimetres and a degree of error. Once a keyframe's features match
points that other keyframes triangulated (2D-3D correspondences), its pose can be corrected:

1. **inliers**: ``cv2.solvePnPRansac`` started at the pose as sent (``pose_ransac_px``) picks the
   correspondences one pose explains; fewer than ``pose_min_inliers`` leave the pose as sent;
2. **refinement**: SciPy ``least_squares`` over the inliers' reprojection errors (in units of
   ``pixel_sigma_px``, Huber-weighted beyond ``pose_huber_px`` by iterative reweighting) plus a
   prior that pulls towards the pose as sent: the camera centre's shift over ``pose_prior_m`` and
   the rotation (about the centre, in the world frame, as odometry errs) over ``pose_prior_deg``,
   per axis;
3. **acceptance**: the refined pose is kept only when it is well constrained (still
   ``pose_min_inliers`` inliers within ``pose_ransac_px`` at it), explains them better (the inliers'
   median reprojection error drops by at least ``pose_min_gain``) and moved little (translation and
   rotation within ``pose_max_sigmas`` of the prior); otherwise the pose as sent is returned.

Pure numpy float64 + OpenCV + SciPy, no torch. Pixel coordinates follow
docs/concepts/conventions.md (centres at +0.5), as :func:`mapper.geometry.triangulation.project`.

Example (exact correspondences, a pose off by 3 cm and 1 degree)::

    >>> import numpy as np
    >>> from mapper.geometry.config import TriangulationConfig
    >>> from mapper.geometry.triangulation import project
    >>> rng = np.random.default_rng(0)
    >>> xyz = rng.uniform([-2, -1.5, 2], [2, 1.5, 5], (80, 3))
    >>> K = np.array([120.0, 120.0, 80.0, 60.0])
    >>> uv = project(K, np.eye(4), xyz)[0]
    >>> sent = perturbed(np.eye(4), np.array([0.03, 0.0, 0.0]), np.radians([0.0, 1.0, 0.0]))
    >>> out = refine_pose(K, sent, uv, xyz, TriangulationConfig())
    >>> out.accepted, bool(np.abs(out.world_from_cam - np.eye(4)).max() < 2e-3)
    (True, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from mapper.geometry.config import TriangulationConfig
from mapper.geometry.triangulation import intrinsics_matrix, project

__all__ = ["PoseRefinement", "perturbed", "pose_change", "refine_pose", "rotation_vector"]


@dataclass(frozen=True)
class PoseRefinement:
    """What :func:`refine_pose` found; ``world_from_cam`` is the pose as sent unless ``accepted``."""

    world_from_cam: np.ndarray  # (4, 4) the refined pose, or the pose as sent
    accepted: bool
    reason: str  # "refined", or why not: "few correspondences", "few inliers", "no gain", "too far"
    correspondences: int
    inliers: int
    error_before_px: float  # inliers' median reprojection error at the pose as sent
    error_after_px: float  # ... at the refined pose (before acceptance)
    translation_m: float  # camera centre moved by the refinement (before acceptance)
    rotation_deg: float  # rotation angle of the refinement (before acceptance)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """(3,) axis-angle (radians) of a (3, 3) rotation."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, np.float64))
    return np.asarray(rvec, np.float64).reshape(3)


def perturbed(world_from_cam: np.ndarray, dt: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """(4, 4) the pose with its centre moved by ``dt`` (3,) metres and its orientation turned by the
    world-frame axis-angle ``dr`` (3,) radians about the centre (as clients.sim.sensor perturbs)."""
    pose = np.asarray(world_from_cam, np.float64).copy()
    R, _ = cv2.Rodrigues(np.asarray(dr, np.float64).reshape(3, 1))
    pose[:3, :3] = R @ pose[:3, :3]
    pose[:3, 3] = pose[:3, 3] + np.asarray(dt, np.float64)
    return pose


def pose_change(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(centre distance m, rotation angle deg) between two (4, 4) world_from_cam poses."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    rel = b[:3, :3] @ a[:3, :3].T
    angle = math.degrees(math.acos(float(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0))))
    return float(np.linalg.norm(b[:3, 3] - a[:3, 3])), angle


def _reprojection(K: np.ndarray, pose: np.ndarray, uv: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(N,) pixel distance of the projections from ``uv``; inf behind the camera."""
    proj, z = project(K, pose, xyz)
    err = np.linalg.norm(proj - uv, axis=1)
    return np.where(z > 1e-6, np.nan_to_num(err, nan=np.inf), np.inf)


def _ransac_inliers(K: np.ndarray, sent: np.ndarray, uv: np.ndarray, xyz: np.ndarray,
                    config: TriangulationConfig) -> np.ndarray:
    """(N,) bool: correspondences within ``pose_ransac_px`` of the RANSAC pose (started at ``sent``)."""
    cam_from_world = np.linalg.inv(sent)
    rvec = rotation_vector(cam_from_world[:3, :3]).reshape(3, 1)
    tvec = cam_from_world[:3, 3].reshape(3, 1).copy()
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        np.ascontiguousarray(xyz, np.float64), np.ascontiguousarray(uv, np.float64),
        intrinsics_matrix(K), None, rvec, tvec, useExtrinsicGuess=True, iterationsCount=200,
        reprojectionError=float(config.pose_ransac_px), confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE,
    )
    inliers = np.zeros(len(uv), bool)
    if ok and idx is not None and len(idx):
        pose = np.eye(4)
        R, _ = cv2.Rodrigues(rvec)
        pose[:3, :3] = R.T
        pose[:3, 3] = (-R.T @ tvec).reshape(3)
        inliers = _reprojection(K, pose, uv, xyz) <= config.pose_ransac_px
    # the pose as sent explains some correspondences already: keep those too (RANSAC's minimal
    # sets on few, noisy points can end beside the prior)
    return inliers | (_reprojection(K, sent, uv, xyz) <= config.pose_ransac_px)


def _solve(K: np.ndarray, sent: np.ndarray, uv: np.ndarray, xyz: np.ndarray,
           config: TriangulationConfig) -> np.ndarray:
    """(4, 4) the pose minimising Huber-weighted reprojection error plus the prior (see module)."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(K, np.float64).reshape(4))
    R0, c0 = sent[:3, :3], sent[:3, 3]
    sigma_px = max(config.pixel_sigma_px, 1e-3)
    prior = np.concatenate([np.full(3, 1.0 / config.pose_prior_m),
                            np.full(3, 1.0 / math.radians(config.pose_prior_deg))])

    def pose_of(x: np.ndarray) -> np.ndarray:
        return perturbed(sent, x[:3], x[3:])

    weights = np.ones(len(uv))

    def residuals(x: np.ndarray) -> np.ndarray:
        dR, _ = cv2.Rodrigues(x[3:].reshape(3, 1))
        R = dR @ R0
        cam = (xyz - (c0 + x[:3])) @ R
        z = np.maximum(cam[:, 2], 1e-6)
        r = np.stack([fx * cam[:, 0] / z + cx - uv[:, 0], fy * cam[:, 1] / z + cy - uv[:, 1]], axis=1)
        return np.concatenate([(r * np.sqrt(weights)[:, None]).ravel() / sigma_px, x * prior])

    x = np.zeros(6)
    for _ in range(3):  # iteratively reweighted: Huber on the reprojection, the prior stays quadratic
        x = least_squares(residuals, x, method="trf", x_scale=1.0 / prior, max_nfev=50).x
        err = _reprojection(K, pose_of(x), uv, xyz)
        weights = np.minimum(1.0, config.pose_huber_px / np.maximum(err, 1e-12))
    return pose_of(x)


def refine_pose(
    K: np.ndarray, world_from_cam: np.ndarray, uv: np.ndarray, xyz: np.ndarray, config: TriangulationConfig
) -> PoseRefinement:
    """Refine the pose of a camera with intrinsics ``K`` (4,) sent as ``world_from_cam`` (4, 4) from
    its keypoints ``uv`` (N, 2) seeing the world points ``xyz`` (N, 3) (see the module docstring)."""
    sent = np.asarray(world_from_cam, np.float64)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    n = len(uv)

    def kept(reason: str, inliers: int = 0, before: float = math.nan, after: float = math.nan,
             dt: float = 0.0, dr: float = 0.0) -> PoseRefinement:
        return PoseRefinement(sent.copy(), False, reason, n, inliers, before, after, dt, dr)

    if n < config.pose_min_inliers:
        return kept("few correspondences")
    inliers = _ransac_inliers(K, sent, uv, xyz, config)
    if int(inliers.sum()) < config.pose_min_inliers:
        return kept("few inliers", int(inliers.sum()))
    refined = _solve(K, sent, uv[inliers], xyz[inliers], config)
    after_all = _reprojection(K, refined, uv, xyz)
    final = after_all <= config.pose_ransac_px
    before = float(np.median(_reprojection(K, sent, uv[final | inliers], xyz[final | inliers])))
    after = float(np.median(after_all[final | inliers]))
    dt, dr = pose_change(sent, refined)
    if int(final.sum()) < config.pose_min_inliers:
        return kept("few inliers", int(final.sum()), before, after, dt, dr)
    if after > (1.0 - config.pose_min_gain) * before:
        return kept("no gain", int(final.sum()), before, after, dt, dr)
    # per-axis sigmas: the norm of a 3-axis error is about sqrt(3) sigma
    if dt > config.pose_max_sigmas * config.pose_prior_m * math.sqrt(3.0) or \
            dr > config.pose_max_sigmas * config.pose_prior_deg * math.sqrt(3.0):
        return kept("too far", int(final.sum()), before, after, dt, dr)
    return PoseRefinement(refined, True, "refined", n, int(final.sum()), before, after, dt, dr)
