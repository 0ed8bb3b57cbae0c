"""Floors of many rooms: `generate_floor(seed, n_rooms, style)` lays out 2-30 rooms along
corridors, each room built by `generate_room` (the single-room generator's furniture, zones and
materials, with an open doorway onto its corridor), and merges them into one `Scene`.

The plan is a comb: bands of rooms run along x, each band a corridor (1.6-2.0 m wide) with
rooms on both sides (at most 8 rooms a band, about half on each side), and a spine corridor
along y at the west end joins the bands' corridors. Every room has one doorway (1.0-1.2 m wide,
2.1 m high) in its wall on the corridor, so every room is reachable from every other one through
doors and corridors. Rooms of a band side share their depth (y); widths vary; walls are 0.1 m
thick, two rooms side by side have their own walls back to back. One ceiling height for the
whole floor. Each room keeps its own light; the corridors have a light every few metres; the
scene's `LightMap` says which light shades which part of the floor.

Rooms are numbered in the order a tour visits them (`clients.sim.tour`): along the first band's
corridor on its south side, back along its north side, then the next band.

>>> floor = generate_floor(0, 4)
>>> len(floor.rooms), len(floor.corridors), floor.scene.light_map is not None
(4, 1, True)
>>> generate_floor(0, 40)
Traceback (most recent call last):
...
ValueError: n_rooms 40 out of range 2..30
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clients.sim.scenes.appearance import Light, Material, Texture
from clients.sim.scenes.generate import _face_normals, _Mesh, generate_room, room_wall_boxes
from clients.sim.scenes.primitives import _box
from clients.sim.scenes.rand import _Rand, _scaled
from clients.sim.scenes.scene import Doorway, Instance, LightMap, Scene
from clients.sim.scenes.styles import STYLES
from clients.sim.scenes.vocabulary import LABEL_OF

FLOOR_ROOMS = (2, 30)
"""Smallest and largest number of rooms of a floor."""
ROOMS_PER_BAND = 8
WALL_T_M = 0.1
_CORRIDOR_LIGHT_SPACING_M = 4.0
_LIGHT_CELL_M = 0.1


@dataclass
class FloorRoom:
    """One room of a floor, where it is and where its doorway is."""

    index: int
    band: int
    side: int                 # 0: south of its corridor (doorway in its y-max wall), 1: north
    offset: np.ndarray        # (3,) world position of the room frame's origin (interior min corner)
    local: Scene              # the room alone, in its own frame (interior [0, size])
    doorway: Doorway

    @property
    def size(self) -> np.ndarray:
        return self.local.room_max.copy()

    @property
    def lo(self) -> np.ndarray:
        """(2,) world xy of the interior's min corner."""
        return self.offset[:2].copy()

    @property
    def hi(self) -> np.ndarray:
        """(2,) world xy of the interior's max corner."""
        return self.offset[:2] + self.local.room_max[:2]

    @property
    def door_xy(self) -> np.ndarray:
        """(2,) world xy of the doorway's centre, in the middle of the wall's thickness."""
        y = -WALL_T_M / 2 if self.doorway.wall == 0 else float(self.local.room_max[1]) + WALL_T_M / 2
        return self.offset[:2] + np.array([self.doorway.centre_x, y])

    @property
    def door_normal(self) -> np.ndarray:
        """(2,) unit vector from the room out through its doorway (into the corridor)."""
        return np.array([0.0, -1.0 if self.doorway.wall == 0 else 1.0])


@dataclass
class Floor:
    """A floor of rooms joined by corridors, merged into one scene (world frame as in `Scene`)."""

    seed: int
    style: str
    scene: Scene
    rooms: list[FloorRoom]
    corridors: list[np.ndarray]   # per band: (2, 2) xy min / max of the corridor's interior
    spine: np.ndarray             # (2, 2) xy min / max of the spine corridor's interior
    band_y: list[tuple[float, float]]  # per band: y of its south and north outer wall faces
    face_zone: np.ndarray         # (F,) int16 band of each face of `scene`, -1 for the spine's

    def zone_at(self, xy: np.ndarray) -> int:
        """The band whose rooms and corridor hold world point xy (2,); -1 in the spine (or off the
        floor). From a band only its own faces and the spine's can be seen (its corridor opens onto
        the spine alone, and a straight ray that has crossed into the spine never comes back east)."""
        if xy[0] <= self.spine[1, 0]:
            return -1
        for b, (y0, y1) in enumerate(self.band_y):
            if y0 <= xy[1] <= y1:
                return b
        return -1

    def room_at(self, xy: np.ndarray) -> np.ndarray:
        """(N,) int32: the room whose interior holds each world point xy (N, 2+), -1 for none."""
        pts = np.asarray(xy, dtype=np.float64)[:, :2]
        out = np.full(len(pts), -1, np.int32)
        for room in self.rooms:
            inside = ((pts >= room.lo) & (pts <= room.hi)).all(1)
            out[inside] = room.index
        return out

    def corridor_y(self, band: int) -> float:
        """The y of band `band`'s corridor centre line."""
        return float(self.corridors[band][:, 1].mean())

    def spine_x(self) -> float:
        """The x of the spine's centre line."""
        return float(self.spine[:, 0].mean())


@dataclass
class _Spec:
    band: int
    side: int
    x0: float
    y0: float
    width: float
    depth: float
    door_x: float             # room frame
    door_w: float


def generate_floor(seed: int, n_rooms: int, style: str = "apartment") -> Floor:
    """A floor of `n_rooms` rooms (2..30) of `style` joined by corridors; fully determined by
    `(seed, n_rooms, style)`. Room k is `generate_room` with seed `seed * 1000 + k`."""
    if style not in STYLES or STYLES[style].layout != "room":
        rooms_only = sorted(k for k, v in STYLES.items() if v.layout == "room")
        raise ValueError(f"style {style!r} cannot make a floor's rooms; choose one of {rooms_only}")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed {seed!r} must be an int >= 0")
    if not FLOOR_ROOMS[0] <= int(n_rooms) <= FLOOR_ROOMS[1]:
        raise ValueError(f"n_rooms {n_rooms} out of range {FLOOR_ROOMS[0]}..{FLOOR_ROOMS[1]}")
    st = STYLES[style]
    r = _Rand(int(seed) * 104_723 + 31 * int(n_rooms) + sum(map(ord, style)), st)
    height = r.u(*st.ceiling_m)
    specs, corridors, spine, band_y = _plan(r, int(n_rooms))
    rooms = []
    for k, sp in enumerate(specs):
        doorway = Doorway(wall=2 if sp.side == 0 else 0, centre_x=sp.door_x, width_m=sp.door_w)
        local = generate_room(int(seed) * 1000 + k, style, (sp.width, sp.depth, height), doorway)
        rooms.append(FloorRoom(k, sp.band, sp.side, np.array([sp.x0, sp.y0, 0.0]), local, doorway))
    scene = _merge(int(seed), style, r, rooms, corridors, spine, height)
    return Floor(int(seed), style, scene, rooms, corridors, spine, band_y,
                 _face_zones(scene, rooms, spine, band_y))


def _face_zones(scene: Scene, rooms: list[FloorRoom], spine: np.ndarray,
                band_y: list[tuple[float, float]]) -> np.ndarray:
    """(F,) band of each face: a room's faces its band's; the corridors' structure by where the
    face's centre is (the spine's, x within it, -1)."""
    zone = np.empty(scene.num_faces, np.int16)
    start = 0
    for room in rooms:
        n = room.local.num_faces
        zone[start:start + n] = room.band
        start += n
    centre = scene.vertices[scene.triangles[start:]].astype(np.float64).mean(1)
    rest = np.full(len(centre), -1, np.int16)
    for b, (y0, y1) in enumerate(band_y):
        in_band = (centre[:, 1] >= y0 - 1e-6) & (centre[:, 1] <= y1 + 1e-6)
        rest[in_band & (centre[:, 0] > spine[1, 0] + 1e-6)] = b
    zone[start:] = rest
    return zone


def _plan(r: _Rand, n_rooms: int
          ) -> tuple[list[_Spec], list[np.ndarray], np.ndarray, list[tuple[float, float]]]:
    """Room rectangles (in tour order), the bands' corridors, the spine and the bands' y extents."""
    st, t = r.style, WALL_T_M
    n_bands = math.ceil(n_rooms / ROOMS_PER_BAND)
    counts = [n_rooms // n_bands + (1 if b < n_rooms % n_bands else 0) for b in range(n_bands)]
    spine_w = r.u(1.6, 2.0)
    x_start = spine_w + t                         # the westmost rooms' interiors (their wall on the spine)
    specs: list[_Spec] = []
    corridors: list[np.ndarray] = []
    band_y: list[tuple[float, float]] = []
    y_base = 0.0                                  # the band's south outer face
    for b, count in enumerate(counts):
        n_side = [math.ceil(count / 2), count // 2]
        depth = [r.u(*st.room_y_m), r.u(*st.room_y_m)]
        cw = r.u(1.6, 2.0)
        y_south = y_base + t
        yc0 = y_south + depth[0] + t
        yc1 = yc0 + cw
        y_north = yc1 + t
        corridors.append(np.array([[spine_w, yc0], [0.0, yc1]]))  # x max set below
        band_rooms: list[list[_Spec]] = [[], []]
        for side in (0, 1):
            x = x_start
            for _ in range(n_side[side]):
                w = r.u(*st.room_x_m)
                dw = r.u(1.0, 1.2)
                door_x = r.u(dw / 2 + 0.4, w - dw / 2 - 0.4)
                band_rooms[side].append(_Spec(b, side, x, y_south if side == 0 else y_north, w, depth[side],
                                              door_x, dw))
                x += w + 2 * t
        corridors[-1][1, 0] = max(s.x0 + s.width + t for s in band_rooms[0] + band_rooms[1])
        specs += band_rooms[0] + band_rooms[1][::-1]   # east along the south side, back along the north
        y_next = y_north + (depth[1] + t if n_side[1] else 0.0)
        band_y.append((y_base, y_next))
        y_base = y_next
    spine = np.array([[0.0, corridors[0][0, 1]], [spine_w, corridors[-1][1, 1]]])
    return specs, corridors, spine, band_y


def _merge(seed: int, style: str, r: _Rand, rooms: list[FloorRoom], corridors: list[np.ndarray],
           spine: np.ndarray, height: float) -> Scene:
    """One scene of the rooms (moved into place), the corridors' structure and the lights."""
    corridor_scene, corridor_walls, corridor_lights = _corridor_structure(r, rooms, corridors, spine, height)
    parts: list[Scene] = []
    instances: list[Instance] = []
    structures: list[tuple[np.ndarray, np.ndarray]] = []
    for room in rooms:
        moved = _moved(room.local, room.offset, len(instances))
        parts.append(moved)
        instances += moved.instances
        for box in room_wall_boxes(room.size, room.doorway):
            structures.append((box[0] + room.offset, box[1] + room.offset))
    parts.append(corridor_scene)
    structures += corridor_walls
    lo = np.array([float(spine[0, 0]), min(float(room.lo[1]) for room in rooms), 0.0])
    hi = np.array([max(float(c[1, 0]) for c in corridors), max(float(room.hi[1]) for room in rooms), height])
    lights = [room.local.light for room in rooms]
    lights = [Light(lt.position + room.offset, lt.colour, lt.diffuse, lt.ambient, lt.falloff_m)
              for lt, room in zip(lights, rooms, strict=True)] + corridor_lights
    light_map = _light_map(rooms, lights, len(rooms), lo, hi)
    return Scene(
        seed=seed, style=style,
        vertices=np.concatenate([p.vertices for p in parts]).astype(np.float32),
        triangles=np.concatenate(_offset_triangles(parts)).astype(np.int32),
        face_label=np.concatenate([p.face_label for p in parts]),
        face_instance=np.concatenate([p.face_instance for p in parts]),
        instances=instances, room_min=lo, room_max=hi,
        face_colour=np.concatenate([p.face_colour for p in parts]),
        face_colour2=np.concatenate([p.face_colour2 for p in parts]),
        face_texture=np.concatenate([p.face_texture for p in parts]),
        face_texture_scale=np.concatenate([p.face_texture_scale for p in parts]),
        face_normal=np.concatenate([p.face_normal for p in parts]), light=lights[0],
        structures=structures, light_map=light_map)


def _offset_triangles(parts: list[Scene]) -> list[np.ndarray]:
    out, n_v = [], 0
    for p in parts:
        out.append(p.triangles + n_v)
        n_v += len(p.vertices)
    return out


def _moved(scene: Scene, offset: np.ndarray, first_id: int) -> Scene:
    """`scene` moved by `offset` (3,), its instance ids from `first_id` on (supports likewise)."""
    ids = np.where(scene.face_instance >= 0, scene.face_instance + first_id, -1).astype(np.int32)
    instances = [Instance(i.instance_id + first_id, i.class_name, i.label, i.aabb_min + offset,
                          i.aabb_max + offset, i.centroid + offset,
                          i.support_id + first_id if i.support_id >= 0 else -1, i.part_aabbs + offset)
                 for i in scene.instances]
    moved = Scene(scene.seed, scene.style, (scene.vertices + offset).astype(np.float32), scene.triangles,
                  scene.face_label, ids, instances, scene.room_min + offset, scene.room_max + offset,
                  scene.face_colour, scene.face_colour2, scene.face_texture, scene.face_texture_scale,
                  scene.face_normal, scene.light, [])
    return moved


def _corridor_structure(
    r: _Rand, rooms: list[FloorRoom], corridors: list[np.ndarray], spine: np.ndarray, height: float,
) -> tuple[Scene, list[tuple[np.ndarray, np.ndarray]], list[Light]]:
    """The corridors' floors, ceilings and walls (their sides are the rooms' walls: only the ends,
    the spine's outer walls and any stretch of a band without rooms), the floor under each
    doorway, and the corridors' lights."""
    st, t = r.style, WALL_T_M
    wall_mat = r.mat(r.pick(st.wall_colours), *r.pick(st.wall_textures), contrast=0.85)
    floor_c, floor_c2 = r.pick(st.floor_colours)
    floor_tex, floor_scale = r.pick(st.floor_textures)
    floor_mat = Material(r.jitter(floor_c), floor_c2, floor_tex, floor_scale)
    ceil_mat = Material(st.ceiling_colour, _scaled(st.ceiling_colour, 0.9), Texture.PLAIN, 0.5)
    floors, walls = [], []
    rects = [*corridors, spine]
    for c in rects:
        floors.append((np.array([c[0, 0], c[0, 1], -t]), np.array([c[1, 0], c[1, 1], 0.0]), "floor"))
        floors.append((np.array([c[0, 0], c[0, 1], height]), np.array([c[1, 0], c[1, 1], height + t]),
                       "ceiling"))
    for b, c in enumerate(corridors):
        walls.append(np.array([[c[1, 0], c[0, 1] - t, 0.0], [c[1, 0] + t, c[1, 1] + t, height]]))  # east end
        for side, y0, y1 in ((0, c[0, 1] - t, c[0, 1]), (1, c[1, 1], c[1, 1] + t)):
            ends = [float(room.hi[0]) + t for room in rooms if room.band == b and room.side == side]
            x_end = max(ends) if ends else float(c[0, 0])
            if x_end < c[1, 0] - 1e-9:  # a stretch of the corridor without rooms on this side
                walls.append(np.array([[x_end, y0, 0.0], [c[1, 0], y1, height]]))
    walls.append(np.array([[spine[0, 0] - t, spine[0, 1] - t, 0.0], [spine[0, 0], spine[1, 1] + t, height]]))
    walls.append(np.array([[spine[0, 0], spine[0, 1] - t, 0.0], [spine[1, 0], spine[0, 1], height]]))
    walls.append(np.array([[spine[0, 0], spine[1, 1], 0.0], [spine[1, 0], spine[1, 1] + t, height]]))
    for room in rooms:  # the floor under each doorway (the wall's thickness)
        d = room.door_xy
        w = room.doorway.width_m
        floors.append((np.array([d[0] - w / 2, d[1] - t / 2, -t]),
                       np.array([d[0] + w / 2, d[1] + t / 2, 0.0]), "floor"))
    mesh = _Mesh()
    for lo, hi, name in floors:
        mesh.add(_box(lo, hi, floor_mat if name == "floor" else ceil_mat), LABEL_OF[name], -1)
    for box in walls:
        mesh.add(_box(box[0], box[1], wall_mat), LABEL_OF["wall"], -1)
    vertices = np.concatenate(mesh.verts).astype(np.float32)
    triangles = np.concatenate(mesh.tris).astype(np.int32)
    lights = []
    for c in rects:
        length = float((c[1] - c[0]).max())
        n = max(1, round(length / _CORRIDOR_LIGHT_SPACING_M))
        along = int(np.argmax(c[1] - c[0]))
        for k in range(n):
            pos = np.array([*(0.5 * (c[0] + c[1])), height - 0.3])
            pos[along] = c[0, along] + (k + 0.5) * length / n
            lights.append(Light(pos, np.asarray(st.light_colour, np.float64), r.u(*st.light_diffuse),
                                r.u(*st.ambient), r.u(3.0, 4.5)))
    scene = Scene(0, r.style.name, vertices, triangles, np.concatenate(mesh.labels),
                  np.concatenate(mesh.inst_ids), [], np.zeros(3), np.zeros(3), np.concatenate(mesh.cols),
                  np.concatenate(mesh.cols2), np.concatenate(mesh.texs), np.concatenate(mesh.scales),
                  _face_normals(vertices, triangles), lights[0], [])
    return scene, [(b[0].copy(), b[1].copy()) for b in walls], lights


def _light_map(rooms: list[FloorRoom], lights: list[Light], first_corridor_light: int, lo: np.ndarray,
               hi: np.ndarray) -> LightMap:
    """Each room's interior lit by its own light, the rest by the nearest corridor light."""
    origin = lo[:2] - 0.5
    nx = int(math.ceil((hi[0] - lo[0] + 1.0) / _LIGHT_CELL_M))
    ny = int(math.ceil((hi[1] - lo[1] + 1.0) / _LIGHT_CELL_M))
    xs = origin[0] + (np.arange(nx) + 0.5) * _LIGHT_CELL_M
    ys = origin[1] + (np.arange(ny) + 0.5) * _LIGHT_CELL_M
    cor = np.stack([lt.position[:2] for lt in lights[first_corridor_light:]])
    ids = np.empty((nx, ny), np.int16)
    for i0 in range(0, nx, 64):  # nearest corridor light, a strip of columns at a time
        gx = xs[i0:i0 + 64, None, None]
        d2 = (gx - cor[None, None, :, 0]) ** 2 + (ys[None, :, None] - cor[None, None, :, 1]) ** 2
        ids[i0:i0 + 64] = first_corridor_light + np.argmin(d2, axis=2)
    for room in rooms:
        i = (xs >= room.lo[0]) & (xs <= room.hi[0])
        j = (ys >= room.lo[1]) & (ys <= room.hi[1])
        ids[np.ix_(i, j)] = room.index
    return LightMap(lights, origin, _LIGHT_CELL_M, ids)
