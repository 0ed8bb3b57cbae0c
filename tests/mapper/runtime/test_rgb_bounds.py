"""The learned model's volume bounds follow the room without depth: ``ModelRuntime.set_view_extent``
(fed by mapper.node.workers.triangulation) replaces the fixed ``model.max_range_m`` frustum of
RGB-only keyframes by their observed points, within the voxel budget."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapper.map.window import KeyframeWindow
from mapper.model.field import GovNeSF
from mapper.node.config import WindowConfig
from mapper.node.workers.triangulation import keyframe_key
from mapper.runtime.density import density_occupancy, free_space, occupancy_grid
from mapper.runtime.model_runtime import ModelRuntime
from tests.mapper.runtime.test_model_runtime import TINY, keyframe, make_runtime, orbit


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


def _extent(runtime: ModelRuntime) -> np.ndarray:
    b = runtime.bounds
    assert b is not None
    return np.asarray(b.max_corner_m) - np.asarray(b.origin_m)


def _room_points(half_x: float, half_y: float, n: int = 400, seed: int = 0) -> np.ndarray:
    """(n, 3) points on the walls of a room [-half_x, half_x] x [-half_y, half_y] x [0, 2.5]."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(-1.0, 1.0, n)
    side = rng.integers(0, 4, n)
    x = np.where(side < 2, np.where(side == 0, -half_x, half_x), t * half_x)
    y = np.where(side < 2, t * half_y, np.where(side == 2, -half_y, half_y))
    return np.column_stack([x, y, rng.uniform(0.0, 2.5, n)])


def _rgb_only_runtime(model: GovNeSF, n: int = 5, **overrides: object) -> tuple[ModelRuntime, list]:
    """A runtime over ``n`` keyframes without depth on the orbit, 3 views a point (cells of 0.25 m)."""
    runtime = make_runtime(model, source_views=3, view_cell_m=0.25, **overrides)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    kfs = [keyframe(i, orbit(i), depth_m=None) for i in range(n)]
    for kf in kfs:
        window.consider(kf)
    return runtime, kfs


def test_view_extents_grow_and_shrink_the_volume_of_rgb_only_keyframes(model: GovNeSF) -> None:
    runtime = make_runtime(model, max_range_m=3.0, bounds_margin_m=0.0)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    kfs = [keyframe(i, orbit(i, radius=1.0), depth_m=None) for i in range(4)]
    for kf in kfs:
        window.consider(kf)
    runtime.sync()
    base, rebuilds, version = _extent(runtime), runtime.rebuilds, runtime.version
    assert runtime.sync() == 0  # nothing recorded: nothing to do
    big = _room_points(4.0, 3.0)  # the points say the room is 8 x 6 m: beyond the 3 m frusta
    for kf in kfs:
        runtime.set_view_extent(keyframe_key(kf), big)
    assert runtime.sync() == 4
    grown = _extent(runtime)
    assert runtime.rebuilds == rebuilds + 1 and runtime.version == version + 1
    assert grown[0] >= 8.0 and grown[1] >= 6.0 and grown.prod() > base.prod()
    assert runtime.bounds is not None
    assert runtime.bounds.num_voxels <= TINY.volume.max_voxels  # the budget holds: coarser voxels
    small = _room_points(1.5, 1.2)
    for kf in kfs:
        runtime.set_view_extent(keyframe_key(kf), small)  # a small room
    runtime.sync()
    shrunk = _extent(runtime)
    assert 3.0 <= shrunk[0] < 4.0 and 2.4 <= shrunk[1] < 3.5 and shrunk.prod() < 0.5 * base.prod()
    for kf in kfs:
        runtime.set_view_extent(keyframe_key(kf), None)  # back to the frusta up to max_range_m
    runtime.sync()
    np.testing.assert_allclose(_extent(runtime), base)


def test_an_extent_set_before_the_keyframe_is_applied_is_used_and_depth_keyframes_ignore_it(
    model: GovNeSF,
) -> None:
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    early, late = make_runtime(model, max_range_m=3.0), make_runtime(model, max_range_m=3.0)
    early.attach(window)
    late.attach(window)
    kfs = [keyframe(i, orbit(i), depth_m=None) for i in range(3)]
    big = _room_points(4.0, 3.0)
    for kf in kfs:
        window.consider(kf)
        early.set_view_extent(keyframe_key(kf), big)  # before the runtime applied the keyframe
    early.sync()
    late.sync()
    for kf in kfs:
        late.set_view_extent(keyframe_key(kf), big)
    late.sync()
    assert early.bounds == late.bounds
    with_depth = make_runtime(model, max_range_m=3.0)
    w2 = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    with_depth.attach(w2)
    dkfs = [keyframe(i, orbit(i), depth_m=2.0) for i in range(3)]
    for kf in dkfs:
        w2.consider(kf)
    with_depth.sync()
    before = with_depth.bounds
    for kf in dkfs:
        with_depth.set_view_extent(keyframe_key(kf), big)
    assert with_depth.sync() == 0 and with_depth.bounds == before
    for bad in (np.zeros((0, 3)), np.zeros((4, 2)), np.full((2, 3), np.nan)):
        with pytest.raises(ValueError, match="points_m"):
            with_depth.set_view_extent(keyframe_key(dkfs[0]), bad)


def test_a_sparse_depth_prior_masks_views_only_where_it_exists(model: GovNeSF) -> None:
    # the prior is what DGM tests against without input depth when the request's points are not
    # the occluders (point_occlusion off)
    runtime, kfs = _rgb_only_runtime(model, point_occlusion=False)
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.4, -0.4, 0.3], [0.4, 0.4, 0.7], (200, 3)).astype(np.float32)
    plain, plain_score, _ = runtime.segment(pts, ["a", "b", "c"])
    no_prior, no_prior_score, _ = runtime.segment(pts, ["a", "b", "c"], use_depth=True)  # nothing to mask
    np.testing.assert_array_equal(plain, no_prior)
    for kf in kfs:  # an empty prior: holes everywhere, so no view is masked
        runtime.set_view_depth_prior(keyframe_key(kf), np.zeros((30, 40), np.float32))
    empty, empty_score, _ = runtime.segment(pts, ["a", "b", "c"], use_depth=True)
    np.testing.assert_array_equal(empty, plain)
    np.testing.assert_allclose(empty_score, plain_score, atol=1e-6)
    for kf in kfs:  # a prior that contradicts every point (a surface 5 cm in front of every camera)
        runtime.set_view_depth_prior(keyframe_key(kf), np.full((15, 20), 0.05, np.float32))
    masked, masked_score, _ = runtime.segment(pts, ["a", "b", "c"], use_depth=True)
    assert (masked == -1).all() and (masked_score == 0).all()
    unmasked, _, _ = runtime.segment(pts, ["a", "b", "c"])  # without use_depth the prior is unused
    np.testing.assert_array_equal(unmasked, plain)
    with pytest.raises(ValueError, match="depth_m"):
        runtime.set_view_depth_prior(keyframe_key(kfs[0]), np.full((3, 4), -1.0, np.float32))


def _carved(runtime: ModelRuntime) -> np.ndarray:
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        return free_space(runtime._loaded, prep).cpu().numpy()


def test_depth_priors_carve_the_free_space_in_front_of_their_surfaces(model: GovNeSF) -> None:
    from dataclasses import replace

    runtime = make_runtime(model, bounds_margin_m=0.0, carve_free_space=True)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    kfs = [keyframe(i, orbit(i), depth_m=None) for i in range(5)]
    for kf in kfs:
        window.consider(kf)
    assert not _carved(runtime).any()  # no prior: nothing carved
    for kf in kfs:  # every camera sees a surface 3 m away (1 m beyond the orbit's centre)
        runtime.set_view_depth_prior(keyframe_key(kf), np.full((30, 40), 3.0, np.float32))
    runtime.sync()
    carved = _carved(runtime)
    assert carved.any()
    b = runtime.bounds
    assert b is not None
    centres = (np.argwhere(carved) + 0.5) * b.voxel_size_m + np.asarray(b.origin_m)
    cams = np.array([orbit(i) for i in range(5)])
    dist = np.linalg.norm(centres[:, None, :] - cams[None, :, :], axis=-1)  # (n, 5)
    # a carved voxel lies within (1 - margin) * 3 m / cos(off-axis angle) of at least carve_min_views
    # cameras (plus a voxel; the 40 x 30 image's corner rays are ~53 deg off the axis)
    reach = (1.0 - runtime.config.carve_margin) * 3.0 / 0.6 + b.voxel_size_m
    assert ((dist <= reach).sum(axis=1) >= runtime.config.carve_min_views).all()
    # the surfaces themselves (3 m along each optical axis) are never carved
    for eye in cams:
        axis = np.array([0.0, 0.0, 0.5]) - eye
        point = eye + 3.0 * axis / np.linalg.norm(axis)
        vox = np.floor((point - np.asarray(b.origin_m)) / b.voxel_size_m).astype(int)
        if ((vox >= 0) & (vox < np.asarray(b.dims))).all():
            assert not carved[tuple(vox)]
    # the occupancy grid leaves the carved voxels out; off, or too many views asked for: nothing carved
    bounds, occupancy = runtime.occupancy()
    assert not (occupancy.cpu().numpy() & carved).any()
    runtime.config = replace(runtime.config, carve_min_views=1000)
    assert not _carved(runtime).any()
    runtime.config = replace(runtime.config, carve_min_views=2, carve_free_space=False)
    with runtime._volume.lock:
        prep = runtime._volume.prepare()
        assert torch.equal(occupancy_grid(runtime._loaded, prep), density_occupancy(runtime._loaded, prep))


def test_keyframes_with_input_depth_never_carve(model: GovNeSF) -> None:
    runtime = make_runtime(model)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    kfs = [keyframe(i, orbit(i), depth_m=2.0) for i in range(5)]
    for kf in kfs:
        window.consider(kf)
        runtime.set_view_depth_prior(keyframe_key(kf), np.full((30, 40), 2.0, np.float32))  # ignored
    assert not _carved(runtime).any()


def test_a_keyframe_with_a_wild_pose_is_left_out_of_the_bounds(model: GovNeSF) -> None:
    """One keyframe 1e6 m away (a valid pose: finite, a rotation) does not stretch the volume over
    it: the bounds and voxel size stay those of the other keyframes; it is counted once."""
    runtime = make_runtime(model, max_range_m=3.0, bounds_margin_m=0.0)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(4):
        window.consider(keyframe(i, orbit(i, radius=1.0), depth_m=None))
    runtime.sync()
    assert runtime.bounds is not None
    base, voxel = _extent(runtime), runtime.bounds.voxel_size_m
    x, y, z = orbit(4, radius=1.0)
    window.consider(keyframe(4, (x + 1e6, y, z), target=(1e6, 0.0, 0.5), depth_m=None))
    runtime.sync()
    assert runtime.bounds is not None and runtime.bounds.voxel_size_m == voxel
    np.testing.assert_allclose(_extent(runtime), base)
    assert runtime.bounds_outliers == 1 and runtime.stats()["bounds_outliers"] == 1
    window.consider(keyframe(5, orbit(5, radius=1.0), depth_m=None))
    runtime.sync()
    assert runtime.bounds_outliers == 1  # counted once


def _shell_and_core(half: float = 0.6, step: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """(S, 3) points on the faces of a cube of half size ``half`` around (0, 0, 0.5) and (C, 3)
    points near its centre, which every camera outside the cube sees only through it."""
    g = np.arange(-half, half + 1e-9, step)
    a, b = (x.ravel() for x in np.meshgrid(g, g))
    faces = []
    for axis in range(3):
        for side in (-half, half):
            f = np.zeros((a.size, 3))
            f[:, axis] = side
            f[:, (axis + 1) % 3], f[:, (axis + 2) % 3] = a, b
            faces.append(f)
    shell = np.unique(np.concatenate(faces).round(6), axis=0) + [0.0, 0.0, 0.5]
    core = np.random.default_rng(1).uniform(-0.08, 0.08, (40, 3)) + [0.0, 0.0, 0.5]
    return shell.astype(np.float32), core.astype(np.float32)


def test_the_requests_points_hide_one_another_in_views_without_input_depth(model: GovNeSF) -> None:
    shell, core = _shell_and_core()
    pts = np.concatenate([shell, core])
    texts = ["a", "b", "c"]
    runs = {}
    for occlusion in (True, False):
        runtime, _ = _rgb_only_runtime(model, point_occlusion=occlusion)
        plain, _, _ = runtime.segment(pts, texts)
        label, score, timing = runtime.segment(pts, texts, use_depth=True)
        runs[occlusion] = (plain, label, score, timing)
    plain, label, score, timing = runs[True]
    core_rows = slice(len(shell), None)
    assert (plain[core_rows] >= 0).all()  # without the depth test every view sees the core
    assert (label[core_rows] == -1).all() and (score[core_rows] == 0).all()  # the shell hides it everywhere
    facing = np.isclose(shell[:, 0], 0.6)  # the face towards the first camera, (2, 0, 1.2)
    assert (label[: len(shell)][facing] >= 0).all()  # it is seen: answered
    assert (label[: len(shell)] == -1).any()  # faces no camera sees (behind the front ones) are not
    assert "occluders" in timing
    off_plain, off_label, _, off_timing = runs[False]  # off: no prior either, so nothing is masked
    np.testing.assert_array_equal(off_label, off_plain)
    assert "occluders" not in off_timing
    alone, _ = _rgb_only_runtime(model)
    core_alone, _, _ = alone.segment(core, texts, use_depth=True)  # asked alone, nothing hides the core
    assert (core_alone >= 0).all()


def test_keyframes_with_input_depth_keep_it_for_the_depth_test(model: GovNeSF) -> None:
    shell, core = _shell_and_core()
    pts = np.concatenate([shell, core])
    answers = []
    for occlusion in (True, False):
        runtime = make_runtime(model, source_views=3, view_cell_m=0.25, point_occlusion=occlusion)
        window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
        runtime.attach(window)
        for i in range(5):
            window.consider(keyframe(i, orbit(i), depth_m=2.0))
        label, score, timing = runtime.segment(pts, ["a", "b", "c"], use_depth=True)
        assert "occluders" not in timing
        answers.append((label, score))
    np.testing.assert_array_equal(answers[0][0], answers[1][0])
    np.testing.assert_array_equal(answers[0][1], answers[1][1])


def test_dgm_view_selection_chooses_views_that_pass_the_depth_test(model: GovNeSF) -> None:
    # three near keyframes whose depth contradicts the points (a surface 0.3 m in front of them)
    # and three farther ones whose depth agrees; two views a point
    near = [keyframe(i, orbit(i, radius=1.5), depth_m=0.3) for i in range(3)]
    far = [keyframe(i + 3, orbit(i + 3, radius=2.5), depth_m=2.6) for i in range(3)]
    pts = np.random.default_rng(2).uniform(-0.05, 0.05, (30, 3)).astype(np.float32) + [0.0, 0.0, 0.5]
    out = {}
    for selection in (False, True):
        runtime = make_runtime(model, source_views=2, point_source_views=2, view_cell_m=1.0,
                               dgm_view_selection=selection)
        window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
        runtime.attach(window)
        for kf in near + far:
            window.consider(kf)
        out[selection] = (runtime.segment(pts, ["a", "b", "c"])[0],
                          runtime.segment(pts, ["a", "b", "c"], use_depth=True)[0])
    plain_off, dgm_off = out[False]
    plain_on, dgm_on = out[True]
    np.testing.assert_array_equal(plain_on, plain_off)  # without the depth test nothing changes
    assert (dgm_off == -1).all()  # the two nearest views are chosen, then both masked
    assert (dgm_on >= 0).all()  # the views that pass the test are chosen instead


def test_point_occlusion_settings_are_checked_with_the_key_named() -> None:
    from mapper.node.config import ConfigError, load_config

    cfg = load_config(None, {})
    assert cfg.model.point_occlusion and cfg.model.dgm_view_selection and cfg.model.point_occlusion_prior_veto
    assert cfg.queries.point_occlusion
    for key, bad in (("model.point_occlusion_footprint", 0.0), ("model.point_occlusion_footprint", 1e3),
                     ("model.point_occlusion", "yes"), ("model.dgm_view_selection", 1),
                     ("model.point_occlusion_prior_veto", "no"), ("queries.point_occlusion", 0)):
        with pytest.raises(ConfigError, match=key.split(".")[1]):
            load_config(None, {key: bad})


def test_an_occluder_that_the_keyframes_depth_prior_sees_through_is_dropped(model: GovNeSF) -> None:
    shell, core = _shell_and_core()
    pts = np.concatenate([shell, core])
    core_rows = slice(len(shell), None)
    out = {}
    for veto in (False, True):
        runtime, kfs = _rgb_only_runtime(model, point_occlusion_prior_veto=veto)
        for kf in kfs:  # each keyframe's prior: a surface 5 m away, behind the whole shell
            runtime.set_view_depth_prior(keyframe_key(kf), np.full((30, 40), 5.0, np.float32))
        out[veto] = runtime.segment(pts, ["a", "b", "c"], use_depth=True)[0]
    assert (out[False][core_rows] == -1).all()  # the shell hides the core
    assert (out[True][core_rows] >= 0).all()  # the priors see through the shell: it hides nothing
