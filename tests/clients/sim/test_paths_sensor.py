"""Camera paths, sensor effects and pose error of the scenario matrix (clients.sim.paths/.sensor)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clients.sim.paths import PATH_KINDS, camera_path
from clients.sim.robot import wall_loop
from clients.sim.scenes import generate_scene
from clients.sim.sensor import (
    apply_exposure,
    blur_vector_px,
    exposure_gains,
    motion_blur,
    perturb_poses,
    rotation_from_vector,
)


def _yaw(pose: np.ndarray) -> float:
    return math.atan2(pose[1, 2], pose[0, 2])


@pytest.fixture(scope="module")
def scene():  # noqa: ANN201
    return generate_scene(1, "apartment")


@pytest.mark.parametrize("kind", PATH_KINDS)
def test_every_path_is_a_valid_pose_sequence(scene, kind: str) -> None:  # noqa: ANN001
    poses = camera_path(scene, kind, 60, seed=2)
    assert poses.shape == (60, 4, 4)
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert (poses[:, :3, 3] >= scene.room_min).all() and (poses[:, :3, 3] <= scene.room_max).all()


def test_sparse_covers_the_loop_in_large_steps(scene) -> None:  # noqa: ANN001
    dense, sparse = camera_path(scene, "loop", 60, 2), camera_path(scene, "sparse", 60, 2)
    step = lambda p: np.median(np.linalg.norm(np.diff(p[:, :2, 3], axis=0), axis=1))  # noqa: E731
    assert step(sparse) > 2.0 * step(dense)


def test_fast_turns_turn_faster_than_the_loop(scene) -> None:  # noqa: ANN001
    def turn(poses: np.ndarray) -> float:
        yaw = np.unwrap([_yaw(p) for p in poses])
        return float(np.max(np.abs(np.diff(yaw))))
    assert turn(camera_path(scene, "fast_turns", 60, 2)) > 2.0 * math.radians(6.0)


def test_wall_hug_keeps_closer_to_the_walls(scene) -> None:  # noqa: ANN001
    near = camera_path(scene, "wall_hug", 60, 2)[:, :2, 3]
    default = camera_path(scene, "loop", 60, 2)[:, :2, 3]
    centre = 0.5 * (scene.room_min[:2] + scene.room_max[:2])
    spread = lambda xy: np.median(np.linalg.norm(xy - centre, axis=1))  # noqa: E731
    assert spread(near) >= spread(default)
    assert len(wall_loop(scene, 0.2)) > 0


def test_revisit_comes_back_to_where_it_started(scene) -> None:  # noqa: ANN001
    poses = camera_path(scene, "revisit", 80, seed=2)
    n_loop = round(80 / (1 + 1 / 3))
    assert np.allclose(poses[n_loop:], poses[: 80 - n_loop])
    far = np.linalg.norm(poses[n_loop // 2, :3, 3] - poses[0, :3, 3])
    assert far > 1.0  # it left the start before coming back


def test_unknown_path_kind_is_a_clear_error(scene) -> None:  # noqa: ANN001
    with pytest.raises(ValueError, match="unknown path kind"):
        camera_path(scene, "spiral", 10, 0)
    with pytest.raises(ValueError, match="n_frames"):
        camera_path(scene, "loop", 1, 0)


@pytest.mark.parametrize(("kind", "t_std", "r_deg"), [("noise_1cm", 0.01, 0.5), ("noise_3cm", 0.03, 1.5)])
def test_pose_noise_has_the_stated_size(kind: str, t_std: float, r_deg: float) -> None:
    poses = np.stack([np.eye(4)] * 4000)
    noisy = perturb_poses(poses, kind, seed=1)
    assert np.std(noisy[:, :3, 3]) == pytest.approx(t_std, rel=0.05)
    angle = np.degrees(np.arccos(np.clip((np.trace(noisy[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    # the angle of a 3D Gaussian rotation vector of per-axis std s: RMS sqrt(3) s
    assert np.sqrt(np.mean(angle**2)) == pytest.approx(math.sqrt(3) * r_deg, rel=0.05)
    R = noisy[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)


def test_drift_grows_with_the_frames_and_starts_exact() -> None:
    poses = np.stack([np.eye(4)] * 400)
    drift = np.stack([perturb_poses(poses, "drift", seed=s)[:, :3, 3] for s in range(40)])
    err = np.linalg.norm(drift, axis=2)  # (seeds, frames)
    assert np.all(err[:, 0] == 0)
    assert err[:, 399].mean() > 3.0 * err[:, 20].mean()


def test_rotation_from_vector_matches_a_known_rotation() -> None:
    R = rotation_from_vector(np.array([0.0, 0.0, math.pi / 2]))
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_motion_blur_follows_the_image_motion() -> None:
    K = np.array([100.0, 100.0, 80.0, 60.0])
    pose = np.eye(4)
    turned = pose.copy()
    turned[:3, :3] = rotation_from_vector(np.array([0.0, 0.1, 0.0]))  # a turn about the camera's y axis
    v = blur_vector_px(K, pose, turned)
    assert abs(v[0]) > 3.0 and abs(v[1]) < 0.5  # a horizontal smear
    assert np.allclose(blur_vector_px(K, pose, pose), 0.0)
    img = np.zeros((20, 30, 3), np.uint8)
    img[:, 15] = 255
    out = motion_blur(img, np.array([6.0, 0.0]))
    assert out.dtype == np.uint8 and (out[:, 12:19] > 0).all() and (out[:, 15] < 255).all()
    assert np.array_equal(out[:, :, 0], out[:, :, 0][:1].repeat(20, 0))  # nothing vertical
    assert motion_blur(img, np.array([0.3, 0.0])) is img


def test_exposure_gains_vary_and_saturate() -> None:
    g = exposure_gains(200, seed=3)
    assert g.shape == (200,) and (g > 0).all() and g.max() / g.min() > 1.3
    assert np.array_equal(g, exposure_gains(200, seed=3))
    img = np.full((2, 2, 3), 200, np.uint8)
    assert (apply_exposure(img, 1.5) == 255).all() and (apply_exposure(img, 0.5) == 100).all()
