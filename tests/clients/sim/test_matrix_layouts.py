"""The scenario matrix's layouts (office, corridor, living_large, sparse): they generate, have the
classes their style promises, leave a drivable floor, and keep the older styles unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from clients.sim.robot import robot_trajectory
from clients.sim.scenes import STYLES, generate_scene

NEW_STYLES = ("office", "corridor", "living_large", "sparse")


@pytest.mark.parametrize("style", NEW_STYLES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_new_layouts_generate_with_a_drivable_floor(style: str, seed: int) -> None:
    scene = generate_scene(seed, style)
    classes = {inst.class_name for inst in scene.instances}
    assert {"door", "window"} <= classes
    size = scene.room_max - scene.room_min
    lo_x, hi_x = STYLES[style].room_x_m
    assert lo_x <= size[0] <= hi_x
    poses = robot_trajectory(scene, 30, seed=seed)
    assert poses.shape == (30, 4, 4) and np.isfinite(poses).all()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_office_has_rows_of_desks_with_monitors_and_chairs(seed: int) -> None:
    scene = generate_scene(seed, "office")
    count = {c: sum(i.class_name == c for i in scene.instances) for c in ("desk", "monitor", "chair")}
    assert count["desk"] >= 2 and count["monitor"] == count["desk"] and count["chair"] >= count["desk"]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_corridor_has_inner_walls_with_doorways(seed: int) -> None:
    scene = generate_scene(seed, "corridor")
    assert len(scene.structures) >= 4  # the corridor's wall in pieces around its doorways, and room walls
    y = {round(float(lo[1]), 3) for lo, _ in scene.structures}
    assert len(y) == 2  # one wall along the corridor, the room walls behind it


def test_large_living_room_is_8_to_10_m() -> None:
    for seed in range(3):
        size = generate_scene(seed, "living_large").room_max
        assert 8.0 <= size[0] <= 10.0 and 6.0 <= size[1] <= 8.0


def test_sparse_room_has_few_objects() -> None:
    n_sparse = np.mean([len(generate_scene(s, "sparse").instances) for s in range(4)])
    n_apartment = np.mean([len(generate_scene(s, "apartment").instances) for s in range(4)])
    assert n_sparse < n_apartment


def test_older_styles_are_unchanged_by_the_new_ones() -> None:
    """A style's rooms depend only on (seed, style): the new layout field defaults to one room."""
    assert STYLES["apartment"].layout == "room" and STYLES["studio"].layout == "room"
    scene = generate_scene(3, "apartment")
    assert scene.structures == [] and len(scene.instances) > 0
