"""Scene assembly: `generate_scene(seed, style)` builds the room, places its objects and returns
the labelled, textured mesh as a `Scene`.

>>> scene = generate_scene(3, "apartment")
>>> scene.seed, scene.style, len(scene.instances) > 0
(3, 'apartment', True)
>>> bool((generate_scene(3, "apartment").vertices == scene.vertices).all())
True
>>> generate_scene(3, "loft")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
ValueError: unknown scene style 'loft'; choose one of ['apartment', 'corridor', ...]
"""

from __future__ import annotations

import numpy as np

from clients.sim.scenes.appearance import Light, Material, Texture
from clients.sim.scenes.furniture import _clock, _curtain_panel, _door, _picture, _window
from clients.sim.scenes.placement import _Placer, placed_reserve
from clients.sim.scenes.primitives import _box, _group, _Object, _Part
from clients.sim.scenes.rand import _Rand, _scaled
from clients.sim.scenes.scene import Doorway, Instance, Scene
from clients.sim.scenes.styles import STYLES, SceneStyle
from clients.sim.scenes.vocabulary import LABEL_OF
from clients.sim.scenes.zones import _ZONES, _clutter

_WALL_T_M = 0.1
_CASING_M = 0.07  # width of a doorway's frame on the room side


def generate_scene(seed: int, style: str = "apartment") -> Scene:
    """Build one room. Fully determined by `(seed, style)`.

    The steps draw from one random stream in a fixed order: the room's shape, the door and windows,
    the functional zones and clutter, the wall decoration, then the materials and light of the mesh.

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
    size, structures = _room_shape(r, st)
    p = _Placer(r, size, structures)
    wall_mat = _place_openings(p, r, st, size)
    _place_zones(p, r, st)
    _place_decoration(p, r)
    return _assemble(int(seed), style, r, st, size, structures, p, wall_mat, None)


def generate_room(seed: int, style: str, size: tuple[float, float, float] | np.ndarray,
                  doorway: Doorway) -> Scene:
    """Build one room of a floor: of the given interior `size` (x, y, ceiling height), rectangular,
    with an open doorway in one of its walls (a door frame, and a keep-out area in front of it that
    no furniture takes, so the robot can always drive in) instead of a closed door. Fully
    determined by `(seed, style, size, doorway)`; the draws after the room's shape follow
    `generate_scene`'s order (windows, zones and clutter, decoration, materials and light).

    >>> room = generate_room(2, "apartment", (5.0, 4.5, 2.6), Doorway(wall=2, centre_x=2.0))
    >>> [round(float(v), 2) for v in room.room_max], any(i.class_name == "door" for i in room.instances)
    ([5.0, 4.5, 2.6], True)
    """
    if style not in STYLES:
        raise ValueError(f"unknown scene style {style!r}; choose one of {sorted(STYLES)}")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed {seed!r} must be an int >= 0")
    st = STYLES[style]
    size_a = np.asarray(size, dtype=np.float64)
    doorway.check(size_a)
    r = _Rand(int(seed) * 7919 + sum(map(ord, style)) + 104_729, st)
    p = _Placer(r, size_a, [])
    _place_doorway(p, r, size_a, doorway)
    wall_mat = _place_windows(p, r, st, size_a)
    _place_zones(p, r, st)
    _place_decoration(p, r)
    return _assemble(int(seed), style, r, st, size_a, [], p, wall_mat, doorway)


def _assemble(seed: int, style: str, r: _Rand, st: SceneStyle, size: np.ndarray,
              structures: list[np.ndarray], p: _Placer, wall_mat: Material,
              doorway: Doorway | None) -> Scene:
    """The room's mesh (structure, then the placed objects), its light, as a `Scene`."""
    structure_parts = _structure_parts(r, st, size, structures, wall_mat, doorway)
    mesh = _Mesh()
    for part, name in structure_parts:
        mesh.add(part, LABEL_OF[name], -1)
    instances = _add_objects(mesh, p.placed)
    vertices = np.concatenate(mesh.verts).astype(np.float32)
    triangles = np.concatenate(mesh.tris).astype(np.int32)
    light = _light(r, st, size)
    return Scene(
        seed=seed, style=style, vertices=vertices, triangles=triangles,
        face_label=np.concatenate(mesh.labels), face_instance=np.concatenate(mesh.inst_ids),
        instances=instances, room_min=np.zeros(3), room_max=size.astype(np.float64),
        face_colour=np.concatenate(mesh.cols), face_colour2=np.concatenate(mesh.cols2),
        face_texture=np.concatenate(mesh.texs), face_texture_scale=np.concatenate(mesh.scales),
        face_normal=_face_normals(vertices, triangles), light=light,
        structures=[(b[0].copy(), b[1].copy()) for b in structures])


def _room_shape(r: _Rand, st: SceneStyle) -> tuple[np.ndarray, list[np.ndarray]]:
    """The room's size (x, y, ceiling height) and its inner full-height blocks: the corner block of
    an L-shaped room, the walls of a corridor layout."""
    size = np.array([r.u(*st.room_x_m), r.u(*st.room_y_m), r.u(*st.ceiling_m)])
    structures: list[np.ndarray] = []
    if r.chance(st.notch_prob):  # L-shaped room: a block fills one corner
        nx, ny = r.u(0.25, 0.4) * size[0], r.u(0.25, 0.4) * size[1]
        cx, cy = r.pick((0, 1)), r.pick((0, 1))
        lo = np.array([0.0 if cx == 0 else size[0] - nx, 0.0 if cy == 0 else size[1] - ny, 0.0])
        structures.append(np.stack([lo, lo + [nx, ny, size[2]]]))
    if st.layout == "corridor":
        structures += _corridor_walls(r, size)
    return size, structures


def _place_openings(p: _Placer, r: _Rand, st: SceneStyle, size: np.ndarray) -> Material:
    """Place the door (with a keep-out zone in front of it), then the windows with curtains; returns
    the walls' material (drawn between the two)."""
    door = _door(r)
    dw = door.aabb()[1, 0]
    p.try_place(door, reserve=np.array([[-dw - 0.1, 0.0, 0.0], [dw + 0.1, 1.1, 2.2]]), tries=80)
    return _place_windows(p, r, st, size)


def _place_windows(p: _Placer, r: _Rand, st: SceneStyle, size: np.ndarray) -> Material:
    """Draw the walls' material, then place the windows with curtains; returns the material."""
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
    return wall_mat


DOORWAY_KEEP_OUT_M = 1.5
"""Depth of the area in front of a floor room's doorway that no furniture takes."""


def _place_doorway(p: _Placer, r: _Rand, size: np.ndarray, d: Doorway) -> None:
    """A door frame around the doorway (three "door" instances: the two jambs and the head, so
    that no obstacle box spans the opening) and the keep-out area in front of it."""
    w, h = d.width_m, d.height_m
    along = d.centre_x if d.wall == 0 else float(size[0]) - d.centre_x
    pose = p.wall_pose(d.wall, along, w / 2 + _CASING_M)
    if pose is None:  # Doorway.check keeps the opening on the wall
        raise ValueError(f"doorway {d} does not fit on wall {d.wall} of a room of size {size.tolist()}")
    mat = r.mat((0.9, 0.9, 0.88), Texture.PLAIN, 0.1)
    c, t = _CASING_M, _WALL_T_M
    left = _Object("door", [_box((-w / 2 - c, 0, 0), (-w / 2, 0.02, h + c), mat),
                            _box((-w / 2, -t, 0), (-w / 2 + 0.02, 0, h), mat)])
    right = _Object("door", [_box((w / 2, 0, 0), (w / 2 + c, 0.02, h + c), mat),
                             _box((w / 2 - 0.02, -t, 0), (w / 2, 0, h), mat)])
    head = _Object("door", [_box((-w / 2, 0, h), (w / 2, 0.02, h + c), mat),
                            _box((-w / 2, -t, h - 0.02), (w / 2, 0, h), mat)])
    keep_out = np.array([[-w / 2 - 0.2, 0.0, 0.0], [w / 2 + 0.2, DOORWAY_KEEP_OUT_M, float(size[2])]])
    p.commit(_group("door", [left, right, head]).transformed(*pose), blocks_floor=False,
             reserve=placed_reserve(keep_out, pose))


def _place_zones(p: _Placer, r: _Rand, st: SceneStyle) -> None:
    """Pick the functional zones by the style's weights, place each zone's anchors, then each zone's
    companions, then the clutter."""
    names = list(st.zone_weights)
    weights = np.array([st.zone_weights[n] for n in names])
    n_z = int(r.rng.integers(st.n_zones[0], st.n_zones[1] + 1))
    chosen = r.rng.choice(len(names), size=min(n_z, len(names)), replace=False, p=weights / weights.sum())
    for zi in chosen:
        _ZONES[names[int(zi)]][0](p)
    for zi in chosen:
        _ZONES[names[int(zi)]][1](p)
    _clutter(p, int(r.rng.integers(st.n_clutter[0], st.n_clutter[1] + 1)))


def _place_decoration(p: _Placer, r: _Rand) -> None:
    """Pictures (1-3) and maybe a clock on the walls."""
    for _ in range(int(r.rng.integers(1, 4))):
        p.try_place(_picture(r), blocks_floor=False)
    if r.chance(0.5):
        p.try_place(_clock(r), blocks_floor=False)


def _structure_parts(r: _Rand, st: SceneStyle, size: np.ndarray, structures: list[np.ndarray],
                     wall_mat: Material, doorway: Doorway | None = None) -> list[tuple[_Part, str]]:
    """Floor, ceiling, the four outer walls (0.1 m thick, outside the room; the one with the
    doorway in three pieces around it) and the inner blocks."""
    floor_c, floor_c2 = r.pick(st.floor_colours)
    floor_tex, floor_scale = r.pick(st.floor_textures)
    floor_mat = Material(r.jitter(floor_c), floor_c2, floor_tex, floor_scale)
    ceil_mat = Material(st.ceiling_colour, _scaled(st.ceiling_colour, 0.9), Texture.PLAIN, 0.5)
    t = _WALL_T_M
    sx, sy, sz = size
    structure_parts: list[tuple[_Part, str]] = [
        (_box((0, 0, -t), (sx, sy, 0), floor_mat), "floor"),
        (_box((0, 0, sz), (sx, sy, sz + t), ceil_mat), "ceiling"),
    ]
    structure_parts += [(_box(b[0], b[1], wall_mat), "wall") for b in room_wall_boxes(size, doorway)]
    for b in structures:
        structure_parts.append((_box(b[0], b[1], wall_mat), "wall"))
    return structure_parts


def room_wall_boxes(size: np.ndarray, doorway: Doorway | None = None) -> list[np.ndarray]:
    """(2, 3) boxes of a room's four outer walls (0.1 m thick, outside the interior [0, size]);
    the wall with the doorway comes as three: either side of the opening and the lintel above it.

    >>> [b[:, 0].tolist() for b in room_wall_boxes(np.array([4.0, 3.0, 2.5]), Doorway(0, 2.0, 1.0))][:3]
    [[-0.1, 1.5], [2.5, 4.1], [1.5, 2.5]]
    """
    t = _WALL_T_M
    sx, sy, sz = (float(v) for v in size)
    walls = {0: np.array([[-t, -t, 0], [sx + t, 0, sz]]), 2: np.array([[-t, sy, 0], [sx + t, sy + t, sz]]),
             1: np.array([[sx, 0, 0], [sx + t, sy, sz]]), 3: np.array([[-t, 0, 0], [0, sy, sz]])}
    out: list[np.ndarray] = []
    for k in (0, 2, 3, 1):
        box = walls[k]
        if doorway is None or doorway.wall != k:
            out.append(box)
            continue
        x0, x1 = doorway.centre_x - doorway.width_m / 2, doorway.centre_x + doorway.width_m / 2
        left, right, lintel = box.copy(), box.copy(), box.copy()
        left[1, 0], right[0, 0] = x0, x1
        lintel[0, 0], lintel[1, 0], lintel[0, 2] = x0, x1, doorway.height_m
        out += [left, right, lintel]
    return out


class _Mesh:
    """The scene's mesh as it is assembled: per part, its vertices and triangles (indices offset
    past the parts before) and per-face label, instance and material columns."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        self.inst_ids: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.cols2: list[np.ndarray] = []
        self.texs: list[np.ndarray] = []
        self.scales: list[np.ndarray] = []
        self.n_v = 0

    def add(self, part: _Part, label: int, inst: int) -> None:
        self.verts.append(part.vertices)
        self.tris.append(part.triangles + self.n_v)
        self.n_v += part.vertices.shape[0]
        m = part.triangles.shape[0]
        self.labels.append(np.full(m, label, np.int32))
        self.inst_ids.append(np.full(m, inst, np.int32))
        self.cols.append(np.tile(np.asarray(part.material.colour, np.float32), (m, 1)))
        self.cols2.append(np.tile(np.asarray(part.material.colour2, np.float32), (m, 1)))
        self.texs.append(np.full(m, int(part.material.texture), np.int8))
        self.scales.append(np.full(m, part.material.scale_m, np.float32))


def _add_objects(mesh: _Mesh, placed: list[_Object]) -> list[Instance]:
    """Add every placed object (children flattened, each object with parts one instance) to `mesh`;
    returns the instances."""
    flat: list[tuple[_Object, int]] = []
    for obj in placed:
        _flatten(obj, -1, flat)
    instances: list[Instance] = []
    for idx, (obj, support) in enumerate(flat):
        for part in obj.parts:
            mesh.add(part, LABEL_OF[obj.class_name], idx)
        v = np.concatenate([q.vertices for q in obj.parts])
        part_boxes = np.stack([q.aabb for q in obj.parts])
        instances.append(Instance(idx, obj.class_name, LABEL_OF[obj.class_name], v.min(0), v.max(0),
                                  _area_centroid(obj.parts), support, part_boxes))
    return instances


def _face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals of the triangles (float32, computed in float64)."""
    tri_v = vertices.astype(np.float64)[triangles]
    n = np.cross(tri_v[:, 1] - tri_v[:, 0], tri_v[:, 2] - tri_v[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def _light(r: _Rand, st: SceneStyle, size: np.ndarray) -> Light:
    """The room's point light, 0.3 m under the ceiling in its middle part."""
    sx, sy, sz = size
    return Light(
        position=np.array([r.u(0.3, 0.7) * sx, r.u(0.3, 0.7) * sy, sz - 0.3]),
        colour=np.asarray(st.light_colour, dtype=np.float64),
        diffuse=r.u(*st.light_diffuse), ambient=r.u(*st.ambient), falloff_m=r.u(3.0, 4.5))


_DOORWAY_M = 1.2


def _corridor_walls(r: _Rand, size: np.ndarray) -> list[np.ndarray]:
    """Inner walls (full-height boxes) of rooms off a corridor: a corridor 1.4-1.7 m wide along
    y = 0, a wall along it with one 1.2 m doorway per room, and walls between 2-3 rooms."""
    sx, sy, sz = (float(v) for v in size)
    cw = r.u(1.4, 1.7)
    n_rooms = 3 if sx >= 9.0 and r.chance(0.5) else 2
    cuts = [sx * (k + r.u(-0.06, 0.06)) / n_rooms for k in range(1, n_rooms)]
    edges = [0.0, *cuts, sx]
    walls: list[np.ndarray] = []
    x0 = 0.0
    for k in range(n_rooms):  # the corridor's wall, a doorway per room
        lo, hi = edges[k] + _WALL_T_M, edges[k + 1] - _WALL_T_M
        d0 = r.u(lo + 0.3, hi - 0.3 - _DOORWAY_M)
        walls.append(np.array([[x0, cw, 0.0], [d0, cw + _WALL_T_M, sz]]))
        x0 = d0 + _DOORWAY_M
    walls.append(np.array([[x0, cw, 0.0], [sx, cw + _WALL_T_M, sz]]))
    for c in cuts:  # walls between the rooms
        walls.append(np.array([[c - _WALL_T_M / 2, cw + _WALL_T_M, 0.0], [c + _WALL_T_M / 2, sy, sz]]))
    return walls


def _flatten(obj: _Object, support: int, out: list[tuple[_Object, int]]) -> None:
    if obj.parts:
        out.append((obj, support))
        me = len(out) - 1
    else:
        me = support
    for c in obj.children:
        _flatten(c, me, out)


def _area_centroid(parts: list[_Part]) -> np.ndarray:
    total, acc = 0.0, np.zeros(3)
    for q in parts:
        tv = q.vertices[q.triangles]
        a = 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)
        total += a.sum()
        acc += (a[:, None] * tv.mean(1)).sum(0)
    return acc / max(total, 1e-12)
