"""mapper.geometry.planes: plane fits to measured points, their support, and the depth on them."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry.planes import Plane, fit_planes, plane_depth, point_normals

K = np.array([80.0, 80.0, 80.0, 60.0])  # 160 x 120


def _box_room(n_per_face: int = 1500, noise: float = 0.005, seed: int = 0) -> np.ndarray:
    """Points on the floor (z = 0), the x = 0 wall and the y = 0 wall of a 4 x 3 x 2.5 m room."""
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.random(n_per_face) * 4, rng.random(n_per_face) * 3, np.zeros(n_per_face)]
    wall_x = np.c_[np.zeros(n_per_face), rng.random(n_per_face) * 3, rng.random(n_per_face) * 2.5]
    wall_y = np.c_[rng.random(n_per_face) * 4, np.zeros(n_per_face), rng.random(n_per_face) * 2.5]
    pts = np.concatenate([floor, wall_x, wall_y])
    return pts + rng.normal(0, noise, pts.shape)


def _down(eye: np.ndarray) -> np.ndarray:
    """(4, 4) camera at ``eye`` looking straight down (optical axis -z, image x along world x)."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]).T
    pose[:3, 3] = eye
    return pose


def _axis_of(plane: Plane) -> int:
    return int(np.argmax(np.abs(plane.normal)))


def test_box_room_gives_its_three_planes_with_the_right_normals_and_offsets() -> None:
    planes = fit_planes(_box_room(), inlier_m=0.02, min_inliers=300, cell_m=0.25, seed=1)
    assert sorted(_axis_of(p) for p in planes) == [0, 1, 2]
    for p in planes:
        axis = _axis_of(p)
        assert abs(abs(p.normal[axis]) - 1.0) < 1e-3
        assert abs(p.offset) < 0.01  # all three planes pass through the origin
        assert p.inliers >= 1400


def test_normals_reject_a_slab_across_two_surfaces() -> None:
    # two perpendicular walls meeting along a line: without normals a diagonal slab through the
    # corner collects points of both walls near the line; with normals only the walls are planes
    pts = _box_room(n_per_face=800, noise=0.0)
    normals, flatness = point_normals(pts, 12)
    assert np.median(flatness) > 0.9
    planes = fit_planes(pts, normals=normals, max_normal_deg=20, inlier_m=0.02, min_inliers=100, cell_m=0.25)
    for p in planes:
        assert abs(p.normal).max() > 0.999  # axis-aligned: a true face of the box


def test_point_normals_of_a_plane_are_its_normal() -> None:
    rng = np.random.default_rng(3)
    pts = np.c_[rng.random((300, 2)), np.zeros(300)]
    normals, flatness = point_normals(pts, 8)
    assert np.allclose(np.abs(normals[:, 2]), 1.0, atol=1e-9)
    assert np.allclose(flatness, 1.0)
    assert point_normals(pts[:2], 8)[0].tolist() == [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]  # too few points


def test_plane_depth_of_a_floor_seen_from_above_is_exact() -> None:
    rng = np.random.default_rng(0)
    floor = np.c_[rng.random((4000, 2)) * 8 - 4, np.zeros(4000)]
    planes = fit_planes(floor, inlier_m=0.01, min_inliers=100, cell_m=0.25, seed=0)
    assert len(planes) == 1
    pose = _down(np.array([0.0, 0.0, 2.0]))  # 2 m up
    depth, index = plane_depth(planes, K, pose, 160, 120)
    assert (index == 0).all()
    # a straight-down camera sees the floor at z-depth 2 m at every pixel
    np.testing.assert_allclose(depth, 2.0, atol=1e-4)


def test_support_stops_the_plane_where_its_points_stop() -> None:
    rng = np.random.default_rng(0)
    patch = np.c_[rng.random((2000, 2)) * 1.0, np.zeros(2000)]  # a 1 x 1 m patch of the z = 0 plane
    planes = fit_planes(patch, inlier_m=0.01, min_inliers=100, cell_m=0.1, close_cells=1, seed=0)
    assert len(planes) == 1
    inside = planes[0].supports(np.array([[0.5, 0.5, 0.0], [0.05, 0.95, 0.0]]))
    outside = planes[0].supports(np.array([[2.0, 0.5, 0.0], [-0.5, -0.5, 0.0], [0.5, 3.0, 0.0]]))
    assert inside.all() and not outside.any()
    pose = _down(np.array([0.5, 0.5, 2.0]))
    depth, index = plane_depth(planes, K, pose, 160, 120)
    hit = depth > 0
    # the patch covers the centre of the image, not its corners (at 2 m the image spans 4 x 3 m)
    assert hit[60, 80] and not hit[0, 0] and not hit[-1, -1]
    assert ((index >= 0) == hit).all()
    # the patch's 1 m at 2 m depth: about fx / 2 = 40 pixels across
    assert 30 <= hit[60].sum() <= 50


def test_the_nearest_of_two_planes_wins_and_planes_behind_the_camera_are_ignored() -> None:
    rng = np.random.default_rng(0)
    xy = rng.random((3000, 2)) * 8 - 4
    near = np.c_[xy, np.full(3000, 1.0)]  # z = 1
    far = np.c_[xy, np.zeros(3000)]  # z = 0
    above = np.c_[xy, np.full(3000, 5.0)]  # z = 5: behind a camera at z = 3 looking down
    planes = fit_planes(np.concatenate([far, near, above]), inlier_m=0.01, min_inliers=100, cell_m=0.25)
    assert len(planes) == 3
    pose = _down(np.array([0.0, 0.0, 3.0]))
    depth, index = plane_depth(planes, K, pose, 160, 120)
    np.testing.assert_allclose(depth, 2.0, atol=1e-4)  # the z = 1 plane, 2 m below the camera
    assert abs(planes[int(index[60, 80])].offset + planes[int(index[60, 80])].normal[2]) < 1e-6


def test_degenerate_inputs_give_no_planes() -> None:
    assert fit_planes(np.zeros((0, 3)), inlier_m=0.01, min_inliers=3, cell_m=0.1) == []
    line = np.c_[np.linspace(0, 1, 500), np.zeros(500), np.zeros(500)]  # collinear: no plane
    assert fit_planes(line, inlier_m=0.01, min_inliers=10, cell_m=0.1) == []
    few = _box_room(n_per_face=30)
    assert fit_planes(few, inlier_m=0.01, min_inliers=100, cell_m=0.1) == []
    nan = np.concatenate([_box_room(n_per_face=500), np.full((50, 3), np.nan)])
    assert len(fit_planes(nan, inlier_m=0.02, min_inliers=100, cell_m=0.25)) == 3  # non-finite rows ignored
    depth, index = plane_depth([], K, np.eye(4), 16, 12)
    assert (depth == 0).all() and (index == -1).all()


def test_fit_is_deterministic_for_a_seed() -> None:
    pts = _box_room()
    a = fit_planes(pts, inlier_m=0.02, min_inliers=300, cell_m=0.25, seed=7)
    b = fit_planes(pts, inlier_m=0.02, min_inliers=300, cell_m=0.25, seed=7)
    assert [p.inliers for p in a] == [p.inliers for p in b]
    for p, q in zip(a, b, strict=True):
        assert np.array_equal(p.support, q.support) and np.array_equal(p.normal, q.normal)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"inlier_m": 0.0}, "inlier_m"),
        ({"inlier_m": float("nan")}, "inlier_m"),
        ({"cell_m": -1.0}, "cell_m"),
        ({"min_inliers": 2}, "min_inliers"),
        ({"iterations": 0}, "iterations"),
        ({"max_normal_deg": 120.0}, "max_normal_deg"),
        ({"normals": np.zeros((5, 3))}, "normals"),
    ],
)
def test_bad_arguments_are_refused(kwargs: dict, message: str) -> None:
    args = {"inlier_m": 0.02, "min_inliers": 10, "cell_m": 0.25, **kwargs}
    with pytest.raises(ValueError, match=message):
        fit_planes(_box_room(n_per_face=100), **args)


def test_bad_cameras_are_refused() -> None:
    with pytest.raises(ValueError, match="fx, fy"):
        plane_depth([], np.array([0.0, 1.0, 1.0, 1.0]), np.eye(4), 4, 4)
    with pytest.raises(ValueError, match="finite"):
        plane_depth([], K, np.full((4, 4), np.nan), 4, 4)
    with pytest.raises(ValueError, match="image size"):
        plane_depth([], K, np.eye(4), 0, 4)
    with pytest.raises(ValueError, match="shape"):
        fit_planes(np.zeros((4, 2)), inlier_m=0.02, min_inliers=3, cell_m=0.25)
    with pytest.raises(ValueError, match="finite"):
        point_normals(np.full((4, 3), np.nan))


def test_geometry_planes_follow_the_node_config_and_the_cache_refits_only_on_change() -> None:
    from dataclasses import replace

    from mapper.node.queries import PlaneCache, geometry_planes, with_planes
    from mapper.runtime.config import ModelRuntimeConfig

    config = ModelRuntimeConfig(device="cpu")
    pts = _box_room()
    planes = geometry_planes(pts, config)
    assert sorted(_axis_of(p) for p in planes) == [0, 1, 2]
    assert geometry_planes(pts, replace(config, surface_plane_max=0)) == []
    assert geometry_planes(pts[:100], config) == []  # fewer than surface_plane_min_points
    few = geometry_planes(pts, replace(config, surface_plane_max_points=1000))  # a subset of 1000
    assert len(few) == 3 and sum(p.inliers for p in few) <= 1000
    cache = PlaneCache()
    first = cache.planes(pts, config)
    assert cache.planes(pts.copy(), config) is first
    assert cache.planes(pts[: int(0.95 * len(pts))], config) is first  # moved by 5% <= 10%: reused
    assert cache.fits == 1
    cache.planes(pts[: int(0.85 * len(pts))], config)  # 15%: refitted
    assert cache.fits == 2
    cache.planes(pts[: int(0.85 * len(pts))], replace(config, surface_plane_inlier_m=0.05))
    assert cache.fits == 3
    every = replace(config, surface_plane_refit=0.0)
    cache.planes(pts, every)
    cache.planes(pts, every)
    assert cache.fits == 4
    cache.planes(pts[:-1], every)
    assert cache.fits == 5  # refit 0: every change of the count
    # with_planes sets only the pixels without a surface
    floor = [p for p in planes if _axis_of(p) == 2]
    surface = np.zeros((120, 160), np.float32)
    surface[:10] = 1.5
    filled, count = with_planes(surface, floor, K, _down(np.array([1.0, 1.0, 2.0])))
    assert (filled[:10] == 1.5).all() and count == int((filled[10:] > 0).sum()) > 0
    np.testing.assert_allclose(filled[10:][filled[10:] > 0], 2.0, atol=0.02)
    assert with_planes(surface, [], K, np.eye(4)) == (surface, 0)
