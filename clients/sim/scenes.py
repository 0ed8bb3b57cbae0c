"""Procedural indoor scenes for the simulated robot (client side, ground truth lives here).

A scene is one room (rectangular, or L-shaped when a structural block fills a corner) built
from axis-aligned boxes, cylinders and spheres. Every triangle carries a class label (index into
`CLASS_NAMES`), an instance id and a material (base colour, second colour, procedural texture
kind and scale) that the ray caster (`clients.sim.raycast`) turns into colour at the hit point.

Furniture comes in functional *zones* (living, dining, bedroom, kitchen, bathroom, office), each
a set of objects placed against walls or in the room's middle. Placement rejects any candidate
whose bounding box touches another object's box (a 1 cm gap is kept; an object resting on
another one, e.g. a pillow on a bed, touches only the part it rests on) and any candidate that
would cut the free floor into pieces, so a robot can always drive around the room.

World frame: metres, right-handed, +z up; the room interior is `[room_min, room_max]` with
`room_min = (0, 0, 0)`.

>>> scene = generate_scene(3, "apartment")
>>> scene.vertices.shape[1], scene.triangles.shape[1]
(3, 3)
>>> bool((scene.face_label >= 0).all() and (scene.face_label < len(CLASS_NAMES)).all())
True
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import TypeVar

import numpy as np
from scipy import ndimage

# ----------------------------------------------------------------------------------------------
# Vocabulary
# ----------------------------------------------------------------------------------------------

SCANNET20: tuple[str, ...] = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "desk", "curtain", "refrigerator", "shower curtain", "toilet", "sink",
    "bathtub", "otherfurniture",
)
"""The 20 ScanNet benchmark classes, in the benchmark's order (label ids 0..19)."""

EXTRA_CLASSES: tuple[str, ...] = (
    "ceiling", "lamp", "plant", "monitor", "pillow", "rug", "television", "mirror", "clock",
    "vase", "towel", "trash can",
)
"""Classes outside the ScanNet-20 set (open vocabulary); label ids 20.. in this order."""

CLASS_NAMES: tuple[str, ...] = SCANNET20 + EXTRA_CLASSES
"""Label id -> class name. The ScanNet-20 classes come first, in the same order."""

LABEL_OF: dict[str, int] = {name: i for i, name in enumerate(CLASS_NAMES)}
"""Class name -> label id."""

NON_BLOCKING_CLASSES: frozenset[str] = frozenset({"rug"})
"""Classes a robot may drive over (all other instances are obstacles for trajectories)."""


class Texture(IntEnum):
    """Procedural texture kinds, evaluated per hit point by the renderer."""

    PLAIN = 0      # base colour with faint noise (still enough for stereo matching)
    CHECKER = 1    # two-colour checker board (floor tiles)
    STRIPES = 2    # two-colour stripes (wallpaper, fabric)
    WOOD = 3       # wood grain bands distorted by noise
    FABRIC = 4     # fine two-scale noise weave
    TILES = 5      # square tiles with grout lines (colour2 = grout)
    MARBLE = 6     # veins from turbulent noise
    PATCHES = 7    # cells of random colours (book spines, paintings)
    SKY = 8        # bright gradient seen through a window; not lit (emissive)


@dataclass(frozen=True)
class Material:
    """Appearance of a part: colours are linear RGB in [0, 1]."""

    colour: tuple[float, float, float]
    colour2: tuple[float, float, float]
    texture: Texture = Texture.PLAIN
    scale_m: float = 0.2  # texture period, metres


@dataclass(frozen=True)
class Light:
    """One point light plus ambient term (Lambert shading)."""

    position: np.ndarray  # (3,) world metres
    colour: np.ndarray    # (3,) RGB multiplier
    diffuse: float        # diffuse strength at distance `falloff_m`
    ambient: float        # ambient strength
    falloff_m: float      # distance at which the diffuse term halves


Colour = tuple[float, float, float]


@dataclass(frozen=True)
class SceneStyle:
    """Parameters of a family of scenes: sizes, palettes, textures, light and furniture mix."""

    name: str
    room_x_m: tuple[float, float]          # interior size along x, metres (min, max)
    room_y_m: tuple[float, float]          # interior size along y
    ceiling_m: tuple[float, float]         # ceiling height
    notch_prob: float                      # probability of an L-shaped room (block in a corner)
    n_zones: tuple[int, int]               # how many furniture zones per room (min, max)
    zone_weights: dict[str, float]         # relative frequency of each zone
    n_windows: tuple[int, int]
    n_clutter: tuple[int, int]             # free-standing objects in the middle (min, max)
    wall_colours: tuple[Colour, ...]
    wall_textures: tuple[tuple[Texture, float], ...]   # (kind, scale_m)
    floor_colours: tuple[tuple[Colour, Colour], ...]   # (colour, colour2)
    floor_textures: tuple[tuple[Texture, float], ...]
    wood_colours: tuple[Colour, ...]
    fabric_colours: tuple[Colour, ...]
    accent_colours: tuple[Colour, ...]
    appliance_colours: tuple[Colour, ...]
    ceiling_colour: Colour
    light_colour: Colour
    light_diffuse: tuple[float, float]
    ambient: tuple[float, float]
    size_jitter: float                     # relative random scaling of furniture dimensions


STYLES: dict[str, SceneStyle] = {
    # Training style: warm, wooden, smallish rooms, rectangular.
    "apartment": SceneStyle(
        name="apartment",
        room_x_m=(4.6, 7.0), room_y_m=(3.8, 5.6), ceiling_m=(2.45, 2.75),
        notch_prob=0.0, n_zones=(3, 4),
        zone_weights={"living": 1.0, "dining": 1.0, "bedroom": 1.0, "kitchen": 1.0,
                      "bathroom": 0.8, "office": 0.8},
        n_windows=(1, 2), n_clutter=(1, 3),
        wall_colours=((0.86, 0.80, 0.70), (0.80, 0.76, 0.66), (0.90, 0.86, 0.78),
                      (0.74, 0.78, 0.70), (0.84, 0.72, 0.62)),
        wall_textures=((Texture.PLAIN, 0.25), (Texture.STRIPES, 0.12), (Texture.FABRIC, 0.08)),
        floor_colours=(((0.55, 0.38, 0.22), (0.42, 0.28, 0.16)), ((0.62, 0.46, 0.30), (0.50, 0.36, 0.22)),
                       ((0.70, 0.66, 0.58), (0.56, 0.52, 0.46))),
        floor_textures=((Texture.WOOD, 0.18), (Texture.TILES, 0.40), (Texture.CHECKER, 0.35)),
        wood_colours=((0.55, 0.36, 0.20), (0.65, 0.47, 0.28), (0.42, 0.27, 0.15), (0.72, 0.58, 0.40)),
        fabric_colours=((0.62, 0.30, 0.22), (0.35, 0.45, 0.30), (0.70, 0.62, 0.45), (0.45, 0.35, 0.50),
                        (0.75, 0.55, 0.35)),
        accent_colours=((0.80, 0.30, 0.20), (0.85, 0.70, 0.25), (0.30, 0.50, 0.35), (0.55, 0.30, 0.45)),
        appliance_colours=((0.92, 0.92, 0.90), (0.85, 0.85, 0.82)),
        ceiling_colour=(0.93, 0.91, 0.86),
        light_colour=(1.0, 0.92, 0.80),
        light_diffuse=(0.60, 0.80), ambient=(0.35, 0.45),
        size_jitter=0.10,
    ),
    # Unseen style: cool, bright and saturated, big rooms, often L-shaped, marble and concrete.
    "studio": SceneStyle(
        name="studio",
        room_x_m=(6.0, 8.5), room_y_m=(4.8, 6.8), ceiling_m=(2.9, 3.3),
        notch_prob=0.6, n_zones=(3, 5),
        zone_weights={"living": 1.2, "dining": 0.8, "bedroom": 0.7, "kitchen": 1.0,
                      "bathroom": 0.6, "office": 1.2},
        n_windows=(2, 3), n_clutter=(2, 4),
        wall_colours=((0.92, 0.93, 0.95), (0.70, 0.72, 0.75), (0.55, 0.65, 0.75), (0.88, 0.88, 0.82)),
        wall_textures=((Texture.MARBLE, 0.60), (Texture.TILES, 0.55), (Texture.PLAIN, 0.40)),
        floor_colours=(((0.35, 0.36, 0.38), (0.20, 0.21, 0.22)), ((0.85, 0.85, 0.84), (0.60, 0.60, 0.62)),
                       ((0.20, 0.22, 0.30), (0.40, 0.42, 0.50))),
        floor_textures=((Texture.MARBLE, 0.80), (Texture.CHECKER, 0.60), (Texture.FABRIC, 0.10)),
        wood_colours=((0.85, 0.82, 0.75), (0.20, 0.20, 0.22), (0.90, 0.90, 0.92), (0.60, 0.30, 0.20)),
        fabric_colours=((0.10, 0.45, 0.70), (0.85, 0.20, 0.25), (0.95, 0.75, 0.10), (0.20, 0.65, 0.45),
                        (0.30, 0.30, 0.35)),
        accent_colours=((0.10, 0.60, 0.85), (0.95, 0.40, 0.10), (0.60, 0.20, 0.80), (0.20, 0.80, 0.50)),
        appliance_colours=((0.75, 0.77, 0.80), (0.25, 0.25, 0.28)),
        ceiling_colour=(0.96, 0.97, 1.00),
        light_colour=(0.85, 0.93, 1.05),
        light_diffuse=(0.70, 0.95), ambient=(0.25, 0.35),
        size_jitter=0.18,
    ),
}
"""Named scene styles. `apartment` is the training style; `studio` is held out (unseen)."""


# ----------------------------------------------------------------------------------------------
# Scene container
# ----------------------------------------------------------------------------------------------


@dataclass
class Instance:
    """One object in the scene (pieces of room structure are not instances)."""

    instance_id: int
    class_name: str
    label: int                # index into CLASS_NAMES
    aabb_min: np.ndarray      # (3,) world metres
    aabb_max: np.ndarray      # (3,)
    centroid: np.ndarray      # (3,) area-weighted centroid of its surface
    support_id: int = -1      # instance it rests on or hangs from, -1 for floor or wall
    part_aabbs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))  # (P, 2, 3) min/max

    @property
    def blocks_robot(self) -> bool:
        """Whether a driving robot must keep clear of this object's footprint."""
        return self.class_name not in NON_BLOCKING_CLASSES


@dataclass
class Scene:
    """A labelled triangle mesh of one room plus what the renderer needs for textures."""

    seed: int
    style: str
    vertices: np.ndarray        # (V, 3) float32 world metres, +z up
    triangles: np.ndarray       # (F, 3) int32
    face_label: np.ndarray      # (F,) int32 index into CLASS_NAMES
    face_instance: np.ndarray   # (F,) int32 instance id, -1 for room structure
    instances: list[Instance]
    room_min: np.ndarray        # (3,) float64 interior bounds
    room_max: np.ndarray        # (3,)
    face_colour: np.ndarray     # (F, 3) float32 base colour, linear RGB in [0, 1]
    face_colour2: np.ndarray    # (F, 3) float32 second colour of the texture
    face_texture: np.ndarray    # (F,) int8 Texture kind
    face_texture_scale: np.ndarray  # (F,) float32 texture period, metres
    face_normal: np.ndarray     # (F, 3) float32 unit normal (winding order; renderer flips it)
    light: Light
    structures: list[tuple[np.ndarray, np.ndarray]]  # AABBs (min, max) of structural blocks

    @property
    def num_faces(self) -> int:
        return int(self.triangles.shape[0])

    def obstacle_aabbs(self) -> np.ndarray:
        """(N, 2, 3) boxes a robot must keep clear of: blocking instances and structure."""
        boxes = [np.stack([i.aabb_min, i.aabb_max]) for i in self.instances if i.blocks_robot]
        boxes += [np.stack([lo, hi]) for lo, hi in self.structures]
        if not boxes:
            return np.zeros((0, 2, 3))
        return np.stack(boxes).astype(np.float64)

    def face_areas(self) -> np.ndarray:
        """(F,) float64 triangle areas, square metres."""
        v = self.vertices.astype(np.float64)[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def sample_surface(
        self, n_points: int, seed: int = 0, exclude_labels: tuple[int, ...] = ()
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample points uniformly by area on the surfaces.

        Returns xyz (P, 3) float32, label (P,) int32, instance (P,) int32.
        """
        if n_points < 1:
            raise ValueError(f"n_points {n_points} out of range 1..")
        areas = self.face_areas()
        if exclude_labels:
            areas = np.where(np.isin(self.face_label, exclude_labels), 0.0, areas)
        rng = np.random.default_rng(seed)
        face = rng.choice(len(areas), size=n_points, p=areas / areas.sum())
        r1, r2 = rng.random(n_points), rng.random(n_points)
        s = np.sqrt(r1)
        bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # (P, 3)
        tri = self.vertices.astype(np.float64)[self.triangles[face]]  # (P, 3, 3)
        xyz = np.einsum("pk,pkd->pd", bary, tri)
        return xyz.astype(np.float32), self.face_label[face].copy(), self.face_instance[face].copy()


# ----------------------------------------------------------------------------------------------
# Mesh pieces
# ----------------------------------------------------------------------------------------------

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


# ----------------------------------------------------------------------------------------------
# Random helpers
# ----------------------------------------------------------------------------------------------


_T = TypeVar("_T")


def _scaled(c: Colour, factor: float) -> Colour:
    return (c[0] * factor, c[1] * factor, c[2] * factor)


class _Rand:
    def __init__(self, seed: int, style: SceneStyle) -> None:
        self.rng = np.random.default_rng(seed)
        self.style = style

    def u(self, lo: float, hi: float) -> float:
        return float(self.rng.uniform(lo, hi))

    def dim(self, nominal: float) -> float:
        j = self.style.size_jitter
        return nominal * self.u(1.0 - j, 1.0 + j)

    def pick(self, seq: Sequence[_T]) -> _T:
        return seq[int(self.rng.integers(len(seq)))]

    def chance(self, p: float) -> bool:
        return bool(self.rng.random() < p)

    def jitter(self, c: Colour, amount: float = 0.06) -> Colour:
        out = np.clip(np.asarray(c) * self.u(1 - amount, 1 + amount)
                      + self.rng.uniform(-amount, amount, 3) * 0.5, 0.02, 1.0)
        return (float(out[0]), float(out[1]), float(out[2]))

    def mat(self, colour: Colour, texture: Texture, scale: float, colour2: Colour | None = None,
            contrast: float = 0.7) -> Material:
        c = self.jitter(colour)
        c2 = colour2 if colour2 is not None else _scaled(c, contrast)
        return Material(c, c2, texture, scale * self.u(0.8, 1.25))

    def wood(self) -> Material:
        return self.mat(self.pick(self.style.wood_colours), Texture.WOOD, 0.05, contrast=0.75)

    def fabric(self) -> Material:
        tex = self.pick((Texture.FABRIC, Texture.STRIPES, Texture.FABRIC))
        return self.mat(self.pick(self.style.fabric_colours), tex, 0.06, contrast=0.7)

    def accent(self) -> Material:
        return self.mat(self.pick(self.style.accent_colours), Texture.PLAIN, 0.1)

    def appliance(self) -> Material:
        return self.mat(self.pick(self.style.appliance_colours), Texture.PLAIN, 0.08, contrast=0.9)

    def ceramic(self) -> Material:
        return self.mat((0.94, 0.94, 0.93), Texture.MARBLE, 0.3, contrast=0.85)

    def metal(self) -> Material:
        return self.mat((0.62, 0.63, 0.66), Texture.PLAIN, 0.05, contrast=0.8)

    def dark(self) -> Material:
        return self.mat((0.08, 0.08, 0.09), Texture.PLAIN, 0.05, contrast=0.6)

    def patches(self, scale: float = 0.05) -> Material:
        return self.mat(self.pick(self.style.accent_colours), Texture.PATCHES, scale, contrast=0.5)


# ----------------------------------------------------------------------------------------------
# Object builders (local frame: x in [-w/2, w/2] along the wall, y in [0, d] from the wall, z up)
# ----------------------------------------------------------------------------------------------


def _legs(w: float, d: float, z1: float, t: float, m: Material, inset: float = 0.0) -> list[_Part]:
    xs = (-w / 2 + inset, w / 2 - inset - t)
    ys = (inset, d - inset - t)
    return [_box((x, y, 0.0), (x + t, y + t, z1), m) for x in xs for y in ys]


def _cabinet(r: _Rand, w: float, d: float, h: float, m: Material | None = None,
             name: str = "cabinet", z0: float = 0.0) -> _Object:
    m = m or r.wood()
    door = Material(m.colour2, m.colour, m.texture, m.scale_m * 0.8)
    handle = r.metal()
    parts = [_box((-w / 2, 0, z0), (w / 2, d - 0.02, z0 + h), m)]
    n_doors = max(1, round(w / 0.45))
    dw = w / n_doors
    for k in range(n_doors):
        x0 = -w / 2 + k * dw + 0.01
        parts.append(_box((x0, d - 0.02, z0 + 0.04), (x0 + dw - 0.02, d - 0.005, z0 + h - 0.03), door))
        hx = x0 + (dw - 0.02) * (0.85 if k % 2 == 0 else 0.15)
        parts.append(_box((hx - 0.01, d - 0.005, z0 + h * 0.55), (hx + 0.01, d, z0 + h * 0.8), handle))
    return _Object(name, parts)


def _bookshelf(r: _Rand) -> _Object:
    w, d, h = r.dim(0.9), r.dim(0.32), r.dim(1.8)
    m = r.wood()
    t = 0.025
    parts = [_box((-w / 2, 0, 0), (-w / 2 + t, d, h), m), _box((w / 2 - t, 0, 0), (w / 2, d, h), m),
             _box((-w / 2 + t, 0, 0), (w / 2 - t, 0.015, h), m)]
    n_shelves = 5
    for k in range(n_shelves + 1):
        z = k * (h - t) / n_shelves
        parts.append(_box((-w / 2 + t, 0.015, z), (w / 2 - t, d, z + t), m))
        if k < n_shelves:  # a row of books
            bh = (h - t) / n_shelves * r.u(0.55, 0.85)
            parts.append(_box((-w / 2 + t, 0.015, z + t), (w / 2 - t, d * r.u(0.6, 0.9), z + t + bh),
                              r.patches(0.035)))
    return _Object("bookshelf", parts)


def _chair(r: _Rand, m: Material | None = None, seat: Material | None = None) -> _Object:
    w, d = r.dim(0.46), r.dim(0.48)
    sh, bh = r.dim(0.46), r.dim(0.90)
    m = m or r.wood()
    seat = seat or r.fabric()
    t = 0.04
    parts = _legs(w, d, sh - 0.05, t, m)
    parts.append(_box((-w / 2, 0, sh - 0.05), (w / 2, d, sh), seat))
    parts.append(_box((-w / 2, 0, sh), (w / 2, 0.05, bh), m))  # back rest at y in [0, 0.05]
    return _Object("chair", parts)


def _facing_table(chair: _Object, x: float, y_edge: float, side: int, gap: float = 0.05) -> _Object:
    """Place a chair (back at local y=0, facing +y) so its front is `gap` from a table edge.

    side -1: chair on the -y side of the edge facing +y; side +1: on the +y side facing -y.
    """
    d = float(chair.aabb()[1, 1])
    if side < 0:
        return chair.transformed(0, np.array([x, y_edge - gap - d, 0.0]))
    return chair.transformed(2, np.array([x, y_edge + gap + d, 0.0]))


def _table(r: _Rand, w: float, d: float, h: float, m: Material | None = None,
           name: str = "table") -> _Object:
    m = m or r.wood()
    t = 0.05
    parts = _legs(w, d, h - 0.04, t, m, inset=0.04)
    parts.append(_box((-w / 2, 0, h - 0.04), (w / 2, d, h), m))
    return _Object(name, parts)


def _desk(r: _Rand) -> _Object:
    w, d, h = r.dim(1.3), r.dim(0.65), r.dim(0.75)
    m = r.wood()
    parts = [_box((-w / 2, 0, 0), (-w / 2 + 0.04, d, h - 0.04), m),
             _box((-w / 2 + 0.04, 0.0, 0), (-w / 2 + 0.45, d, h - 0.04), Material(m.colour2, m.colour,
                                                                                Texture.WOOD, 0.04)),
             _box((w / 2 - 0.04, 0, 0), (w / 2, d, h - 0.04), m),
             _box((-w / 2, 0, h - 0.04), (w / 2, d, h), m)]
    desk = _Object("desk", parts)
    # monitor on the desk, near the wall
    mw, mh = r.dim(0.55), r.dim(0.34)
    mon = [_box((-0.1, 0.08, h), (0.1, 0.24, h + 0.015), r.dark()),
           _box((-0.025, 0.10, h + 0.015), (0.025, 0.13, h + 0.12), r.dark()),
           _box((-mw / 2, 0.13, h + 0.10), (mw / 2, 0.16, h + 0.10 + mh),
                r.mat((0.05, 0.07, 0.10), Texture.PATCHES, 0.06, contrast=0.3))]
    desk.children.append(_Object("monitor", mon))
    x = w / 2 - 0.13
    if r.chance(0.5) and x - 0.11 > mw / 2 + 0.02:  # a small desk lamp beside the monitor
        desk.children.append(_Object("lamp", [
            _cylinder(x, 0.15, h, h + 0.02, 0.07, r.metal()),
            _cylinder(x, 0.15, h + 0.02, h + 0.32, 0.012, r.metal(), sections=8),
            _cylinder(x, 0.15, h + 0.32, h + 0.46, 0.11, r.accent(), radius_top=0.06)]))
    return desk


def _sofa(r: _Rand) -> _Object:
    w, d = r.dim(2.0), r.dim(0.90)
    m = r.fabric()
    arm = 0.18
    parts = [_box((-w / 2, 0, 0), (w / 2, d, 0.42), m),                     # base + seat
             _box((-w / 2, 0, 0.42), (w / 2, 0.22, 0.85), m),                # back
             _box((-w / 2, 0.22, 0.42), (-w / 2 + arm, d, 0.62), m),         # arms
             _box((w / 2 - arm, 0.22, 0.42), (w / 2, d, 0.62), m)]
    sofa = _Object("sofa", parts)
    for k in range(int(r.rng.integers(1, 3))):
        px = -w / 2 + arm + 0.05 + k * (w - 2 * arm - 0.5)
        sofa.children.append(_Object("pillow", [
            _box((px, 0.24, 0.42), (px + 0.42, 0.40, 0.80), r.accent())]))
    return sofa


def _bed(r: _Rand) -> _Object:
    w, length = r.pick((1.4, 1.6, 0.95)) * r.u(0.97, 1.03), r.dim(2.05)
    frame = r.wood()
    sheet = r.fabric()
    parts = [_box((-w / 2, 0.06, 0), (w / 2, length, 0.32), frame),
             _box((-w / 2, 0, 0), (w / 2, 0.06, 1.0), frame),                  # headboard
             _box((-w / 2 + 0.02, 0.06, 0.32), (w / 2 - 0.02, length - 0.02, 0.52), sheet)]
    bed = _Object("bed", parts)
    n_p = 2 if w > 1.2 else 1
    pw = (w - 0.1) / n_p - 0.05
    for k in range(n_p):
        x0 = -w / 2 + 0.06 + k * (pw + 0.05)
        bed.children.append(_Object("pillow", [_box((x0, 0.1, 0.52), (x0 + pw, 0.5, 0.64), r.accent())]))
    return bed


def _nightstand(r: _Rand, lamp: bool) -> _Object:
    w, d, h = r.dim(0.45), r.dim(0.40), r.dim(0.55)
    ns = _cabinet(r, w, d, h, name="otherfurniture")
    if lamp:
        ns.children.append(_Object("lamp", [
            _cylinder(0, d / 2, h, h + 0.22, 0.06, r.ceramic()),
            _cylinder(0, d / 2, h + 0.22, h + 0.42, 0.17, r.accent(), radius_top=0.11)]))
    return ns


def _floor_lamp(r: _Rand) -> _Object:
    h = r.dim(1.6)
    m = r.metal()
    return _Object("lamp", [_cylinder(0, 0.2, 0, 0.03, 0.16, m),
                            _cylinder(0, 0.2, 0.03, h - 0.3, 0.015, m, sections=8),
                            _cylinder(0, 0.2, h - 0.3, h, 0.2, r.accent(), radius_top=0.12)])


def _plant(r: _Rand) -> _Object:
    h_pot = r.dim(0.35)
    pot_r = r.dim(0.16)
    leaves = r.mat((0.20, 0.45, 0.18), Texture.FABRIC, 0.04, colour2=(0.10, 0.28, 0.08))
    fol_r = r.dim(0.32)
    fol_h = r.dim(0.45)
    cy = max(pot_r, fol_r)
    return _Object("plant", [
        _cylinder(0, cy, 0, h_pot, pot_r * 0.8, r.ceramic(), radius_top=pot_r),
        _ellipsoid((0, cy, h_pot + fol_h), (fol_r, fol_r, fol_h), leaves)])


def _trash_can(r: _Rand) -> _Object:
    rad, h = r.dim(0.16), r.dim(0.42)
    return _Object("trash can", [_cylinder(0, rad, 0, h, rad * 0.85, r.appliance(), radius_top=rad)])


def _refrigerator(r: _Rand) -> _Object:
    w, d, h = r.dim(0.7), r.dim(0.68), r.dim(1.85)
    m = r.appliance()
    handle = r.metal()
    return _Object("refrigerator", [
        _box((-w / 2, 0, 0), (w / 2, d - 0.03, h), m),
        _box((-w / 2 + 0.05, d - 0.03, h * 0.60), (-w / 2 + 0.08, d, h * 0.85), handle),
        _box((-w / 2 + 0.05, d - 0.03, h * 0.25), (-w / 2 + 0.08, d, h * 0.50), handle)])


def _toilet(r: _Rand) -> _Object:
    m = r.ceramic()
    return _Object("toilet", [
        _box((-0.19, 0.0, 0.35), (0.19, 0.20, 0.80), m),                  # tank
        _box((-0.13, 0.20, 0.0), (0.13, 0.50, 0.36), m),                  # pedestal
        _box((-0.19, 0.20, 0.36), (0.19, 0.68, 0.42), m)])                # bowl + seat


def _bathtub(r: _Rand) -> tuple[_Object, _Object]:
    w, d, h = r.dim(1.65), r.dim(0.75), r.dim(0.56)
    m = r.ceramic()
    t = 0.07
    tub = _Object("bathtub", [
        _box((-w / 2, 0, 0), (w / 2, d, 0.12), m),
        _box((-w / 2, 0, 0.12), (w / 2, t, h), m), _box((-w / 2, d - t, 0.12), (w / 2, d, h), m),
        _box((-w / 2, t, 0.12), (-w / 2 + t, d - t, h), m), _box((w / 2 - t, t, 0.12), (w / 2, d - t, h), m)])
    curtain = _Object("shower curtain", [
        _box((-w / 2, d - 0.03, h + 0.08), (-w / 2 + w * r.u(0.45, 0.7), d, 2.0),
             r.mat(r.pick(r.style.fabric_colours), Texture.STRIPES, 0.08, contrast=0.6))])
    return tub, curtain


def _sink_on_top(r: _Rand, x: float, y0: float, z: float, w: float = 0.5, d: float = 0.42) -> _Object:
    m = r.metal() if r.chance(0.5) else r.ceramic()
    t = 0.025
    h = 0.14
    return _Object("sink", [
        _box((x - w / 2, y0, z), (x + w / 2, y0 + d, z + 0.02), m),
        _box((x - w / 2, y0, z + 0.02), (x + w / 2, y0 + t, z + h), m),
        _box((x - w / 2, y0 + d - t, z + 0.02), (x + w / 2, y0 + d, z + h), m),
        _box((x - w / 2, y0 + t, z + 0.02), (x - w / 2 + t, y0 + d - t, z + h), m),
        _box((x + w / 2 - t, y0 + t, z + 0.02), (x + w / 2, y0 + d - t, z + h), m),
        _cylinder(x, y0 + 0.06, z + h, z + h + 0.22, 0.015, r.metal(), sections=8)])


def _vanity(r: _Rand) -> _Object:
    w, d, h = r.dim(0.8), r.dim(0.5), r.dim(0.8)
    v = _cabinet(r, w, d, h)
    v.children.append(_sink_on_top(r, 0.0, 0.02, h, w=min(0.55, w - 0.1), d=min(0.42, d - 0.04)))
    return v


def _kitchen_run(r: _Rand, max_cabinets: int = 4) -> list[_Object]:
    """Base cabinets with a counter top and a sink on it (the fridge is placed separately)."""
    n = int(r.rng.integers(min(2, max_cabinets), max_cabinets + 1))
    cw, d, h = 0.6, r.dim(0.6), 0.86
    m = r.wood()
    cabinets = [_cabinet(r, cw, d, h, m).transformed(0, np.array([(k + 0.5) * cw - n * cw / 2, 0, 0]))
                for k in range(n)]
    top_mat = r.pick((r.mat((0.2, 0.2, 0.22), Texture.MARBLE, 0.3, contrast=1.6),
                      r.mat((0.85, 0.84, 0.80), Texture.MARBLE, 0.4, contrast=0.8), r.wood()))
    counter = _Object("counter", [_box((-n * cw / 2, 0, h), (n * cw / 2, d + 0.03, h + 0.04), top_mat)])
    sink_x = (int(r.rng.integers(n)) + 0.5) * cw - n * cw / 2
    counter.children.append(_sink_on_top(r, sink_x, 0.08, h + 0.04))
    cabinets[0].children.append(counter)
    return cabinets


def _tv_stand(r: _Rand) -> _Object:
    w, d, h = r.dim(1.4), r.dim(0.42), r.dim(0.5)
    stand = _cabinet(r, w, d, h, name="otherfurniture")
    tw = min(w - 0.1, r.dim(1.1))
    th = tw * 0.58
    stand.children.append(_Object("television", [
        _box((-0.15, 0.1, h), (0.15, 0.3, h + 0.02), r.dark()),
        _box((-0.03, 0.15, h + 0.02), (0.03, 0.2, h + 0.1), r.dark()),
        _box((-tw / 2, 0.12, h + 0.08), (tw / 2, 0.17, h + 0.08 + th),
             r.mat((0.04, 0.04, 0.05), Texture.PATCHES, 0.15, contrast=0.4))]))
    return stand


# Wall-mounted things: local frame with z absolute (height above the floor).

def _picture(r: _Rand) -> _Object:
    w, h = r.u(0.35, 1.0), r.u(0.3, 0.8)
    zc = r.u(1.35, 1.7)
    frame = r.mat(r.pick(((0.1, 0.1, 0.1), (0.8, 0.7, 0.4), (0.5, 0.3, 0.15))), Texture.PLAIN, 0.1)
    return _Object("picture", [
        _box((-w / 2, 0, zc - h / 2), (w / 2, 0.02, zc + h / 2), frame),
        _box((-w / 2 + 0.04, 0.02, zc - h / 2 + 0.04), (w / 2 - 0.04, 0.03, zc + h / 2 - 0.04),
             r.patches(r.u(0.05, 0.15)))])


def _window(r: _Rand, ceiling: float) -> _Object:
    w = r.u(0.9, 1.6)
    z0, z1 = r.u(0.85, 1.0), min(ceiling - 0.25, r.u(2.0, 2.3))
    frame = r.mat((0.92, 0.92, 0.90), Texture.PLAIN, 0.05)
    sky = Material((0.75, 0.85, 1.0), (0.95, 0.97, 1.0), Texture.SKY, 1.0)
    f = 0.06
    return _Object("window", [
        _box((-w / 2, 0, z0 + f), (w / 2, 0.01, z1 - f), sky),
        _box((-w / 2, 0, z0), (w / 2, 0.06, z0 + f), frame),
        _box((-w / 2, 0, z1 - f), (w / 2, 0.06, z1), frame),
        _box((-w / 2, 0, z0 + f), (-w / 2 + f, 0.06, z1 - f), frame),
        _box((w / 2 - f, 0, z0 + f), (w / 2, 0.06, z1 - f), frame),
        _box((-0.02, 0.01, z0 + f), (0.02, 0.04, z1 - f), frame)])


def _curtain_panel(r: _Rand, w: float, z1: float, m: Material) -> _Object:
    folds = max(2, int(w / 0.12))
    fw = w / folds
    parts = []
    for k in range(folds):
        depth = 0.06 if k % 2 == 0 else 0.10
        parts.append(_box((-w / 2 + k * fw, 0.0, 0.05), (-w / 2 + (k + 1) * fw, depth, z1), m))
    return _Object("curtain", parts)


def _door(r: _Rand) -> _Object:
    w, h = r.u(0.82, 0.95), r.u(2.0, 2.1)
    m = r.wood()
    return _Object("door", [
        _box((-w / 2 - 0.06, 0, 0), (w / 2 + 0.06, 0.02, h + 0.06),
             r.mat((0.9, 0.9, 0.88), Texture.PLAIN, 0.1)),
        _box((-w / 2, 0.02, 0), (w / 2, 0.05, h), m),
        _cylinder(w / 2 - 0.08, 0.09, 0.95, 1.0, 0.025, r.metal(), sections=8),
        _box((w / 2 - 0.1, 0.05, 0.96), (w / 2 - 0.06, 0.07, 0.99), r.metal())])


def _mirror(r: _Rand) -> _Object:
    w, h = r.u(0.5, 0.8), r.u(0.6, 0.9)
    return _Object("mirror", [_box((-w / 2, 0, 1.25), (w / 2, 0.02, 1.25 + h),
                                   r.mat((0.70, 0.78, 0.82), Texture.MARBLE, 0.5, contrast=0.9))])


def _towel(r: _Rand) -> _Object:
    w = r.u(0.35, 0.55)
    return _Object("towel", [_box((-w / 2 - 0.03, 0, 1.45), (w / 2 + 0.03, 0.05, 1.48), r.metal()),
                             _box((-w / 2, 0.01, 0.95), (w / 2, 0.04, 1.45), r.fabric())])


def _clock(r: _Rand) -> _Object:
    rad = r.u(0.15, 0.22)
    zc = r.u(1.8, 2.05)
    face = r.mat((0.95, 0.95, 0.92), Texture.PATCHES, 0.04, contrast=0.2)
    # a flat cylinder lying on its side: build along z then swap axes (y <-> z)
    cyl = _cylinder(0, zc, 0.0, 0.05, rad, face, sections=20)
    v = cyl.vertices[:, [0, 2, 1]]
    return _Object("clock", [_Part(v, cyl.triangles[:, ::-1].copy(), face)])


def _wall_cabinet(r: _Rand, w: float) -> _Object:
    return _cabinet(r, w, r.dim(0.35), r.dim(0.7), z0=1.45)


# ----------------------------------------------------------------------------------------------
# Placement
# ----------------------------------------------------------------------------------------------

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


def _group(name: str, members: list[_Object]) -> _Object:
    """Several objects placed as one rigid group (the group itself has no parts)."""
    return _Object(name, [], members)


def _flatten(obj: _Object, support: int, out: list[tuple[_Object, int]]) -> None:
    if obj.parts:
        out.append((obj, support))
        me = len(out) - 1
    else:
        me = support
    for c in obj.children:
        _flatten(c, me, out)


# ----------------------------------------------------------------------------------------------
# Zones
# ----------------------------------------------------------------------------------------------


def _living_anchor(p: _Placer) -> None:
    r = p.r
    sofa = _sofa(r)
    sofa_aabb = sofa.aabb()
    ct = _table(r, r.dim(1.0), r.dim(0.55), r.dim(0.42)).transformed(
        0, np.array([0.0, sofa_aabb[1, 1] + 0.45, 0.0]))
    if p.try_place(_group("living", [sofa, ct]), tries=80) is None:
        p.try_place(sofa, tries=40)


def _living_extras(p: _Placer) -> None:
    r = p.r
    p.try_place(_tv_stand(r))
    p.try_place(_bookshelf(r))
    p.try_place(_floor_lamp(r))
    p.try_place(_plant(r))
    if r.chance(0.6):
        rug_w, rug_d = r.dim(1.8), r.dim(1.3)
        rug = _Object("rug", [_box((-rug_w / 2, 0, 0), (rug_w / 2, rug_d, 0.01),
                                   r.mat(r.pick(r.style.fabric_colours), Texture.STRIPES, 0.1))])
        p.try_place(rug, central=True, blocks_floor=False)


def _dining_anchor(p: _Placer) -> None:
    r = p.r
    n_side = int(r.rng.integers(1, 3))
    tw, td, th = max(0.8, 0.55 * n_side + 0.2) * r.u(1.0, 1.2), r.dim(0.85), r.dim(0.75)
    wood = r.wood()
    seat = r.fabric()
    table = _table(r, tw, td, th, wood)
    members = [table.transformed(0, np.array([0.0, 0.0, 0.0]))]
    for k in range(n_side):
        x = -tw / 2 + (k + 0.5) * tw / n_side
        members.append(_facing_table(_chair(r, wood, seat), x, 0.0, -1))
        members.append(_facing_table(_chair(r, wood, seat), x, td, +1))
    if r.chance(0.7):
        members[0].children.append(_Object("vase", [
            _cylinder(0.0, td / 2, th, th + r.u(0.2, 0.32), 0.06, r.accent(), radius_top=0.045)]))
    group = _group("dining", members)
    if r.chance(0.5):  # the whole group stands on a rug
        box = group.aabb()
        lifted = [m.transformed(0, np.array([0.0, 0.0, 0.01])) for m in members]
        rug_mat = r.mat(r.pick(r.style.fabric_colours), Texture.CHECKER, 0.25)
        group = _Object("rug", [_box((box[0, 0] - 0.25, box[0, 1] - 0.25, 0.0),
                                     (box[1, 0] + 0.25, box[1, 1] + 0.25, 0.01), rug_mat)], lifted)
    if p.try_place(group, central=True, walkway_m=0.5, tries=60) is None:
        # fall back to a smaller table with one chair against a wall
        p.try_place(_group("dining", [_table(r, 0.9, 0.7, 0.75), _facing_table(_chair(r), 0.0, 0.7, +1)]))


def _bedroom_anchor(p: _Placer) -> None:
    r = p.r
    bed = _bed(r)
    bw = bed.aabb()[1, 0]
    ns1 = _nightstand(r, lamp=True)
    nw = ns1.aabb()[1, 0]
    members = [bed, ns1.transformed(0, np.array([bw + nw + 0.03, 0.0, 0.0]))]
    if r.chance(0.6):
        ns2 = _nightstand(r, lamp=r.chance(0.5))
        members.append(ns2.transformed(0, np.array([-bw - ns2.aabb()[1, 0] - 0.03, 0.0, 0.0])))
    if p.try_place(_group("bedroom", members), tries=100) is None:
        p.try_place(bed, tries=60)


def _bedroom_extras(p: _Placer) -> None:
    r = p.r
    p.try_place(_cabinet(r, r.dim(1.0), r.dim(0.58), r.dim(2.0)))   # wardrobe
    if r.chance(0.5):
        p.try_place(_plant(r))


def _kitchen_anchor(p: _Placer) -> None:
    r = p.r
    for attempt in range(3):  # shorter runs when the long one does not fit
        run = _kitchen_run(r, max_cabinets=4 - attempt)
        run_w = run[-1].aabb()[1, 0]
        fridge = _refrigerator(r)
        fw = fridge.aabb()[1, 0]
        members = run + [fridge.transformed(0, np.array([run_w + fw + 0.03, 0.0, 0.0]))]
        members.append(_wall_cabinet(r, 2 * run_w - 0.1))
        if p.try_place(_group("kitchen", members), tries=60) is not None:
            return
    p.try_place(_refrigerator(r))


def _kitchen_extras(p: _Placer) -> None:
    p.try_place(_trash_can(p.r))


def _bathroom_anchor(p: _Placer) -> None:
    r = p.r
    tub, curtain = _bathtub(r)
    tub.children.append(curtain)
    p.try_place(tub, tries=80)
    p.try_place(_toilet(r), tries=60)


def _bathroom_extras(p: _Placer) -> None:
    r = p.r
    p.try_place(_group("vanity", [_vanity(r), _mirror(r)]))
    p.try_place(_towel(r), blocks_floor=False)


def _office_anchor(p: _Placer) -> None:
    r = p.r
    desk = _desk(r)
    dd = desk.aabb()[1, 1]
    chair = _facing_table(_chair(r), 0.0, dd, +1)
    p.try_place(_group("office", [desk, chair]), tries=80)


def _office_extras(p: _Placer) -> None:
    r = p.r
    p.try_place(_bookshelf(r))
    p.try_place(_cabinet(r, r.dim(0.5), r.dim(0.55), r.dim(1.1)))
    p.try_place(_trash_can(r))


def _nothing(p: _Placer) -> None:
    return None


_ZONES: dict[str, tuple[Callable[[_Placer], None], Callable[[_Placer], None]]] = {
    "living": (_living_anchor, _living_extras), "dining": (_dining_anchor, _nothing),
    "bedroom": (_bedroom_anchor, _bedroom_extras), "kitchen": (_kitchen_anchor, _kitchen_extras),
    "bathroom": (_bathroom_anchor, _bathroom_extras), "office": (_office_anchor, _office_extras),
}
"""Zone -> (anchor placement, extras). All anchors (big groups) are placed before any extras."""


def _armchair(r: _Rand) -> _Object:
    w, d = r.dim(0.85), r.dim(0.85)
    m = r.fabric()
    return _Object("chair", [_box((-w / 2, 0, 0), (w / 2, d, 0.42), m),
                             _box((-w / 2, 0, 0.42), (w / 2, 0.2, 0.85), m),
                             _box((-w / 2, 0.2, 0.42), (-w / 2 + 0.15, d, 0.62), m),
                             _box((w / 2 - 0.15, 0.2, 0.42), (w / 2, d, 0.62), m)])


def _ottoman(r: _Rand) -> _Object:
    w, d, h = r.dim(0.6), r.dim(0.5), r.dim(0.42)
    return _Object("otherfurniture", [_box((-w / 2, 0, 0.05), (w / 2, d, h), r.fabric())] +
                   _legs(w, d, 0.05, 0.04, r.wood(), inset=0.02))


def _side_table(r: _Rand) -> _Object:
    rad, h = r.dim(0.28), r.dim(0.55)
    m = r.wood()
    t = _Object("table", [_cylinder(0, rad, 0, 0.03, rad * 0.6, m),
                          _cylinder(0, rad, 0.03, h - 0.03, 0.03, m),
                          _cylinder(0, rad, h - 0.03, h, rad, m, sections=20)])
    if r.chance(0.5):
        t.children.append(_Object("vase", [_cylinder(0, rad, h, h + r.u(0.18, 0.3), 0.05, r.accent(),
                                                     radius_top=0.035)]))
    return t


def _clutter(p: _Placer, n: int) -> None:
    """Free-standing objects away from the walls: occluders at middle depths."""
    r = p.r
    makers = (_armchair, _ottoman, _plant, _floor_lamp, _side_table, _trash_can)
    for _ in range(n):
        p.try_place(r.pick(makers)(r), central=True, walkway_m=0.45, tries=30)


# ----------------------------------------------------------------------------------------------
# Scene assembly
# ----------------------------------------------------------------------------------------------


def generate_scene(seed: int, style: str = "apartment") -> Scene:
    """Build one room. Fully determined by `(seed, style)`.

    Args:
        seed: any int >= 0.
        style: a key of `STYLES`.
    """
    if style not in STYLES:
        raise ValueError(f"unknown scene style {style!r}; choose one of {sorted(STYLES)}")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed {seed!r} must be an int >= 0")
    st = STYLES[style]
    r = _Rand(int(seed) * 7919 + sum(map(ord, style)), st)
    size = np.array([r.u(*st.room_x_m), r.u(*st.room_y_m), r.u(*st.ceiling_m)])

    structures: list[np.ndarray] = []
    if r.chance(st.notch_prob):  # L-shaped room: a block fills one corner
        nx, ny = r.u(0.25, 0.4) * size[0], r.u(0.25, 0.4) * size[1]
        cx, cy = r.pick((0, 1)), r.pick((0, 1))
        lo = np.array([0.0 if cx == 0 else size[0] - nx, 0.0 if cy == 0 else size[1] - ny, 0.0])
        structures.append(np.stack([lo, lo + [nx, ny, size[2]]]))
    p = _Placer(r, size, structures)

    # door first (with a keep-out zone in front of it), then windows with curtains
    door = _door(r)
    dw = door.aabb()[1, 0]
    p.try_place(door, reserve=np.array([[-dw - 0.1, 0.0, 0.0], [dw + 0.1, 1.1, 2.2]]), tries=80)
    wall_mat = r.mat(r.pick(st.wall_colours), *r.pick(st.wall_textures), contrast=0.85)
    curtain_mat = r.mat(r.pick(st.fabric_colours), Texture.FABRIC, 0.05)
    for _ in range(int(r.rng.integers(st.n_windows[0], st.n_windows[1] + 1))):
        win = _window(r, size[2])
        ww = win.aabb()[1, 0]
        z1 = win.aabb()[1, 2] + 0.12
        cw = r.u(0.3, 0.45)
        members = [win]
        if r.chance(0.85):
            members.append(_curtain_panel(r, cw, z1, curtain_mat).transformed(
                0, np.array([-ww - cw / 2 - 0.01, 0, 0])))
            members.append(_curtain_panel(r, cw, z1, curtain_mat).transformed(
                0, np.array([ww + cw / 2 + 0.01, 0, 0])))
        p.try_place(_group("window", members), blocks_floor=True)

    # functional zones
    names = list(st.zone_weights)
    weights = np.array([st.zone_weights[n] for n in names])
    n_z = int(r.rng.integers(st.n_zones[0], st.n_zones[1] + 1))
    chosen = r.rng.choice(len(names), size=min(n_z, len(names)), replace=False, p=weights / weights.sum())
    for zi in chosen:
        _ZONES[names[int(zi)]][0](p)
    for zi in chosen:
        _ZONES[names[int(zi)]][1](p)
    _clutter(p, int(r.rng.integers(st.n_clutter[0], st.n_clutter[1] + 1)))

    # decoration on the walls
    for _ in range(int(r.rng.integers(1, 4))):
        p.try_place(_picture(r), blocks_floor=False)
    if r.chance(0.5):
        p.try_place(_clock(r), blocks_floor=False)

    # --- assemble the mesh ---
    floor_c, floor_c2 = r.pick(st.floor_colours)
    floor_tex, floor_scale = r.pick(st.floor_textures)
    floor_mat = Material(r.jitter(floor_c), floor_c2, floor_tex, floor_scale)
    ceil_mat = Material(st.ceiling_colour, _scaled(st.ceiling_colour, 0.9), Texture.PLAIN, 0.5)
    t = 0.1
    sx, sy, sz = size
    structure_parts: list[tuple[_Part, str]] = [
        (_box((0, 0, -t), (sx, sy, 0), floor_mat), "floor"),
        (_box((0, 0, sz), (sx, sy, sz + t), ceil_mat), "ceiling"),
        (_box((-t, -t, 0), (sx + t, 0, sz), wall_mat), "wall"),
        (_box((-t, sy, 0), (sx + t, sy + t, sz), wall_mat), "wall"),
        (_box((-t, 0, 0), (0, sy, sz), wall_mat), "wall"),
        (_box((sx, 0, 0), (sx + t, sy, sz), wall_mat), "wall"),
    ]
    for b in structures:
        structure_parts.append((_box(b[0], b[1], wall_mat), "wall"))

    flat: list[tuple[_Object, int]] = []
    for obj in p.placed:
        _flatten(obj, -1, flat)

    verts, tris, labels, inst_ids, cols, cols2, texs, scales = [], [], [], [], [], [], [], []
    n_v = 0

    def add(part: _Part, label: int, inst: int) -> None:
        nonlocal n_v
        verts.append(part.vertices)
        tris.append(part.triangles + n_v)
        n_v += part.vertices.shape[0]
        m = part.triangles.shape[0]
        labels.append(np.full(m, label, np.int32))
        inst_ids.append(np.full(m, inst, np.int32))
        cols.append(np.tile(np.asarray(part.material.colour, np.float32), (m, 1)))
        cols2.append(np.tile(np.asarray(part.material.colour2, np.float32), (m, 1)))
        texs.append(np.full(m, int(part.material.texture), np.int8))
        scales.append(np.full(m, part.material.scale_m, np.float32))

    for part, name in structure_parts:
        add(part, LABEL_OF[name], -1)
    instances: list[Instance] = []
    for idx, (obj, support) in enumerate(flat):
        for part in obj.parts:
            add(part, LABEL_OF[obj.class_name], idx)
        v = np.concatenate([q.vertices for q in obj.parts])
        part_boxes = np.stack([q.aabb for q in obj.parts])
        instances.append(Instance(idx, obj.class_name, LABEL_OF[obj.class_name], v.min(0), v.max(0),
                                  _area_centroid(obj.parts), support, part_boxes))

    vertices = np.concatenate(verts).astype(np.float32)
    triangles = np.concatenate(tris).astype(np.int32)
    tri_v = vertices.astype(np.float64)[triangles]
    n = np.cross(tri_v[:, 1] - tri_v[:, 0], tri_v[:, 2] - tri_v[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    light = Light(
        position=np.array([r.u(0.3, 0.7) * sx, r.u(0.3, 0.7) * sy, sz - 0.3]),
        colour=np.asarray(st.light_colour, dtype=np.float64),
        diffuse=r.u(*st.light_diffuse), ambient=r.u(*st.ambient), falloff_m=r.u(3.0, 4.5))

    return Scene(
        seed=int(seed), style=style, vertices=vertices, triangles=triangles,
        face_label=np.concatenate(labels), face_instance=np.concatenate(inst_ids),
        instances=instances, room_min=np.zeros(3), room_max=size.astype(np.float64),
        face_colour=np.concatenate(cols), face_colour2=np.concatenate(cols2),
        face_texture=np.concatenate(texs), face_texture_scale=np.concatenate(scales),
        face_normal=n.astype(np.float32), light=light,
        structures=[(b[0].copy(), b[1].copy()) for b in structures])


def _area_centroid(parts: list[_Part]) -> np.ndarray:
    total, acc = 0.0, np.zeros(3)
    for q in parts:
        tv = q.vertices[q.triangles]
        a = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
        total += a.sum()
        acc += (a[:, None] * tv.mean(1)).sum(0)
    return acc / max(total, 1e-12)
