"""A camera tour of a floor (`clients.sim.scenes.floor`): every room in turn, then the first rooms
again (a robot that comes back where it started: for "nothing forgotten" checks).

The route, on the floor plan:

1. from the corridor in front of the room's doorway, straight in through the doorway to a point
   0.75 m inside the room;
2. the room's own loop near its walls (`clients.sim.robot.wall_loop`, looking across the room),
   reached from there and left again by A* on the room's free floor;
3. out through the doorway to the corridor's centre line, along the corridor (and along the
   spine between two bands' corridors) to the next room's doorway.

After the last room the tour goes back to rooms 0 .. `revisit_rooms` - 1 and loops in them again.
The camera moves along the route with a constant step (the route's length over the frames); when
the frames are too few for whole loops at `max_step_m`, each room's loop is shortened (to a
quarter at least) and the step grows. In a room the camera looks across it (a target wandering
around its middle, as in `robot_trajectory`); between rooms it looks where it goes; the yaw turns
at most `max_turn_deg` a frame. The camera's centre stays in free space: `clearance_m` from walls
and obstacle boxes in rooms, the middle of doorways and corridors between them.

>>> from clients.sim.scenes.floor import generate_floor
>>> tour = floor_tour(generate_floor(0, 3), 300, seed=0)
>>> tour.poses.shape, sorted(set(tour.room.tolist()) - {-1})
((300, 4, 4), [0, 1, 2])
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from clients.sim.robot import _astar, _smooth_noise, obstacle_distance_field, poses_from_angles, wall_loop
from clients.sim.scenes import Scene
from clients.sim.scenes.floor import Floor, FloorRoom

_GRID_M = 0.05
DOOR_INSIDE_M = 0.75
"""How far inside a room (from its wall) the tour's straight run through the doorway ends."""
MIN_LOOP_SHARE = 0.25


@dataclass
class Tour:
    """Poses of a floor tour and where each frame is."""

    poses: np.ndarray       # (F, 4, 4) float64 world_from_cam
    room: np.ndarray        # (F,) int32 room whose interior holds the camera, -1 in doorways / corridors
    visits: list[int]       # rooms in the order the tour loops in them (the revisits at the end)
    loop_share: float       # share of each room's loop the tour covers (1: whole loops)
    step_m: float           # camera move a frame


def floor_tour(floor: Floor, n_frames: int, seed: int, *, revisit_rooms: int = 2, clearance_m: float = 0.3,
               max_step_m: float = 0.08, max_turn_deg: float = 6.0,
               height_range_m: tuple[float, float] = (0.8, 1.6)) -> Tour:
    """The tour of every room of `floor` in `n_frames` poses, then rooms 0 .. revisit_rooms - 1 again.

    Raises:
        ValueError: n_frames out of range (10 a visit .. 100000), revisit_rooms out of 0..rooms,
            a height range that does not fit under the doorways.
    """
    n_rooms = len(floor.rooms)
    if not 0 <= revisit_rooms <= n_rooms:
        raise ValueError(f"revisit_rooms {revisit_rooms} out of range 0..{n_rooms}")
    visits = list(range(n_rooms)) + list(range(revisit_rooms))
    if not 10 * len(visits) <= int(n_frames) <= 100_000:
        raise ValueError(f"n_frames {n_frames} out of range {10 * len(visits)}..100000 for a tour of "
                         f"{len(visits)} room visits (10 frames a visit at least)")
    lo_h, hi_h = (float(x) for x in height_range_m)
    door_h = min(room.doorway.height_m for room in floor.rooms)
    if not 0.1 <= lo_h <= hi_h <= door_h - 0.2:
        raise ValueError(f"height_range_m {height_range_m} must satisfy 0.1 <= min <= max <= "
                         f"{door_h - 0.2:.2f} (under the doorways)")
    if not 0.0 < max_step_m <= 1.0:
        raise ValueError(f"max_step_m {max_step_m} out of range (0, 1]")
    loops = {k: _room_legs(floor.rooms[k], clearance_m) for k in set(visits)}
    loop_total = sum(_length(loops[k][1]) for k in visits)
    share = 1.0
    for _ in range(2):  # the share depends on the transit length, which hardly depends on it
        legs, modes = _route(floor, visits, loops, share, clearance_m)
        pts = np.concatenate(legs)
        total = _length(pts)
        transit_len = total - share * loop_total
        budget = n_frames * max_step_m - transit_len
        share = float(np.clip(budget / max(loop_total, 1e-9), MIN_LOOP_SHARE, 1.0))
    legs, modes = _route(floor, visits, loops, share, clearance_m)
    xy, look_room, step = _walk(legs, modes, n_frames)
    poses = _gaze(floor, xy, look_room, step, seed, max_turn_deg, (lo_h, hi_h))
    return Tour(poses, floor.room_at(xy), visits, share, step)


def _length(pts: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0


def _room_legs(room: FloorRoom, clearance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World xy of the way in (from 0.75 m inside the doorway to the loop) and of the loop (closed:
    its last point is its first), both in free space."""
    local = room.local
    loop = wall_loop(local, clearance_m)
    door_local = room.door_xy - room.lo
    inside = door_local - room.door_normal * (DOOR_INSIDE_M + 0.05)
    start = int(np.argmin(np.linalg.norm(loop - inside, axis=1)))
    loop = np.concatenate([loop[start:], loop[:start], loop[start:start + 1]])
    way_in = _free_path(local, inside, loop[0], clearance_m)
    return way_in + room.lo, loop + room.lo


def _free_path(scene_local: Scene, a: np.ndarray, b: np.ndarray, clearance_m: float) -> np.ndarray:
    """(M, 2) xy from a to b through cells of the room's free floor, the widest clearance that
    connects them first (clearance + 0.15, + 0.05, + 0)."""
    dist, origin = obstacle_distance_field(scene_local)
    ia = tuple(np.clip(((a - origin) / _GRID_M).astype(int), 0, np.array(dist.shape) - 1))
    ib = tuple(np.clip(((b - origin) / _GRID_M).astype(int), 0, np.array(dist.shape) - 1))
    for margin in (0.15, 0.05, 0.0):
        ok = dist >= clearance_m + margin
        if not (ok[ia] and ok[ib]):
            continue
        labels, _ = ndimage.label(ok, structure=np.ones((3, 3)))
        if labels[ia] != labels[ib]:
            continue
        route = _astar(ok, (int(ia[0]), int(ia[1])), (int(ib[0]), int(ib[1])))
        if route is not None:
            cells = origin + (np.asarray(route, dtype=np.float64) + 0.5) * _GRID_M
            return np.concatenate([a[None], cells[1:-1], b[None]]) if len(cells) > 2 else np.stack([a, b])
    raise ValueError(f"no free way of clearance {clearance_m} m between {a.round(2).tolist()} and "
                     f"{b.round(2).tolist()} in room {scene_local.style}/{scene_local.seed}")


def _route(floor: Floor, visits: list[int], loops: dict[int, tuple[np.ndarray, np.ndarray]],
           share: float, clearance_m: float) -> tuple[list[np.ndarray], list[int]]:
    """The tour as legs of xy points and, per leg, the room the camera looks across (-1: it looks
    where it goes)."""
    legs: list[np.ndarray] = []
    modes: list[int] = []
    here = _door_out(floor, floor.rooms[visits[0]])
    for k in visits:
        room = floor.rooms[k]
        way_in, loop = loops[k]
        legs.append(np.concatenate([here[None], _corridor_way(floor, here, room),
                                    _door_out(floor, room)[None], way_in]))
        modes.append(-1)
        n_loop = max(2, int(round(share * (len(loop) - 1))) + 1)
        part = loop[:n_loop]
        legs.append(part)
        modes.append(k)
        if n_loop < len(loop):   # back to where the loop began (A* on the room's free floor)
            back = _free_path(room.local, part[-1] - room.lo, loop[0] - room.lo, clearance_m) + room.lo
            legs.append(back)
            modes.append(-1)
        legs.append(np.concatenate([way_in[::-1], _door_out(floor, room)[None]]))
        modes.append(-1)
        here = _door_out(floor, room)
    return legs, modes


def _door_out(floor: Floor, room: FloorRoom) -> np.ndarray:
    """The point on the room's corridor's centre line in front of its doorway."""
    return np.array([room.door_xy[0], floor.corridor_y(room.band)])


def _corridor_way(floor: Floor, here: np.ndarray, room: FloorRoom) -> np.ndarray:
    """(M, 2) corners between a corridor point `here` and the room's doorway: none within one band;
    from another band, to the spine and along it."""
    target_y = floor.corridor_y(room.band)
    if abs(here[1] - target_y) < 1e-6:
        return np.zeros((0, 2))
    sx = floor.spine_x()
    return np.array([[sx, here[1]], [sx, target_y]])


def _walk(legs: list[np.ndarray], modes: list[int], n_frames: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Frame positions with a constant step along the legs, the room each frame looks across."""
    pts = np.concatenate(legs)
    mode = np.concatenate([np.full(len(leg), m) for leg, m in zip(legs, modes, strict=True)])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.linspace(0.0, cum[-1], n_frames)
    xy = np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], 1)
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(pts) - 1)
    return xy, mode[idx], float(cum[-1] / max(n_frames - 1, 1))


def _gaze(floor: Floor, xy: np.ndarray, look_room: np.ndarray, step: float, seed: int, max_turn_deg: float,
          heights: tuple[float, float]) -> np.ndarray:
    """Poses: heights and targets from smooth noise of the distance travelled; across the room in
    a room's loop, along the way elsewhere, blended over about a metre."""
    n = len(xy)
    rng = np.random.default_rng(seed)
    travelled = step * np.arange(n)
    z = heights[0] + (heights[1] - heights[0]) * (0.5 + 0.5 * _smooth_noise(rng, travelled, (4.0, 9.0)))
    centres = np.stack([0.5 * (r.lo + r.hi) for r in floor.rooms])
    sizes = np.stack([r.hi - r.lo for r in floor.rooms])
    in_loop = look_room >= 0
    k = np.maximum(look_room, 0)
    target = centres[k] + 0.3 * sizes[k] * np.stack([_smooth_noise(rng, travelled, (3.0, 8.0)),
                                                     _smooth_noise(rng, travelled, (3.0, 8.0))], 1)
    across = target - xy
    ahead = np.gradient(xy, axis=0) if n > 1 else np.zeros_like(xy)
    for arr in (across, ahead):
        arr /= np.maximum(np.linalg.norm(arr, axis=1, keepdims=True), 1e-9)
    sigma = max(1.0, 0.5 / max(step, 1e-6))
    w = ndimage.gaussian_filter1d(in_loop.astype(np.float64), sigma, mode="nearest")[:, None]
    fwd = w * across + (1.0 - w) * ahead
    still = np.linalg.norm(fwd, axis=1) < 1e-6   # across and ahead opposite, half and half
    fwd[still] = ahead[still]
    yaw = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
    yaw += np.radians(20.0) * w[:, 0] * _smooth_noise(rng, travelled, (2.0, 5.0))
    max_turn = math.radians(max_turn_deg)
    for i in range(1, n):
        yaw[i] = yaw[i - 1] + float(np.clip(yaw[i] - yaw[i - 1], -max_turn, max_turn))
    tz = 0.75 + 0.45 * _smooth_noise(rng, travelled, (3.0, 7.0))
    horiz = np.maximum(np.linalg.norm(target - xy, axis=1), 1.0)
    pitch_room = np.clip(np.arctan2(tz - z, horiz), math.radians(-35.0), math.radians(12.0))
    pitch = w[:, 0] * pitch_room + (1.0 - w[:, 0]) * math.radians(-8.0)
    roll = np.radians(1.5) * _smooth_noise(rng, travelled, (2.0, 4.0))
    return poses_from_angles(xy, z, yaw, pitch, roll)
