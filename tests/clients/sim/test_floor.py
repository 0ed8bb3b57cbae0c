"""Floors of rooms (`clients.sim.scenes.floor`), their tour (`clients.sim.tour`) and per-band ray
casting (`clients.sim.floor_render`)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import ndimage

from clients.sim.floor_render import FloorRenderer
from clients.sim.raycast import SceneRenderer
from clients.sim.robot import default_intrinsics, obstacle_distance_field
from clients.sim.scenes import LABEL_OF, Doorway, generate_room
from clients.sim.scenes.floor import Floor, generate_floor
from clients.sim.tour import floor_tour


@pytest.fixture(scope="module")
def floor() -> Floor:
    return generate_floor(4, 11)   # two bands (6 + 5 rooms) joined by the spine


def _free_cells(floor: Floor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dist, origin = obstacle_distance_field(floor.scene)
    return dist, origin, dist >= 0.3


def _cell(origin: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    g = np.floor((np.atleast_2d(xy) - origin) / 0.05).astype(int)
    return g[:, 0], g[:, 1]


def test_every_room_is_reachable_through_its_doorway(floor: Floor) -> None:
    """On the floor's free space (0.3 m from every wall and obstacle box), one connected piece holds
    a point inside each room and the corridor in front of each doorway; with the doorway's opening
    walled up, the room is cut off."""
    dist, origin, ok = _free_cells(floor)
    labels, _ = ndimage.label(ok, structure=np.ones((3, 3)))
    inside = [r.door_xy - r.door_normal * 0.8 for r in floor.rooms]
    outside = [np.array([r.door_xy[0], floor.corridor_y(r.band)]) for r in floor.rooms]
    pieces = {int(labels[_cell(origin, p)][0]) for p in inside + outside}
    assert len(pieces) == 1 and 0 not in pieces
    assert len(floor.corridors) == 2 and {r.band for r in floor.rooms} == {0, 1}
    room = floor.rooms[3]
    closed = ok.copy()
    d = room.door_xy
    half = np.array([room.doorway.width_m / 2 + 0.1, 0.1])
    lo, hi = _cell(origin, d - half), _cell(origin, d + half)
    closed[lo[0][0]:hi[0][0] + 1, lo[1][0]:hi[1][0] + 1] = False
    labels2, _ = ndimage.label(closed, structure=np.ones((3, 3)))
    assert labels2[_cell(origin, inside[3])][0] != labels2[_cell(origin, outside[3])][0]


def test_floor_is_deterministic_and_has_the_room_classes(floor: Floor) -> None:
    again = generate_floor(4, 11)
    np.testing.assert_array_equal(again.scene.vertices, floor.scene.vertices)
    np.testing.assert_array_equal(again.scene.face_label, floor.scene.face_label)
    other = generate_floor(5, 11)
    assert other.scene.vertices.shape != floor.scene.vertices.shape or \
        not np.array_equal(other.scene.vertices, floor.scene.vertices)
    classes = {i.class_name for i in floor.scene.instances}
    assert {"door", "chair", "table", "window", "cabinet"} <= classes
    assert {LABEL_OF["wall"], LABEL_OF["floor"], LABEL_OF["ceiling"]} <= set(floor.scene.face_label.tolist())
    ids = [i.instance_id for i in floor.scene.instances]
    assert ids == list(range(len(ids)))                         # one numbering for the whole floor
    assert set(np.unique(floor.scene.face_instance)) <= {-1, *ids}
    for room in floor.rooms:                                    # each room's objects stay in it
        mine = [i for i in room.local.instances]
        assert mine and all((i.aabb_min[:2] >= -0.11).all() for i in mine)
    with pytest.raises(ValueError, match="n_rooms 1 out of range"):
        generate_floor(0, 1)
    with pytest.raises(ValueError, match="cannot make a floor"):
        generate_floor(0, 3, "corridor")


def test_room_with_a_doorway_keeps_it_clear() -> None:
    room = generate_room(7, "office", (5.0, 4.2, 2.6), Doorway(wall=0, centre_x=1.2))
    keep_out = np.array([[1.2 - 0.75, 0.0], [1.2 + 0.75, 1.5]])
    for inst in room.instances:
        if inst.class_name in ("door", "rug"):
            continue
        overlap = (inst.aabb_min[:2] < keep_out[1]).all() and (inst.aabb_max[:2] > keep_out[0]).all()
        assert not overlap, inst.class_name
    with pytest.raises(ValueError, match="doorway centre_x"):
        generate_room(7, "office", (5.0, 4.2, 2.6), Doorway(wall=0, centre_x=0.2))


def test_tour_visits_every_room_in_free_space_and_comes_back(floor: Floor) -> None:
    tour = floor_tour(floor, 3000, seed=1)
    assert tour.poses.shape == (3000, 4, 4) and tour.visits == [*range(11), 0, 1]
    dist, origin, _ = _free_cells(floor)
    i, j = _cell(origin, tour.poses[:, :2, 3])
    assert dist[i, j].min() >= 0.25                             # 0.3 m clearance, to the grid's 5 cm
    assert np.linalg.norm(np.diff(tour.poses[:, :2, 3], axis=0), axis=1).max() <= tour.step_m + 1e-6
    assert (tour.poses[:, 2, 3] >= 0.8 - 1e-9).all() and (tour.poses[:, 2, 3] <= 1.6 + 1e-9).all()
    rooms_in_order = [int(k) for k, _ in itertools.groupby(tour.room) if k >= 0]
    assert rooms_in_order == [*range(11), 0, 1]                  # each room once, then the first two
    R = tour.poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-9)
    again = floor_tour(floor, 3000, seed=1)
    np.testing.assert_array_equal(again.poses, tour.poses)
    short = floor_tour(floor, 300, seed=1, revisit_rooms=0)     # few frames: shorter loops, every room
    assert short.loop_share < 1.0 and sorted(set(short.room.tolist()) - {-1}) == list(range(11))
    with pytest.raises(ValueError, match="n_frames 20 out of range"):
        floor_tour(floor, 20, seed=1)


def test_floor_renderer_matches_the_whole_floor_with_open3d(floor: Floor) -> None:
    pytest.importorskip("open3d")
    tour = floor_tour(floor, 400, seed=2)
    K = default_intrinsics(40, 30)
    whole = SceneRenderer(floor.scene, backend="open3d")
    culled = FloorRenderer(floor, backend="open3d")
    zones = set()
    for k in range(0, 400, 25):
        a = culled.render(K, tour.poses[k], 40, 30)
        b = whole.render(K, tour.poses[k], 40, 30)
        zones.add(floor.zone_at(tour.poses[k][:2, 3]))
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        np.testing.assert_array_equal(a.label, b.label)
        np.testing.assert_array_equal(a.rgb, b.rgb)
    assert {0, 1} <= zones
