"""Ways of moving through a room: the camera paths of the scenario matrix (docs/how-to/scenario-matrix.md).

Each kind is built on :func:`clients.sim.robot.robot_trajectory` (a loop through the free floor
near the walls, looking across the room) and differs in how the robot covers it:

* ``loop``: the dense loop the rest of the project uses (steps of at most 8 cm, turns of at most
  6 degrees a frame; covers as much of the loop as the frames allow);
* ``sparse``: the whole loop in the given frames (60-80 frames a room: steps of 0.2-0.4 m, turns
  up to 20 degrees a frame), as a robot that keeps only sparse keyframes sends them;
* ``wall_hug``: the camera 0.2 m from the walls and furniture (the planner's closest), looking
  across the room, steps of up to 12 cm;
* ``fast_turns``: the dense loop with a fast side-to-side sweep of the gaze on top (+-35 degrees,
  a period of 12 frames: up to about 18 degrees a frame);
* ``revisit``: once around the whole loop, then on over its first third again: the robot leaves
  where it started (in the ``corridor`` layout: the room) and comes back after the window has let
  those keyframes go.

>>> from clients.sim.scenes import generate_scene
>>> poses = camera_path(generate_scene(1), "revisit", 40, seed=0)
>>> poses.shape
(40, 4, 4)
>>> camera_path(generate_scene(1), "zigzag", 40, seed=0)
Traceback (most recent call last):
...
ValueError: unknown path kind 'zigzag'; choose one of ['fast_turns', 'loop', 'revisit', 'sparse', 'wall_hug']
"""

from __future__ import annotations

import math

import numpy as np

from clients.sim.robot import robot_trajectory
from clients.sim.scenes import Scene

PATH_KINDS: tuple[str, ...] = ("loop", "sparse", "wall_hug", "fast_turns", "revisit")
"""The path kinds :func:`camera_path` knows."""

FAST_TURN_AMPLITUDE_DEG = 35.0
FAST_TURN_PERIOD_FRAMES = 12
REVISIT_SHARE = 1.0 / 3.0
"""``revisit``: the share of the loop covered a second time."""


def yaw_about_world_z(world_from_cam: np.ndarray, angle_rad: float) -> np.ndarray:
    """The pose turned by ``angle_rad`` about the world's vertical axis through the camera centre."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = world_from_cam.copy()
    out[:3, :3] = rz @ world_from_cam[:3, :3]
    return out


def camera_path(scene: Scene, kind: str, n_frames: int, seed: int) -> np.ndarray:
    """(n_frames, 4, 4) float64 world_from_cam poses of a path of ``kind`` (:data:`PATH_KINDS`).

    Raises:
        ValueError: an unknown kind, or n_frames out of 2..100000.
    """
    if kind not in PATH_KINDS:
        raise ValueError(f"unknown path kind {kind!r}; choose one of {sorted(PATH_KINDS)}")
    if not 2 <= int(n_frames) <= 100_000:
        raise ValueError(f"n_frames {n_frames} out of range 2..100000")
    if kind == "loop":
        return robot_trajectory(scene, n_frames, seed=seed)
    if kind == "sparse":
        return robot_trajectory(scene, n_frames, seed=seed, max_step_m=1.0, max_turn_deg=20.0)
    if kind == "wall_hug":
        return robot_trajectory(scene, n_frames, seed=seed, clearance_m=0.2, max_step_m=0.12)
    if kind == "fast_turns":
        poses = robot_trajectory(scene, n_frames, seed=seed, max_turn_deg=10.0)
        amp = math.radians(FAST_TURN_AMPLITUDE_DEG)
        return np.stack([yaw_about_world_z(p, amp * math.sin(2.0 * math.pi * k / FAST_TURN_PERIOD_FRAMES))
                         for k, p in enumerate(poses)])
    # revisit: one whole loop in n_loop frames (the poses close up: the one after the last is the
    # first), then its first frames again
    n_loop = max(2, int(round(n_frames / (1.0 + REVISIT_SHARE))))
    loop = robot_trajectory(scene, n_loop, seed=seed, max_step_m=1.0, max_turn_deg=12.0)
    again = loop[: n_frames - n_loop]
    return np.concatenate([loop, again]) if len(again) else loop
