"""The learned model's volume bounds follow the room without depth: ``ModelRuntime.set_view_extent``
(fed by mapper.node.plugins.triangulation) replaces the fixed ``model.max_range_m`` frustum of
RGB-only keyframes by their observed points, within the voxel budget."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapper.model.field import GovNeSF
from mapper.node.config import WindowConfig
from mapper.node.plugins.triangulation import keyframe_key
from mapper.node.window import KeyframeWindow
from mapper.runtime.model_runtime import ModelRuntime
from tests.mapper.test_runtime import TINY, keyframe, make_runtime, orbit


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
    runtime = make_runtime(model, source_views=3, view_cell_m=0.25)
    window = KeyframeWindow(WindowConfig(max_keyframes=6, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    kfs = [keyframe(i, orbit(i), depth_m=None) for i in range(5)]
    for kf in kfs:
        window.consider(kf)
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
    with runtime._lock:
        prep = runtime._prepare()
        return runtime._free_space(prep).cpu().numpy()


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
    with runtime._lock:
        prep = runtime._prepare()
        assert torch.equal(runtime._occupancy(prep), runtime._density_occupancy(prep))


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
