"""Pose refinement against triangulated points (mapper.geometry.pose_refine): exact, robust, left alone."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.errors import ConfigError
from mapper.geometry.config import TriangulationConfig
from mapper.geometry.pose_refine import perturbed, pose_change, refine_pose
from mapper.geometry.triangulation import project

K = np.array([115.0, 115.0, 80.0, 60.0])  # 160 x 120, about 70 degrees wide


def _look_pose() -> np.ndarray:
    """A camera at (1, 0.5, -0.3) turned 20 degrees about y (not the identity, to catch frame mix-ups)."""
    a = np.radians(20.0)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    pose[:3, 3] = [1.0, 0.5, -0.3]
    return pose


def _scene(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true pose, uv (n, 2) inside the image, xyz (n, 3)) of points 1.5-5 m in front of it."""
    rng = np.random.default_rng(seed)
    pose = _look_pose()
    cam = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.45, 0.45, n), np.ones(n)])
    cam *= rng.uniform(1.5, 5.0, n)[:, None]
    xyz = cam @ pose[:3, :3].T + pose[:3, 3]
    uv, z = project(K, pose, xyz)
    assert (z > 1.0).all() and (uv[:, 0] > 0).all() and (uv[:, 0] < 160).all()
    return pose, uv, xyz


def _sent(pose: np.ndarray) -> np.ndarray:
    """The pose as odometry sends it: 3 cm and about 1.7 degrees off."""
    return perturbed(pose, np.array([0.02, -0.015, 0.015]), np.radians([1.0, -1.0, 0.8]))


def test_exact_matches_recover_the_true_pose() -> None:
    pose, uv, xyz = _scene(60)
    sent = _sent(pose)
    dt0, dr0 = pose_change(pose, sent)
    out = refine_pose(K, sent, uv, xyz, TriangulationConfig())
    assert out.accepted and out.reason == "refined"
    dt, dr = pose_change(pose, out.world_from_cam)
    # the prior pulls a little towards the pose as sent; exact data outweighs it
    assert dt < 0.1 * dt0 and dr < 0.1 * dr0, (dt, dr, dt0, dr0)
    assert out.inliers == 60 and out.error_after_px < 0.1 * out.error_before_px
    assert out.translation_m == pytest.approx(pose_change(sent, out.world_from_cam)[0])


def test_noisy_matches_with_outliers_are_robust() -> None:
    pose, uv, xyz = _scene(120, seed=1)
    rng = np.random.default_rng(2)
    uv = uv + rng.normal(0.0, 0.5, uv.shape)  # keypoint noise
    wrong = rng.choice(len(uv), 36, replace=False)  # 30% mismatches anywhere in the image
    uv[wrong] = rng.uniform([0, 0], [160, 120], (len(wrong), 2))
    sent = _sent(pose)
    dt0, dr0 = pose_change(pose, sent)
    out = refine_pose(K, sent, uv, xyz, TriangulationConfig())
    assert out.accepted
    dt, dr = pose_change(pose, out.world_from_cam)
    assert dt < 0.35 * dt0 and dr < 0.25 * dr0, (dt, dr, dt0, dr0)
    assert out.inliers <= 120 - 30  # the mismatches (a few land near their point by chance) are out
    # the same without the robust steps would be pulled: plain least squares on everything is worse
    plain = refine_pose(K, sent, uv, xyz, TriangulationConfig(pose_ransac_px=1000.0, pose_huber_px=100.0,
                                                               pose_min_gain=0.0, pose_max_sigmas=100.0))
    assert pose_change(pose, plain.world_from_cam)[1] > dr


def test_few_points_leave_the_pose_as_sent() -> None:
    pose, uv, xyz = _scene(8, seed=3)
    sent = _sent(pose)
    out = refine_pose(K, sent, uv, xyz, TriangulationConfig())
    assert not out.accepted and out.reason == "few correspondences"
    assert np.array_equal(out.world_from_cam, sent)


def test_correspondences_that_no_pose_explains_are_rejected() -> None:
    pose, uv, xyz = _scene(40, seed=4)
    rng = np.random.default_rng(5)
    uv = rng.uniform([0, 0], [160, 120], uv.shape)  # every match wrong
    sent = _sent(pose)
    out = refine_pose(K, sent, uv, xyz, TriangulationConfig())
    assert not out.accepted and out.reason in ("few inliers", "no gain", "too far")
    assert np.array_equal(out.world_from_cam, sent)


def test_a_correction_beyond_the_prior_is_rejected() -> None:
    pose, uv, xyz = _scene(60, seed=6)
    sent = perturbed(pose, np.array([0.3, 0.0, 0.0]), np.zeros(3))  # 30 cm off: not odometry noise
    out = refine_pose(K, sent, uv, xyz, TriangulationConfig(pose_ransac_px=100.0))
    assert not out.accepted and out.reason == "too far" and np.array_equal(out.world_from_cam, sent)


def test_pose_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="pose_prior_m"):
        TriangulationConfig(pose_prior_m=0.0).validate("node.toml")
    with pytest.raises(ConfigError, match="pose_min_inliers"):
        TriangulationConfig(pose_min_inliers=2).validate("node.toml")
