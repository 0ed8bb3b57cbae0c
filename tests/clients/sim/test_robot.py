"""Robot trajectories: inside the room, clear of furniture, smooth, looking across the room."""

from __future__ import annotations

import numpy as np
import pytest

from clients.sim.raycast import SceneRenderer
from clients.sim.robot import default_intrinsics, look_at, robot_trajectory
from clients.sim.scenes import Scene, generate_scene

CASES = [("apartment", 0), ("apartment", 5), ("studio", 3), ("studio", 6)]


@pytest.fixture(scope="module")
def runs() -> list[tuple[Scene, np.ndarray]]:
    return [(sc := generate_scene(s, st), robot_trajectory(sc, 150, seed=s + 11)) for st, s in CASES]


def _dist_to_boxes_xy(xy: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Horizontal distance from points (N, 2) to the nearest box footprint (M, 2, 3) -> (N,)."""
    lo, hi = boxes[None, :, 0, :2], boxes[None, :, 1, :2]
    gap = np.maximum(np.maximum(lo - xy[:, None], xy[:, None] - hi), 0.0)
    return np.linalg.norm(gap, axis=-1).min(axis=1)


def test_default_intrinsics() -> None:
    K = default_intrinsics(160, 120, 90.0)
    np.testing.assert_allclose(K, [80.0, 80.0, 80.0, 60.0])
    with pytest.raises(ValueError, match="hfov"):
        default_intrinsics(160, 120, 0.0)
    with pytest.raises(ValueError, match="size"):
        default_intrinsics(0, 120)


def test_look_at_is_opencv() -> None:
    pose = look_at(np.array([1.0, 2.0, 1.5]), np.array([4.0, 2.0, 1.5]))
    R = pose[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)   # +z forward
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)  # +y down
    np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-12)  # +x right (looking along +x, z up)


def test_poses_are_rigid_and_in_height_range(runs: list[tuple[Scene, np.ndarray]]) -> None:
    for _, poses in runs:
        assert poses.shape == (150, 4, 4)
        R = poses[:, :3, :3]
        RtR = np.einsum("nji,njk->nik", R, R)
        np.testing.assert_allclose(RtR, np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
        z = poses[:, 2, 3]
        assert (z >= 0.8 - 1e-9).all() and (z <= 1.6 + 1e-9).all()
        assert z.max() - z.min() > 0.05  # height actually varies


def test_clear_of_walls_and_furniture(runs: list[tuple[Scene, np.ndarray]]) -> None:
    assert any(scene.structures for scene, _ in runs)  # an L-shaped room is among the cases
    for scene, poses in runs:
        xy = poses[:, :2, 3]
        wall = np.minimum(xy - scene.room_min[:2], scene.room_max[:2] - xy).min(1)
        assert wall.min() >= 0.3, (scene.style, scene.seed, wall.min())
        obstacles = scene.obstacle_aabbs()
        assert _dist_to_boxes_xy(xy, obstacles).min() >= 0.3, (scene.style, scene.seed)


def test_smooth(runs: list[tuple[Scene, np.ndarray]]) -> None:
    for _, poses in runs:
        step_xy = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1)
        assert step_xy.max() <= 0.08 + 1e-9
        assert step_xy.min() > 0.0
        step_z = np.abs(np.diff(poses[:, 2, 3]))
        assert step_z.max() < 0.05
        fwd = poses[:, :3, 2]
        turn = np.degrees(np.arccos(np.clip((fwd[1:] * fwd[:-1]).sum(1), -1, 1)))
        assert turn.max() < 10.0


def test_looks_across_the_room_from_near_the_walls(runs: list[tuple[Scene, np.ndarray]]) -> None:
    for scene, poses in runs:
        xy = poses[:, :2, 3]
        size = scene.room_max[:2] - scene.room_min[:2]
        wall = np.minimum(xy - scene.room_min[:2], scene.room_max[:2] - xy).min(1)
        assert np.median(wall) < 0.3 * size.min()  # the robot keeps to the walls' side
        centre = 0.5 * (scene.room_min + scene.room_max)[:2]
        fwd = poses[:, :2, 2]
        towards = ((centre - xy) * fwd).sum(1) > 0
        assert towards.mean() > 0.8
        # the optical axis travels far: the far side of the room, not a wall in front of the nose
        t, _ = SceneRenderer(scene).cast(poses[:, :3, 3], poses[:, :3, 2])
        assert np.median(t) > 0.45 * size.min()
        pitch = np.degrees(np.arcsin(poses[:, 2, 2]))
        assert (pitch < 15).all() and (pitch > -40).all() and pitch.std() > 1.0


def test_deterministic_and_seeded() -> None:
    scene = generate_scene(2)
    a, b = robot_trajectory(scene, 30, seed=1), robot_trajectory(scene, 30, seed=1)
    c = robot_trajectory(scene, 30, seed=2)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_few_frames_keep_step_bound() -> None:
    poses = robot_trajectory(generate_scene(2), 5, seed=0, max_step_m=0.05)
    assert np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1).max() <= 0.05 + 1e-9
    assert robot_trajectory(generate_scene(2), 1, seed=0).shape == (1, 4, 4)


@pytest.mark.parametrize("kwargs, match", [
    ({"n_frames": 0}, "n_frames"), ({"n_frames": 5, "height_range_m": (1.5, 1.0)}, "height_range_m"),
    ({"n_frames": 5, "max_step_m": 0.0}, "max_step_m"),
])
def test_bad_arguments_raise(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        robot_trajectory(generate_scene(0), seed=0, **kwargs)
