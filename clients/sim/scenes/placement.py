"""Placement of objects in a room: against a wall or in the middle, never touching another
object's box (a 1 cm gap is kept; an object resting on another one touches only the part it
rests on) and never cutting the free floor into pieces, so a robot can always drive around.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from clients.sim.scenes.primitives import _Object, _rotate_k
from clients.sim.scenes.rand import _Rand

_GAP_M = 0.01          # clearance kept between unrelated objects
_GRID_M = 0.05         # floor occupancy grid for the connectivity check
_ROBOT_RADIUS_M = 0.35  # half-width of the corridor that must stay connected


class _Placer:
    def __init__(self, r: _Rand, size: np.ndarray, structures: list[np.ndarray]) -> None:
        self.r = r
        self.size = size  # (3,) interior size
        self.placed: list[_Object] = []          # world-frame objects (with children)
        self.boxes: list[np.ndarray] = []        # (2, 3) boxes that new objects must avoid
        self.boxes += structures
        nx, ny = int(math.ceil(size[0] / _GRID_M)), int(math.ceil(size[1] / _GRID_M))
        self.grid = np.zeros((nx, ny), dtype=bool)
        for b in structures:
            self._rasterise(self.grid, b)

    def _rasterise(self, grid: np.ndarray, box: np.ndarray) -> None:
        i0 = max(0, int(math.floor(box[0, 0] / _GRID_M)))
        i1 = min(grid.shape[0], int(math.ceil(box[1, 0] / _GRID_M)))
        j0 = max(0, int(math.floor(box[0, 1] / _GRID_M)))
        j1 = min(grid.shape[1], int(math.ceil(box[1, 1] / _GRID_M)))
        grid[i0:i1, j0:j1] = True

    def _free_ok(self, new_boxes: list[np.ndarray]) -> bool:
        grid = self.grid.copy()
        for b in new_boxes:
            self._rasterise(grid, b)
        free = ~grid
        free[0, :] = free[-1, :] = free[:, 0] = free[:, -1] = False
        dist = ndimage.distance_transform_edt(free) * _GRID_M
        ok = dist >= _ROBOT_RADIUS_M
        labels, n = ndimage.label(ok)
        if n == 0:
            return False
        sizes = np.bincount(labels.ravel())[1:] * _GRID_M**2
        # one corridor network; tiny pockets behind furniture do not count
        return int((sizes > 0.3).sum()) == 1 and sizes.max() > 0.2 * self.size[0] * self.size[1]

    def _inside(self, box: np.ndarray) -> bool:
        return bool((box[0] >= -1e-9).all() and (box[1] <= self.size + 1e-9).all())

    def _collides(self, box: np.ndarray, extra: list[np.ndarray] | None = None) -> bool:
        lo, hi = box[0] - _GAP_M, box[1] + _GAP_M
        for b in self.boxes + (extra or []):
            if (lo < b[1]).all() and (hi > b[0]).all():
                return True
        return False

    def wall_pose(self, wall: int, along: float, half_w: float) -> tuple[int, np.ndarray] | None:
        """Rotation and offset placing a local-frame object against `wall` at `along`."""
        sx, sy = float(self.size[0]), float(self.size[1])
        length = sx if wall in (0, 2) else sy
        if along - half_w < 0 or along + half_w > length:
            return None
        if wall == 0:
            return 0, np.array([along, 0.0, 0.0])
        if wall == 1:
            return 1, np.array([sx, along, 0.0])
        if wall == 2:
            return 2, np.array([sx - along, sy, 0.0])
        return 3, np.array([0.0, sy - along, 0.0])

    def try_place(self, obj: _Object, *, wall: int | None = None, central: bool = False,
                  blocks_floor: bool = True, walkway_m: float = 0.0, tries: int = 40,
                  reserve: np.ndarray | None = None) -> _Object | None:
        """Place `obj` against a random wall (or in the middle); returns the world object."""
        local = obj.aabb()
        half_w = max(-local[0, 0], local[1, 0])
        for _ in range(tries):
            if central:
                k = int(self.r.rng.integers(4))
                margin = 0.9
                lo_rot = _rotate_k(local, k)
                ext_lo, ext_hi = lo_rot.min(0), lo_rot.max(0)
                xmin, xmax = margin - ext_lo[0], self.size[0] - margin - ext_hi[0]
                ymin, ymax = margin - ext_lo[1], self.size[1] - margin - ext_hi[1]
                if xmin > xmax or ymin > ymax:
                    return None
                off = np.array([self.r.u(xmin, xmax), self.r.u(ymin, ymax), 0.0])
                pose: tuple[int, np.ndarray] | None = (k, off)
            else:
                w = int(self.r.rng.integers(4)) if wall is None else wall
                length = self.size[0] if w in (0, 2) else self.size[1]
                pose = self.wall_pose(w, self.r.u(half_w, max(half_w, length - half_w)), half_w)
            if pose is None:
                continue
            placed = obj.transformed(*pose)
            boxes = placed.all_aabbs()
            if not all(self._inside(b) for b in boxes):
                continue
            check = [b.copy() for b in boxes]
            if walkway_m > 0:
                for b in check:
                    b[0, :2] -= walkway_m
                    b[1, :2] += walkway_m
            if any(self._collides(b) for b in check):
                continue
            res_world: np.ndarray | None = None
            if reserve is not None:
                res_world = placed_reserve(reserve, pose)
                if self._collides(res_world):
                    continue
            if blocks_floor and not self._free_ok([b for b in boxes if b[0, 2] < 2.0]):
                continue
            self.commit(placed, blocks_floor, res_world)
            return placed
        return None

    def commit(self, placed: _Object, blocks_floor: bool, reserve: np.ndarray | None = None) -> None:
        self.placed.append(placed)
        for b in placed.all_aabbs():
            self.boxes.append(b)
        if reserve is not None:
            self.boxes.append(reserve)
        if blocks_floor:
            for b in placed.all_aabbs():
                if b[0, 2] < 2.0:
                    self._rasterise(self.grid, b)


def placed_reserve(reserve: np.ndarray, pose: tuple[int, np.ndarray]) -> np.ndarray:
    """World AABB of a local-frame keep-out box (2, 3) under a wall pose."""
    pts = np.array([[x, y, z] for x in reserve[:, 0] for y in reserve[:, 1] for z in reserve[:, 2]])
    w = _rotate_k(pts, pose[0]) + pose[1]
    return np.stack([w.min(0), w.max(0)])
