"""Tests for mapper.geometry.splat: z-buffered splats of world points (exact depths of known
geometry, nearest wins, points behind the camera, footprints) and the see-through test."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapper.geometry.splat import (
    MAX_REACH_PX,
    fill_holes,
    fill_nearest,
    occluder_depths,
    point_spacing,
    remove_speckles,
    see_through,
    splat_points,
)

K = np.array([50.0, 50.0, 20.0, 15.0])  # 40 x 30 image


def plane_points(z: float, spacing: float = 0.01, half: float = 1.0) -> np.ndarray:
    """A fronto-parallel plane at z (camera = world frame), points on a grid."""
    g = np.arange(-half, half + 1e-9, spacing)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


@settings(max_examples=20, deadline=None)
@given(z=st.floats(0.3, 20.0), tx=st.floats(-0.5, 0.5), ty=st.floats(-0.5, 0.5))
def test_a_plane_splats_to_its_depth_and_each_pixel_shows_a_point_that_projects_near_it(
    z: float, tx: float, ty: float
) -> None:
    pose = np.eye(4)
    pose[:3, 3] = [tx, ty, 0.0]
    xyz = plane_points(z + 0.0, spacing=0.5 * z / K[0], half=2.0 * z) + [tx, ty, 0.0]
    index, depth = splat_points(xyz, K, pose, 40, 30, footprint_m=0.0)
    assert index.shape == (30, 40) and depth.dtype == np.float32
    assert np.all(index >= 0)  # points 0.5 px apart cover every pixel
    np.testing.assert_allclose(depth, z, rtol=1e-6)
    p = xyz[index] - [tx, ty, 0.0]
    u, v = K[0] * p[..., 0] / p[..., 2] + K[2], K[1] * p[..., 1] / p[..., 2] + K[3]
    cols, rows = np.meshgrid(np.arange(40), np.arange(30))
    assert np.all((np.floor(u) == cols) & (np.floor(v) == rows))  # footprint 0: the pixel it falls in


def _brute_force_splat(xyz: np.ndarray, width: int, height: int, footprint: float) -> np.ndarray:
    """The definition, point by point (camera = world frame): (H, W) nearest covering z."""
    out = np.full((height, width), np.inf)
    for x, y, z in xyz:
        if not z > 1e-3:
            continue
        u, v = K[0] * x / z + K[2], K[1] * y / z + K[3]
        reach = int(np.clip(np.rint(0.5 * K[0] * footprint / z), 0, MAX_REACH_PX))
        c, r = int(np.floor(u)), int(np.floor(v))
        for rr in range(r - reach, r + reach + 1):
            for cc in range(c - reach, c + reach + 1):
                if 0 <= rr < height and 0 <= cc < width:
                    out[rr, cc] = min(out[rr, cc], z)
    return np.where(np.isfinite(out), out, 0.0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 300), footprint=st.sampled_from([0.0, 0.05, 0.2, 1.0]))
def test_splat_equals_its_definition_point_by_point(seed: int, n: int, footprint: float) -> None:
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-1.2, 1.2, n), rng.uniform(-0.5, 4.0, n)])
    if n > 10:  # points sharing a pixel (and exact ties) on purpose
        xyz[: n // 4] = xyz[n // 4 : 2 * (n // 4)] * (1.0 + rng.uniform(0, 0.5))  # same pixel, farther
        xyz[-3:] = xyz[0]
    index, depth = splat_points(xyz, K, np.eye(4), 40, 30, footprint)
    np.testing.assert_allclose(depth, _brute_force_splat(xyz, 40, 30, footprint), rtol=1e-6)
    shown = index >= 0
    assert np.array_equal(shown, depth > 0)
    np.testing.assert_allclose(xyz[index[shown], 2], depth[shown], rtol=1e-6)  # the point it shows


def test_nearest_point_wins_and_points_behind_the_camera_are_ignored() -> None:
    near, far = plane_points(2.0, 0.02), plane_points(3.0, 0.02)
    behind = plane_points(-1.0, 0.02)
    xyz = np.concatenate([far, behind, near])
    index, depth = splat_points(xyz, K, np.eye(4), 40, 30, footprint_m=0.05)
    assert np.all(depth == np.float32(2.0))
    assert np.all(index >= len(far) + len(behind))  # every pixel shows a point of the near plane
    only_behind, d_behind = splat_points(behind, K, np.eye(4), 40, 30, footprint_m=0.05)
    assert np.all(only_behind == -1) and np.all(d_behind == 0)


def test_a_point_covers_its_footprint_up_to_the_reach() -> None:
    xyz = np.array([[0.0, 0.0, 2.0]])  # projects into pixel (20, 15)
    for footprint, reach in ((0.0, 0), (0.08, 1), (0.16, 2), (10.0, MAX_REACH_PX)):  # 0.5 fx f / z px
        index, depth = splat_points(xyz, K, np.eye(4), 40, 30, footprint_m=footprint)
        rows, cols = np.nonzero(index == 0)
        assert rows.min() == 15 - reach and rows.max() == 15 + reach
        assert cols.min() == 20 - reach and cols.max() == 20 + reach
        assert np.count_nonzero(depth) == (2 * reach + 1) ** 2


def test_empty_and_bad_inputs() -> None:
    index, depth = splat_points(np.zeros((0, 3)), K, np.eye(4), 8, 6, 0.05)
    assert index.shape == (6, 8) and np.all(index == -1) and np.all(depth == 0)
    for bad in (
        dict(xyz=np.zeros((3, 2))),
        dict(K=np.array([0.0, 50.0, 20.0, 15.0])),
        dict(K=np.array([np.nan, 50.0, 20.0, 15.0])),
        dict(world_from_cam=np.eye(3)),
        dict(width=0),
        dict(footprint_m=-1.0),
    ):
        args = dict(xyz=np.zeros((1, 3)), K=K, world_from_cam=np.eye(4), width=8, height=6, footprint_m=0.05)
        args.update(bad)
        with pytest.raises(ValueError):
            splat_points(**args)  # type: ignore[arg-type]


def test_see_through_flags_a_far_point_in_a_hole_of_a_near_surface_only() -> None:
    z = np.full((9, 9), 2.0, np.float32)
    z[4, 4] = 5.0  # seen through a hole of the 2 m surface
    z[0, 0] = 0.0  # no depth: never flagged
    flagged = see_through(z, window_px=1, rel=0.1)
    assert flagged[4, 4] and flagged.sum() == 1
    assert not see_through(z, window_px=0, rel=0.1).any()
    assert not see_through(z, window_px=1, rel=2.0).any()  # 5 m is within 3x of 2 m
    # a step between two surfaces (nearer on one side only) is an edge, not a hole
    step = np.full((5, 10), 2.0, np.float32)
    step[:, 5:] = 4.0
    assert not see_through(step, window_px=3, rel=0.1).any()
    # a far strip 2 px wide inside a near surface is a hole: flagged within the window only
    strip = np.full((5, 10), 2.0, np.float32)
    strip[:, 4:6] = 4.0
    assert see_through(strip, window_px=2, rel=0.1)[:, 4:6].all()
    assert not see_through(strip, window_px=1, rel=0.1).any()  # 1 px: the far side's partner is far
    with pytest.raises(ValueError):
        see_through(np.zeros(4), 1, 0.1)
    with pytest.raises(ValueError):
        see_through(z, -1, 0.1)


def test_fill_holes_interpolates_small_holes_of_one_surface_only() -> None:
    ramp = np.tile(np.linspace(2.0, 2.9, 10, dtype=np.float32), (6, 1))  # a slanted surface
    holes = ramp.copy()
    holes[2, 4:6] = 0.0  # 2 px hole in a row: both sides within 2 px
    holes[0:3, 8] = 0.0  # 3 px tall hole in a column, also bounded left and right
    filled = fill_holes(holes, window_px=2, rel=0.1)
    np.testing.assert_allclose(filled, ramp, rtol=1e-5)  # linear across the hole: exact on a ramp
    assert np.array_equal(fill_holes(holes, window_px=0, rel=0.1), holes)
    wide = ramp.copy()
    wide[:, 3:7] = 0.0  # 4 px wide, every row: farther than 2 px from one side for the middle ones
    out = fill_holes(wide, window_px=2, rel=0.1)
    assert np.all(out[:, 4:6] == 0)
    edge = np.zeros((3, 7), np.float32)
    edge[:, :3], edge[:, 4:] = 2.0, 4.0  # a hole between two different surfaces stays a hole
    assert np.all(fill_holes(edge, window_px=2, rel=0.1)[:, 3] == 0)
    border = ramp.copy()
    border[:, 0] = 0.0  # nothing on one side: not a hole of a surface
    assert np.all(fill_holes(border, window_px=2, rel=0.1)[:, 0] == 0)
    with pytest.raises(ValueError):
        fill_holes(np.zeros(3), 1, 0.1)


def test_remove_speckles_drops_small_islands_off_the_surface_only() -> None:
    z = np.tile(np.linspace(2.0, 3.0, 30, dtype=np.float32), (20, 1))  # a slanted wall
    z[5:8, 5:8] = 1.0  # a 9-pixel island floating in front of it
    z[12:15, 20:23] = 0.0  # a hole in it
    z[13, 21] = 6.0  # a 1-pixel island behind, inside the hole
    out = remove_speckles(z, max_size_px=10, rel=0.05)
    assert np.all(out[5:8, 5:8] == 0) and out[13, 21] == 0
    kept = np.ones(z.shape, bool)
    kept[5:8, 5:8] = False
    kept[12:15, 20:23] = False
    np.testing.assert_array_equal(out[kept], z[kept])  # the wall (600 pixels, smooth) stays
    assert np.array_equal(remove_speckles(z, max_size_px=0, rel=0.05), z)
    assert np.all(remove_speckles(z, max_size_px=8, rel=0.05)[5:8, 5:8] == 1.0)  # 9 > 8 pixels: kept
    big = remove_speckles(z, max_size_px=10_000, rel=0.05)
    assert not big.any()  # everything is an island below that size
    assert not remove_speckles(np.zeros((4, 4), np.float32), 5, 0.05).any()
    with pytest.raises(ValueError):
        remove_speckles(z, -1, 0.05)


@pytest.mark.parametrize("width,height,fx",
                         [(160, 120, 144.0), (320, 240, 288.0), (640, 480, 525.0), (1280, 960, 1150.0)])
def test_surface_depth_covers_a_voxel_grid_wall_at_every_resolution(
    width: int, height: int, fx: float
) -> None:
    """A wall of 5 cm voxel centres 2.4 m ahead: the surface covers the image and has its depth at
    every camera resolution (the splat's scale follows the focal length: a 640 x 480 camera is not
    left with dots and gaps); the scale is 1 where the footprint is not clipped anyway."""
    from mapper.geometry.splat import scaled_camera, splat_scale, upsample_nearest
    from mapper.node.queries import surface_depth
    from mapper.runtime.config import ModelRuntimeConfig

    g = np.arange(-3.0, 3.0, 0.05) + 0.025
    gx, gy = np.meshgrid(g, g)
    xyz = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 2.4)], axis=1)
    K = np.array([fx, fx, width / 2, height / 2])
    z = surface_depth(xyz, 0.05, K, np.eye(4), width, height, ModelRuntimeConfig())
    assert z.shape == (height, width) and z.dtype == np.float32
    assert (z > 0).mean() > 0.98
    np.testing.assert_allclose(z[z > 0], 2.4, rtol=1e-5)
    assert splat_scale(K, 0.05) == max(1, int(0.5 * fx * 0.05 / (MAX_REACH_PX * 2.0) + 0.5))
    K_s, w_s, h_s = scaled_camera(K, width, height, 3)
    assert (w_s, h_s) == (-(-width // 3), -(-height // 3)) and np.allclose(K_s * 3, K)
    up = upsample_nearest(np.arange(w_s * h_s).reshape(h_s, w_s), 3, height, width)
    assert up.shape == (height, width) and up[4, 7] == 1 * w_s + 2


def test_point_spacing_is_the_median_nearest_neighbour_distance() -> None:
    grid = plane_points(2.0, spacing=0.05, half=0.5)
    assert point_spacing(grid) == pytest.approx(0.05)
    assert point_spacing(grid, sample=50) == pytest.approx(0.05)  # subsampled: the same on a grid
    big = np.random.default_rng(0).uniform(-1, 1, (20000, 3))
    assert point_spacing(big) == point_spacing(big)  # seeded: the same cloud, the same answer
    with_nan = np.concatenate([grid, np.full((3, 3), np.nan)])
    assert point_spacing(with_nan) == pytest.approx(0.05)
    assert point_spacing(np.zeros((1, 3))) == 0.0 and point_spacing(np.zeros((5, 3))) == 0.0
    with pytest.raises(ValueError, match="xyz"):
        point_spacing(np.zeros((4, 2)))


def test_occluder_depths_hide_points_behind_nearer_ones_in_each_view() -> None:
    near = plane_points(1.0, spacing=0.01, half=0.2)  # a card 1 m in front of the first camera
    far = plane_points(3.0, spacing=0.02, half=1.5)  # a wall behind it
    xyz = np.concatenate([near, far])
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, :3, 3] = [1.0, 0.0, 0.0]  # a second camera, off to the side: the card is out of its view
    Ks = np.stack([K, K])
    z = occluder_depths(xyz, Ks, poses, 40, 30, footprint_m=0.03)
    assert z.shape == (2, 30, 40) and z.dtype == np.float32
    for m in range(2):  # each view equals its own splat at this resolution
        np.testing.assert_array_equal(z[m], splat_points(xyz, K, poses[m], 40, 30, 0.03)[1])
    # the depth test of DGM: a wall point behind the card is hidden in view 0, seen in view 1
    behind = np.array([0.0, 0.0, 3.0])
    u, v = (int(K[0] * behind[0] / 3.0 + K[2]), int(K[1] * behind[1] / 3.0 + K[3]))
    assert abs(3.0 - z[0, v, u]) > 0.25 * z[0, v, u]  # masked: the card at 1 m is in front
    assert z[0, v, u] == pytest.approx(1.0)
    p1 = behind - poses[1, :3, 3]
    u1, v1 = int(K[0] * p1[0] / p1[2] + K[2]), int(K[1] * p1[1] / p1[2] + K[3])
    assert z[1, v1, u1] == pytest.approx(3.0)  # seen: its own depth
    with pytest.raises(ValueError, match="views"):
        occluder_depths(xyz, Ks, poses[:1], 40, 30, 0.03)


def test_occluder_depths_of_a_high_resolution_camera_leave_no_holes_between_points() -> None:
    K_hi = np.array([525.0, 525.0, 320.0, 240.0])
    wall = plane_points(2.0, spacing=0.05, half=2.0)  # 5 cm apart: ~13 px apart at 640 x 480
    z = occluder_depths(wall, K_hi[None], np.eye(4)[None], 640, 480, footprint_m=0.05)
    assert (z[0] > 0).all()  # splatted at a lower resolution and upsampled
    np.testing.assert_allclose(z[0], 2.0, rtol=1e-6)
    _, plain = splat_points(wall, K_hi, np.eye(4), 640, 480, 0.05)
    assert (plain == 0).mean() > 0.5  # at full resolution the footprint is clipped: mostly holes


def test_fill_nearest_extends_surfaces_only_within_its_reach() -> None:
    z = np.zeros((5, 8), np.float32)
    z[:, :2] = 2.0  # a surface on the left
    z[0, 7] = 5.0  # a lone far pixel on the right
    out = fill_nearest(z, 2.0)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[:, :2], 2.0)  # pixels with depth are unchanged
    np.testing.assert_array_equal(out[:, 2:4], 2.0)  # within 2 px of the surface: its depth
    assert (out[1:, 4] == 0).all()  # beyond the reach of both: still empty
    assert out[0, 6] == 5.0 and out[0, 5] == 5.0 and out[2, 7] == 5.0  # the nearest of the two
    np.testing.assert_array_equal(fill_nearest(z, 0.0), z)
    np.testing.assert_array_equal(fill_nearest(np.zeros((3, 3)), 5.0), 0.0)  # nothing to extend
    with pytest.raises(ValueError, match="max_px"):
        fill_nearest(z, -1.0)
