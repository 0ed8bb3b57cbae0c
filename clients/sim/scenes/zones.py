"""Functional furniture zones (living, dining, bedroom, kitchen, bathroom, office) and clutter.

A zone is an anchor (its big group, e.g. a sofa with a coffee table) plus extras; the
generator places all anchors before any extras.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from clients.sim.scenes.appearance import Texture
from clients.sim.scenes.furniture import (
    _armchair,
    _bathtub,
    _bed,
    _bookshelf,
    _cabinet,
    _chair,
    _desk,
    _facing_table,
    _floor_lamp,
    _kitchen_run,
    _mirror,
    _nightstand,
    _ottoman,
    _plant,
    _refrigerator,
    _side_table,
    _sofa,
    _table,
    _toilet,
    _towel,
    _trash_can,
    _tv_stand,
    _vanity,
    _wall_cabinet,
)
from clients.sim.scenes.placement import _Placer
from clients.sim.scenes.primitives import _box, _cylinder, _group, _Object


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


def _desk_row(p: _Placer) -> None:
    """Open-plan office: a row of 2-3 desks side by side in the middle of the room, each with a
    monitor and a chair in front of it; sometimes a second row back to back."""
    r = p.r
    n = int(r.rng.integers(2, 4))
    desks = [_desk(r) for _ in range(n)]
    widths = [float(d.aabb()[1, 0] - d.aabb()[0, 0]) for d in desks]
    x = -0.5 * (sum(widths) + 0.02 * (n - 1))
    members: list[_Object] = []
    for desk, w in zip(desks, widths, strict=True):
        cx = x + w / 2
        members.append(desk.transformed(0, np.array([cx, 0.0, 0.0])))
        dd = float(desk.aabb()[1, 1])
        members.append(_facing_table(_chair(r), cx, dd, +1))
        x += w + 0.02
    row = _group("desks", members)
    if r.chance(0.5):  # back to back: the same row turned around, behind the first
        row = _group("desks", [row, row.transformed(2, np.array([0.0, -0.02, 0.0]))])
    p.try_place(row, central=True, walkway_m=0.5, tries=60)


def _chair_row(p: _Placer) -> None:
    """A row of 3-5 chairs against a wall (a waiting or meeting area)."""
    r = p.r
    n = int(r.rng.integers(3, 6))
    m, seat = r.wood(), r.fabric()
    chairs = [_chair(r, m, seat) for _ in range(n)]
    w = float(chairs[0].aabb()[1, 0] - chairs[0].aabb()[0, 0])
    members = [c.transformed(0, np.array([(k - (n - 1) / 2) * (w + 0.08), 0.0, 0.0]))
               for k, c in enumerate(chairs)]
    p.try_place(_group("chairs", members), tries=60)


def _open_office_extras(p: _Placer) -> None:
    r = p.r
    _chair_row(p)
    p.try_place(_cabinet(r, r.dim(0.8), r.dim(0.45), r.dim(1.1)))
    p.try_place(_plant(r))
    p.try_place(_trash_can(r))


def _nothing(p: _Placer) -> None:
    return None


_ZONES: dict[str, tuple[Callable[[_Placer], None], Callable[[_Placer], None]]] = {
    "living": (_living_anchor, _living_extras), "dining": (_dining_anchor, _nothing),
    "bedroom": (_bedroom_anchor, _bedroom_extras), "kitchen": (_kitchen_anchor, _kitchen_extras),
    "bathroom": (_bathroom_anchor, _bathroom_extras), "office": (_office_anchor, _office_extras),
    "desk_rows": (_desk_row, _open_office_extras),
}
"""Zone -> (anchor placement, extras). All anchors (big groups) are placed before any extras."""


def _clutter(p: _Placer, n: int) -> None:
    """Free-standing objects away from the walls: occluders at middle depths."""
    r = p.r
    makers = (_armchair, _ottoman, _plant, _floor_lamp, _side_table, _trash_can)
    for _ in range(n):
        p.try_place(r.pick(makers)(r), central=True, walkway_m=0.45, tries=30)
