"""Procedural scenes: determinism, vocabulary coverage, no interpenetration, objects in the room."""

from __future__ import annotations

import numpy as np
import pytest

from clients.sim.scenes import CLASS_NAMES, LABEL_OF, SCANNET20, STYLES, Scene, generate_scene

SEEDS = range(6)


@pytest.fixture(scope="module")
def scenes() -> dict[tuple[str, int], Scene]:
    return {(style, s): generate_scene(s, style) for style in ("apartment", "studio") for s in SEEDS}


def _overlap_volume(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise overlap volume of boxes a (N, 2, 3) and b (M, 2, 3) -> (N, M)."""
    lo = np.maximum(a[:, None, 0], b[None, :, 0])
    hi = np.minimum(a[:, None, 1], b[None, :, 1])
    return np.prod(np.clip(hi - lo, 0.0, None), axis=-1)


def test_vocabulary_layout() -> None:
    assert len(SCANNET20) == 20
    assert SCANNET20[0] == "wall" and SCANNET20[-1] == "otherfurniture"
    assert CLASS_NAMES[:20] == SCANNET20
    assert len(set(CLASS_NAMES)) == len(CLASS_NAMES)
    for extra in ("ceiling", "lamp", "plant", "monitor", "pillow", "rug"):
        assert extra in CLASS_NAMES[20:]
    assert {"apartment", "studio"} <= set(STYLES)


def test_deterministic_and_seed_dependent() -> None:
    a, b, c = generate_scene(4), generate_scene(4), generate_scene(5)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.face_label, b.face_label)
    np.testing.assert_array_equal(a.face_colour, b.face_colour)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


def test_arrays_consistent(scenes: dict[tuple[str, int], Scene]) -> None:
    for scene in scenes.values():
        f = scene.num_faces
        assert scene.vertices.dtype == np.float32 and scene.vertices.shape[1] == 3
        assert scene.triangles.dtype == np.int32 and scene.triangles.shape == (f, 3)
        assert scene.triangles.min() >= 0 and scene.triangles.max() < len(scene.vertices)
        for arr in (scene.face_label, scene.face_instance, scene.face_texture, scene.face_texture_scale):
            assert arr.shape == (f,)
        assert scene.face_colour.shape == scene.face_colour2.shape == scene.face_normal.shape == (f, 3)
        assert ((scene.face_label >= 0) & (scene.face_label < len(CLASS_NAMES))).all()
        np.testing.assert_allclose(np.linalg.norm(scene.face_normal, axis=1), 1.0, atol=1e-4)
        # instance ids are list positions, and their faces carry the instance's label
        for inst in scene.instances:
            faces = scene.face_instance == inst.instance_id
            assert faces.any()
            assert (scene.face_label[faces] == inst.label).all()
            assert CLASS_NAMES[inst.label] == inst.class_name
            assert (inst.aabb_min <= inst.centroid + 1e-6).all()
            assert (inst.centroid <= inst.aabb_max + 1e-6).all()
        # room structure has no instance, objects all have one
        structural = scene.face_instance < 0
        structure_labels = {LABEL_OF[n] for n in ("wall", "floor", "ceiling")}
        assert set(np.unique(scene.face_label[structural])) <= structure_labels


def test_objects_inside_room(scenes: dict[tuple[str, int], Scene]) -> None:
    for scene in scenes.values():
        for inst in scene.instances:
            assert (inst.aabb_min >= scene.room_min - 1e-6).all(), (scene.style, scene.seed, inst.class_name)
            assert (inst.aabb_max <= scene.room_max + 1e-6).all(), (scene.style, scene.seed, inst.class_name)


def test_nothing_interpenetrates(scenes: dict[tuple[str, int], Scene]) -> None:
    for key, scene in scenes.items():
        insts = scene.instances
        boxes = np.stack([np.stack([i.aabb_min, i.aabb_max]) for i in insts]).astype(np.float64)
        vol = _overlap_volume(boxes, boxes)
        np.fill_diagonal(vol, 0.0)
        # objects resting on / hanging from another are exempt only from their supporter's box
        for i in insts:
            if i.support_id >= 0:
                vol[i.instance_id, i.support_id] = vol[i.support_id, i.instance_id] = 0.0
        bad = np.argwhere(vol > 1e-9)
        assert len(bad) == 0, (key, [(insts[a].class_name, insts[b].class_name) for a, b in bad[:5]])
        # ... but no part of any object may overlap a part of another one, supporters included
        parts = np.concatenate([i.part_aabbs for i in insts])
        owner = np.concatenate([np.full(len(i.part_aabbs), i.instance_id) for i in insts])
        pv = _overlap_volume(parts, parts)
        pv[owner[:, None] == owner[None, :]] = 0.0
        bad = np.argwhere(pv > 1e-9)
        names = [(insts[owner[a]].class_name, insts[owner[b]].class_name) for a, b in bad[:5]]
        assert len(bad) == 0, (key, names)
        # and nothing overlaps the structural blocks of L-shaped rooms
        if scene.structures:
            sb = np.stack([np.stack(s) for s in scene.structures])
            assert (_overlap_volume(parts, sb) <= 1e-9).all()


def test_all_classes_appear_over_a_few_seeds(scenes: dict[tuple[str, int], Scene]) -> None:
    for style in ("apartment", "studio"):
        seen: set[str] = set()
        for s in SEEDS:
            scene = scenes[(style, s)]
            seen |= {CLASS_NAMES[x] for x in np.unique(scene.face_label)}
        assert set(SCANNET20) <= seen, (style, set(SCANNET20) - seen)
        assert set(CLASS_NAMES) - seen <= {"clock", "vase", "mirror", "towel", "television"}, style
    every = set()
    for scene in scenes.values():
        every |= {CLASS_NAMES[x] for x in np.unique(scene.face_label)}
    assert every == set(CLASS_NAMES)


def test_styles_differ(scenes: dict[tuple[str, int], Scene]) -> None:
    styles = ("apartment", "studio")
    area = {st: np.mean([np.prod(scenes[(st, s)].room_max[:2]) for s in SEEDS]) for st in styles}
    assert area["studio"] > area["apartment"]
    walls = {}
    for st in ("apartment", "studio"):
        cols = [sc.face_colour[sc.face_label == LABEL_OF["wall"]].mean(0)
                for sc in (scenes[(st, s)] for s in SEEDS)]
        walls[st] = np.mean(cols, axis=0)
    # studio walls are cooler (bluer relative to red) than apartment walls
    assert walls["studio"][2] - walls["studio"][0] > walls["apartment"][2] - walls["apartment"][0]
    assert not np.allclose(scenes[("apartment", 0)].light.colour, scenes[("studio", 0)].light.colour)


def test_surface_samples_lie_on_labelled_faces() -> None:
    scene = generate_scene(2)
    xyz, label, inst = scene.sample_surface(5000, seed=1, exclude_labels=(LABEL_OF["ceiling"],))
    assert xyz.shape == (5000, 3) and xyz.dtype == np.float32 and label.dtype == np.int32
    assert (label != LABEL_OF["ceiling"]).all()
    assert (xyz >= scene.room_min - 0.11).all() and (xyz <= scene.room_max + 0.11).all()
    # the floor's share of samples matches its share of the area (excluding the ceiling)
    areas = scene.face_areas()
    keep = scene.face_label != LABEL_OF["ceiling"]
    share = areas[keep & (scene.face_label == LABEL_OF["floor"])].sum() / areas[keep].sum()
    assert abs((label == LABEL_OF["floor"]).mean() - share) < 0.03
    for i in np.unique(inst[inst >= 0])[:10]:
        assert (label[inst == i] == scene.instances[i].label).all()


def test_surface_samples_of_only_some_labels() -> None:
    scene = generate_scene(2)
    chair = LABEL_OF["chair"] if LABEL_OF["chair"] in scene.face_label else int(scene.face_label[0])
    _, label, _ = scene.sample_surface(200, seed=3, only_labels=(chair,))
    assert (label == chair).all()
    with pytest.raises(ValueError, match="no surface"):
        scene.sample_surface(10, only_labels=(chair,), exclude_labels=(chair,))


@pytest.mark.parametrize("seed, style", [(-1, "apartment"), (0, "castle")])
def test_bad_arguments_raise(seed: int, style: str) -> None:
    with pytest.raises(ValueError, match="seed|style"):
        generate_scene(seed, style)
