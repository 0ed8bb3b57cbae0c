"""Mesh pieces: boxes, cylinders and ellipsoids (`_Part`), and objects built from them (`_Object`).

An `_Object` lives in its local frame (x along the wall, y away from it, z up); placement
rotates it by multiples of 90 degrees about +z and moves it into the room.

>>> from clients.sim.scenes.appearance import Material
>>> part = _box((0, 0, 0), (1, 2, 3), Material((1, 1, 1), (1, 1, 1)))
>>> part.vertices.shape, part.triangles.shape, part.aabb.tolist()
((8, 3), (12, 3), [[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from clients.sim.scenes.appearance import Material

_BOX_FACES = np.array([
    [0, 2, 1], [0, 3, 2],  # z-
    [4, 5, 6], [4, 6, 7],  # z+
    [0, 1, 5], [0, 5, 4],  # y-
    [2, 3, 7], [2, 7, 6],  # y+
    [1, 2, 6], [1, 6, 5],  # x+
    [3, 0, 4], [3, 4, 7],  # x-
], dtype=np.int32)


@dataclass
class _Part:
    vertices: np.ndarray   # (n, 3) float64 in the owner's frame
    triangles: np.ndarray  # (m, 3) int32
    material: Material

    def transformed(self, rot_k: int, offset: np.ndarray) -> _Part:
        return _Part(_rotate_k(self.vertices, rot_k) + offset, self.triangles, self.material)

    @property
    def aabb(self) -> np.ndarray:
        return np.stack([self.vertices.min(0), self.vertices.max(0)])


def _box(lo: tuple[float, float, float] | np.ndarray, hi: tuple[float, float, float] | np.ndarray,
         material: Material) -> _Part:
    lo_a, hi_a = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    x0, y0, z0 = lo_a
    x1, y1, z1 = hi_a
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
    return _Part(v, _BOX_FACES.copy(), material)


def _cylinder(cx: float, cy: float, z0: float, z1: float, radius: float, material: Material,
              sections: int = 16, radius_top: float | None = None) -> _Part:
    """Closed (possibly tapered) cylinder along z."""
    r_top = radius if radius_top is None else radius_top
    ang = np.arange(sections) * (2.0 * np.pi / sections)
    ring0 = np.stack([cx + radius * np.cos(ang), cy + radius * np.sin(ang), np.full(sections, z0)], 1)
    ring1 = np.stack([cx + r_top * np.cos(ang), cy + r_top * np.sin(ang), np.full(sections, z1)], 1)
    v = np.concatenate([ring0, ring1, [[cx, cy, z0], [cx, cy, z1]]])
    i = np.arange(sections)
    j = (i + 1) % sections
    side = np.concatenate([np.stack([i, j, j + sections], 1), np.stack([i, j + sections, i + sections], 1)])
    bottom = np.stack([np.full(sections, 2 * sections), j, i], 1)
    top = np.stack([np.full(sections, 2 * sections + 1), i + sections, j + sections], 1)
    return _Part(v, np.concatenate([side, bottom, top]).astype(np.int32), material)


def _ellipsoid(centre: tuple[float, float, float], radii: tuple[float, float, float],
               material: Material, n_lat: int = 8, n_lon: int = 12) -> _Part:
    lat = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    lon = np.arange(n_lon) * (2.0 * np.pi / n_lon)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    pts = np.stack([np.sin(la) * np.cos(lo), np.sin(la) * np.sin(lo), np.cos(la)], -1).reshape(-1, 3)
    v = np.concatenate([[[0, 0, 1.0]], pts, [[0, 0, -1.0]]]) * np.asarray(radii) + np.asarray(centre)
    tris = []
    top, bot = 0, 1 + pts.shape[0]
    for b in range(n_lon):
        tris.append([top, 1 + b, 1 + (b + 1) % n_lon])
    for a in range(n_lat - 2):
        for b in range(n_lon):
            p00 = 1 + a * n_lon + b
            p01 = 1 + a * n_lon + (b + 1) % n_lon
            p10 = p00 + n_lon
            p11 = p01 + n_lon
            tris += [[p00, p10, p11], [p00, p11, p01]]
    last = 1 + (n_lat - 2) * n_lon
    for b in range(n_lon):
        tris.append([bot, last + (b + 1) % n_lon, last + b])
    return _Part(v, np.asarray(tris, dtype=np.int32), material)


def _rotate_k(v: np.ndarray, k: int) -> np.ndarray:
    """Rotate (n, 3) points by k * 90 degrees about +z."""
    k %= 4
    x, y = v[:, 0], v[:, 1]
    if k == 0:
        xr, yr = x, y
    elif k == 1:
        xr, yr = -y, x
    elif k == 2:
        xr, yr = -x, -y
    else:
        xr, yr = y, -x
    return np.stack([xr, yr, v[:, 2]], 1)


@dataclass
class _Object:
    """An object in its local frame: x along the wall, y away from the wall (front is +y)."""

    class_name: str
    parts: list[_Part]
    children: list[_Object] = field(default_factory=list)  # resting on / hanging from this one

    def aabb(self) -> np.ndarray:
        """(2, 3) box of this object's own parts, or of all members for a group (no parts)."""
        if self.parts:
            v = np.concatenate([p.vertices for p in self.parts])
            return np.stack([v.min(0), v.max(0)])
        arr = np.stack(self.all_aabbs())
        return np.stack([arr[:, 0].min(0), arr[:, 1].max(0)])

    def transformed(self, rot_k: int, offset: np.ndarray) -> _Object:
        return _Object(self.class_name, [p.transformed(rot_k, offset) for p in self.parts],
                       [c.transformed(rot_k, offset) for c in self.children])

    def all_aabbs(self) -> list[np.ndarray]:
        """Boxes of this object (if it has parts) and of everything resting on it."""
        out = [self.aabb()] if self.parts else []
        for c in self.children:
            out += c.all_aabbs()
        return out


def _group(name: str, members: list[_Object]) -> _Object:
    """Several objects placed as one rigid group (the group itself has no parts)."""
    return _Object(name, [], members)
