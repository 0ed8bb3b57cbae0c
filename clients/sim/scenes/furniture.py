"""Object builders: furniture, appliances, wall-mounted things and free-standing clutter.

Each builder draws its sizes and materials from a `_Rand` and returns an `_Object` in its local
frame: x in [-w/2, w/2] along the wall, y in [0, d] from the wall (front is +y), z up.
"""

from __future__ import annotations

import numpy as np

from clients.sim.scenes.appearance import Material, Texture
from clients.sim.scenes.primitives import _box, _cylinder, _ellipsoid, _Object, _Part
from clients.sim.scenes.rand import _Rand


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


# Free-standing clutter (placed in the middle of the room)

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
