"""Robot camera trajectories through a procedural scene.

The robot drives a smooth loop through the free floor near the walls (just in front of the
furniture that stands against them) and looks ACROSS the room: towards a target that wanders
around the room's middle, at furniture height, so views see occluders at several depths. This is
where plain multi-view averaging of open-vocabulary features fails and learned blending can win
(see docs/how-to/simulator.md).

How a loop is made:
1. Rasterise the footprints of every obstacle (all instances except rugs, plus structural blocks)
   into a 5 cm floor grid; distance transform; keep cells at least `clearance_m + 0.15` m away.
2. Cast 36 rays from the middle of the free area; on each, the free cell farthest out (nearest
   the walls) is a waypoint. Consecutive waypoints are joined by straight lines when free, else
   by A* on the grid.
3. Resample by arc length, smooth (Gaussian), keep smoothing only where clearance holds.
4. Walk along the loop from a random start in a random direction with a constant step
   (`min(max_step_m, loop_length / n_frames)`); height, look-at target and yaw wobble follow
   smooth random functions of the distance travelled; yaw rate is limited per frame.

>>> from clients.sim.scenes import generate_scene
>>> poses = robot_trajectory(generate_scene(1), 20, seed=0)
>>> poses.shape
(20, 4, 4)
"""

from __future__ import annotations

import heapq
import math

import numpy as np
from scipy import ndimage

from clients.sim.scenes import Scene

_GRID_M = 0.05
_PLAN_MARGIN_M = 0.15


def default_intrinsics(width: int, height: int, hfov_deg: float = 70.0) -> np.ndarray:
    """(4,) float64 [fx, fy, cx, cy] of a square-pixel pinhole with the principal point centred."""
    if not (1 <= int(width) <= 4096) or not (1 <= int(height) <= 4096):
        raise ValueError(f"image size {width}x{height} out of range 1..4096")
    if not (1.0 <= hfov_deg <= 170.0):
        raise ValueError(f"hfov_deg {hfov_deg} out of range 1..170")
    fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([fx, fx, 0.5 * width, 0.5 * height], dtype=np.float64)


def look_at(eye: np.ndarray, target: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """(4, 4) world_from_cam of an OpenCV camera at `eye` (3,) looking at `target` (3,), world +z up."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:            # looking straight up or down
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    if roll_rad:
        cr, sr = math.cos(roll_rad), math.sin(roll_rad)
        right, down = cr * right + sr * down, -sr * right + cr * down
    world_from_cam = np.eye(4)
    world_from_cam[:3, 0], world_from_cam[:3, 1], world_from_cam[:3, 2] = right, down, fwd
    world_from_cam[:3, 3] = eye
    return world_from_cam


# ----------------------------------------------------------------------------------------------
# Free space
# ----------------------------------------------------------------------------------------------


def obstacle_distance_field(scene: Scene, max_height_m: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Distance (metres) from each floor grid cell centre to the nearest obstacle or wall.

    Returns dist (nx, ny) float64 and origin (2,) = world xy of cell (0, 0)'s corner.
    Obstacles are `scene.obstacle_aabbs()` whose bottom is below `max_height_m`.
    """
    lo, hi = scene.room_min[:2], scene.room_max[:2]
    nx = int(math.ceil((hi[0] - lo[0]) / _GRID_M))
    ny = int(math.ceil((hi[1] - lo[1]) / _GRID_M))
    occ = np.zeros((nx + 2, ny + 2), dtype=bool)   # one ring of wall cells around the room
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    for box in scene.obstacle_aabbs():
        if box[0, 2] >= max_height_m:
            continue
        i0 = int(math.floor((box[0, 0] - lo[0]) / _GRID_M)) + 1
        i1 = int(math.ceil((box[1, 0] - lo[0]) / _GRID_M)) + 1
        j0 = int(math.floor((box[0, 1] - lo[1]) / _GRID_M)) + 1
        j1 = int(math.ceil((box[1, 1] - lo[1]) / _GRID_M)) + 1
        occ[max(i0, 0):max(i1, 0), max(j0, 0):max(j1, 0)] = True
    dist = ndimage.distance_transform_edt(~occ) * _GRID_M
    return dist[1:-1, 1:-1], lo.astype(np.float64)


def _sample_field(field: np.ndarray, origin: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a cell-centred grid at world points xy (N, 2) -> (N,)."""
    g = (xy - origin) / _GRID_M - 0.5
    return ndimage.map_coordinates(field, [g[:, 0], g[:, 1]], order=1, mode="nearest")


def _astar(ok: np.ndarray, a: tuple[int, int], b: tuple[int, int]) -> list[tuple[int, int]] | None:
    """8-connected shortest path on boolean grid `ok` from cell a to b (inclusive)."""
    nx, ny = ok.shape
    sq2 = math.sqrt(2.0)
    openh: list[tuple[float, float, tuple[int, int]]] = [(0.0, 0.0, a)]
    came: dict[tuple[int, int], tuple[int, int]] = {}
    cost = {a: 0.0}
    while openh:
        _, g, cur = heapq.heappop(openh)
        if cur == b:
            path = [cur]
            while cur in came:
                cur = came[cur]
                path.append(cur)
            return path[::-1]
        if g > cost.get(cur, math.inf):
            continue
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == 0 and dj == 0:
                    continue
                n = (cur[0] + di, cur[1] + dj)
                if not (0 <= n[0] < nx and 0 <= n[1] < ny) or not ok[n]:
                    continue
                ng = g + (sq2 if di and dj else 1.0)
                if ng < cost.get(n, math.inf):
                    cost[n] = ng
                    came[n] = cur
                    h = math.hypot(n[0] - b[0], n[1] - b[1])
                    heapq.heappush(openh, (ng + h, ng, n))
    return None


def _line_free(ok: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    n = int(np.ceil(np.abs(b - a).max())) + 1
    pts = np.round(np.linspace(a, b, n * 2)).astype(int)
    return bool(ok[pts[:, 0], pts[:, 1]].all())


def wall_loop(scene: Scene, clearance_m: float = 0.3, n_rays: int = 36) -> np.ndarray:
    """(M, 2) closed loop of world xy points (about 2 cm apart) near the walls, in free space.

    Every point keeps at least `clearance_m` from obstacles and walls (to grid accuracy; planning
    uses an extra 0.15 m margin and smoothing never goes below `clearance_m + 0.05`).
    """
    dist, origin = obstacle_distance_field(scene)
    ok = dist >= clearance_m + _PLAN_MARGIN_M
    labels, n = ndimage.label(ok, structure=np.ones((3, 3)))
    if n == 0:
        raise ValueError(f"scene {scene.style}/{scene.seed}: no free floor with clearance {clearance_m} m")
    sizes = np.bincount(labels.ravel())[1:]
    ok = labels == (1 + int(np.argmax(sizes)))
    cells = np.argwhere(ok)
    centre = cells.mean(0)
    if not ok[tuple(np.round(centre).astype(int))]:  # centre outside (e.g. ring-shaped free area)
        centre = cells[np.argmin(np.linalg.norm(cells - centre, axis=1))].astype(np.float64)
    rel = cells - centre
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    rad = np.linalg.norm(rel, axis=1)
    waypoints = []
    for k in range(n_rays):
        a = -math.pi + (k + 0.5) * 2 * math.pi / n_rays
        d_ang = np.abs((ang - a + math.pi) % (2 * math.pi) - math.pi)
        sel = d_ang < (math.pi / n_rays)
        if sel.any():
            idx = np.flatnonzero(sel)[np.argmax(rad[sel])]
            waypoints.append(cells[idx])
    if len(waypoints) < 3:
        raise ValueError(f"scene {scene.style}/{scene.seed}: free floor too small for a loop")
    path: list[np.ndarray] = []
    for k in range(len(waypoints)):
        a, b = waypoints[k], waypoints[(k + 1) % len(waypoints)]
        if _line_free(ok, a.astype(float), b.astype(float)):
            seg = np.stack([a, b]).astype(np.float64)
        else:
            route = _astar(ok, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])))
            if route is None:
                continue
            seg = np.asarray(route, dtype=np.float64)
        path.extend(seg[:-1])
    pts = np.asarray(path)
    xy = origin + (pts + 0.5) * _GRID_M
    xy = _resample_closed(xy, 0.02)
    return _smooth_closed(xy, dist, origin, clearance_m + 0.05)


def _resample_closed(xy: np.ndarray, spacing_m: float) -> np.ndarray:
    closed = np.concatenate([xy, xy[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(8, int(s[-1] / spacing_m))
    t = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])], 1)


def _smooth_closed(xy: np.ndarray, dist: np.ndarray, origin: np.ndarray, min_clear: float) -> np.ndarray:
    out = xy.copy()
    for sigma in (15.0, 8.0, 4.0):
        cand = ndimage.gaussian_filter1d(out, sigma, axis=0, mode="wrap")
        keep = _sample_field(dist, origin, cand) >= min_clear
        out[keep] = cand[keep]
    return _resample_closed(out, 0.02)


# ----------------------------------------------------------------------------------------------
# Trajectory
# ----------------------------------------------------------------------------------------------


def _smooth_noise(rng: np.random.Generator, s: np.ndarray, period_m: tuple[float, float],
                  n_terms: int = 3) -> np.ndarray:
    """Smooth random function of distance travelled s (N,), values in [-1, 1]."""
    out = np.zeros_like(s)
    for _ in range(n_terms):
        per = rng.uniform(*period_m)
        out += np.sin(2 * np.pi * s / per + rng.uniform(0, 2 * np.pi))
    return out / n_terms


def robot_trajectory(
    scene: Scene, n_frames: int, seed: int, *, height_range_m: tuple[float, float] = (0.8, 1.6),
    clearance_m: float = 0.3, max_step_m: float = 0.08, max_turn_deg: float = 6.0,
) -> np.ndarray:
    """Camera poses of a robot driving near the walls and looking across the room.

    Args:
        scene: the room.
        n_frames: number of poses, 1..100000.
        seed: randomness of start, direction, heights and gaze (the loop itself is the scene's).
        height_range_m: camera height above the floor (min, max), metres.
        clearance_m: minimum horizontal distance from the camera to any obstacle box or wall.
        max_step_m: largest horizontal distance between consecutive camera centres (the height
            changes smoothly on top of it, a few millimetres a frame).
        max_turn_deg: largest yaw change between consecutive frames.

    Returns:
        (F, 4, 4) float64 world_from_cam (OpenCV optical camera frame).
    """
    if not (1 <= int(n_frames) <= 100_000):
        raise ValueError(f"n_frames {n_frames} out of range 1..100000")
    lo_h, hi_h = (float(x) for x in height_range_m)
    room_h = float(scene.room_max[2] - scene.room_min[2])
    if not (0.1 <= lo_h <= hi_h <= room_h - 0.1):
        raise ValueError(
            f"height_range_m {height_range_m} must satisfy 0.1 <= min <= max <= {room_h - 0.1:.2f}")
    if not (0.0 < max_step_m <= 1.0):
        raise ValueError(f"max_step_m {max_step_m} out of range (0, 1]")
    rng = np.random.default_rng(seed)
    loop = wall_loop(scene, clearance_m)
    closed = np.concatenate([loop, loop[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(cum[-1])
    step = min(max_step_m, length / n_frames)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    s = (rng.uniform(0, length) + direction * step * np.arange(n_frames)) % length
    xy = np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], 1)
    travelled = step * np.arange(n_frames)

    z = scene.room_min[2] + lo_h + (hi_h - lo_h) * (0.5 + 0.5 * _smooth_noise(rng, travelled, (4.0, 9.0)))
    size = scene.room_max - scene.room_min
    centre = 0.5 * (scene.room_min + scene.room_max)
    tx = centre[0] + 0.3 * size[0] * _smooth_noise(rng, travelled, (3.0, 8.0))
    ty = centre[1] + 0.3 * size[1] * _smooth_noise(rng, travelled, (3.0, 8.0))
    tz = scene.room_min[2] + 0.75 + 0.45 * _smooth_noise(rng, travelled, (3.0, 7.0))
    dx, dy = tx - xy[:, 0], ty - xy[:, 1]
    yaw = np.unwrap(np.arctan2(dy, dx)) + np.radians(25.0) * _smooth_noise(rng, travelled, (2.0, 5.0))
    if n_frames > 1:
        yaw = ndimage.gaussian_filter1d(yaw, 3.0, mode="nearest")
        max_turn = math.radians(max_turn_deg)
        for k in range(1, n_frames):  # rate limit
            yaw[k] = yaw[k - 1] + float(np.clip(yaw[k] - yaw[k - 1], -max_turn, max_turn))
    horiz = np.maximum(np.hypot(dx, dy), 1.0)
    pitch = np.clip(np.arctan2(tz - z, horiz), math.radians(-35.0), math.radians(12.0))
    roll = np.radians(1.5) * _smooth_noise(rng, travelled, (2.0, 4.0))
    return poses_from_angles(xy, z, yaw, pitch, roll)


def poses_from_angles(
    xy: np.ndarray,  # (n, 2) camera positions in the floor plane (m)
    z: np.ndarray,  # (n,) camera heights (m)
    yaw: np.ndarray,  # (n,) heading about world z (rad)
    pitch: np.ndarray,  # (n,) elevation of the optical axis (rad)
    roll: np.ndarray,  # (n,) roll about it (rad)
) -> np.ndarray:  # (n, 4, 4) world_from_cam
    """Camera poses looking along the heading and elevation at each position (:func:`look_at`)."""
    poses = np.empty((xy.shape[0], 4, 4))
    for k in range(xy.shape[0]):
        eye = np.array([xy[k, 0], xy[k, 1], z[k]])
        fwd = np.array([math.cos(pitch[k]) * math.cos(yaw[k]), math.cos(pitch[k]) * math.sin(yaw[k]),
                        math.sin(pitch[k])])
        poses[k] = look_at(eye, eye + fwd, roll_rad=float(roll[k]))
    return poses
