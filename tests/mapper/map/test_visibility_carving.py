"""Visibility carving of the global map (mapper/map/carving.py): what a depth image sees through
loses evidence and goes, a static scene streamed with depth noise keeps its surface, and points
outside the frustum or behind the measured surface are untouched. Also the parts: the box lookup
over the sorted voxel keys (mapper/map/voxels.py) and the row removal that keeps the index and the
snapshot's unit-feature blocks right."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import mapper.map.voxels as voxels
from mapper.map.carving import remove_rows, see_through_depths
from mapper.map.global_map import GlobalMapSnapshot, GlobalSemanticMap, voxel_keys
from mapper.map.window import Keyframe
from mapper.node.config import GlobalMapConfig

W, H = 64, 48
K = np.array([56.0, 56.0, 32.0, 24.0])  # about 60 x 46 degrees
WALL_Z = 4.0
BOX = (np.array([-0.4, -0.4, 1.8]), np.array([0.4, 0.4, 2.4]))  # the object, in front of the wall


def pose(x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """A camera at (x, y, 0) looking along +z, turned by ``yaw_deg`` about the world y axis."""
    a = np.deg2rad(yaw_deg)
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    m[:3, 3] = [x, y, 0.0]
    return m


def render_depth(world_from_cam: np.ndarray, with_box: bool) -> np.ndarray:
    """(H, W) z-depth of the wall z = WALL_Z and, ``with_box``, the object box in front of it."""
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    ray_cam = np.stack([(cols - K[2]) / K[0], (rows - K[3]) / K[1], np.ones_like(cols)], -1)  # z = 1
    d = ray_cam @ world_from_cam[:3, :3].T  # world direction per unit of z-depth
    o = world_from_cam[:3, 3]
    t = (WALL_Z - o[2]) / d[..., 2]
    if with_box:
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (BOX[0] - o) / d
            t1 = (BOX[1] - o) / d
        near = np.nanmax(np.minimum(t0, t1), axis=-1)
        far = np.nanmin(np.maximum(t0, t1), axis=-1)
        hit = (near <= far) & (near > 0)
        t = np.where(hit & (near < t), near, t)
    return t.astype(np.float32)


def keyframe(world_from_cam: np.ndarray, depth: np.ndarray, stamp: int) -> Keyframe:
    return Keyframe(seq=stamp, stamp_ns=stamp, camera="cam0", K=K.copy(), world_from_cam=world_from_cam,
                    rgb=np.zeros((H, W, 3), np.uint8), depth_m=depth,
                    ov=np.ones((H // 4, W // 4, 3), np.float16), ov_space="test")  # fmt: skip


NOISE = 0.02
"""Relative depth noise of the static-scene test (8 cm at the wall, against a 20 cm margin there)."""
VIEWS = [pose(0.0), pose(0.3, 0.1, 4.0), pose(-0.3, -0.1, -4.0), pose(0.15, -0.2, 2.0), pose(-0.2, 0.2, -2.0)]


def keys_of(snap: GlobalMapSnapshot) -> np.ndarray:
    assert snap.keys is not None
    return snap.keys


def in_box(xyz: np.ndarray, pad: float = 0.05) -> np.ndarray:
    return np.all((xyz >= BOX[0] - pad) & (xyz <= BOX[1] + pad), axis=1)


def stream(gmap: GlobalSemanticMap, with_box: bool, passes: int, start: int = 0,
           noise: np.random.Generator | None = None) -> int:  # fmt: skip
    stamp = start
    for _ in range(passes):
        for view in VIEWS:
            depth = render_depth(view, with_box)
            if noise is not None:
                depth = depth * (1.0 + NOISE * noise.standard_normal(depth.shape)).astype(np.float32)
            gmap.integrate(keyframe(view, depth, stamp))
            stamp += 1
    return stamp


def test_an_object_seen_through_goes_and_the_wall_behind_it_stays() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=True))
    stamp = stream(gmap, with_box=True, passes=4)
    before = gmap.snapshot()
    box_before = int(np.count_nonzero(in_box(before.xyz)))
    wall_before = keys_of(before)[before.xyz[:, 2] > WALL_Z - 0.1]
    assert box_before > 200 and wall_before.size > 1000 and gmap.points_carved == 0
    stream(gmap, with_box=False, passes=4, start=stamp)  # the same views, the object gone
    after = gmap.snapshot()
    assert int(np.count_nonzero(in_box(after.xyz))) == 0
    assert np.isin(wall_before, keys_of(after)).all()  # the wall is untouched ...
    assert np.count_nonzero(after.xyz[:, 2] > WALL_Z - 0.1) > wall_before.size  # ... and now seen behind it
    assert gmap.points_carved == gmap.stats()["global_points_carved"] >= box_before
    np.testing.assert_array_equal(np.sort(keys_of(after)), gmap._sorted_keys)  # the index follows


def test_carving_off_keeps_the_old_place() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=False))
    stamp = stream(gmap, with_box=True, passes=2)
    box_before = int(np.count_nonzero(in_box(gmap.snapshot().xyz)))
    stream(gmap, with_box=False, passes=2, start=stamp)
    assert int(np.count_nonzero(in_box(gmap.snapshot().xyz))) == box_before and gmap.points_carved == 0


def test_a_static_scene_streamed_with_depth_noise_keeps_its_surface() -> None:
    """2% depth noise (8 cm at the wall), 30 passes of the same views: every voxel the surface
    holds without carving (seen by at least 5 keyframes) is still there with it, and carving
    removes only a few stray voxels off the surface."""
    cfg = GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=True)
    carved = GlobalSemanticMap(cfg)
    kept = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=False))
    stream(carved, with_box=True, passes=30, noise=np.random.default_rng(5))
    stream(kept, with_box=True, passes=30, noise=np.random.default_rng(5))
    ref, got = kept.snapshot(), carved.snapshot()
    surface = keys_of(ref)[ref.hits >= 5]
    assert surface.size > 1000 and np.isin(surface, keys_of(got)).all()
    assert carved.points_carved <= 0.02 * len(ref)


def test_points_outside_the_frustum_or_behind_the_surface_are_untouched() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=True))
    stamp = stream(gmap, with_box=True, passes=2)
    before = gmap.snapshot()
    weight_of = dict(zip(keys_of(before).tolist(), before.weight.tolist(), strict=True))
    # a view turned 70 degrees away: the object is outside its frustum, it sees only empty space
    away = pose(0.0, 0.0, 70.0)
    gmap.integrate(keyframe(away, np.full((H, W), 3.0, np.float32), stamp))
    # a view whose depth is a surface 1 m ahead: every map point is behind it
    gmap.integrate(keyframe(pose(), np.full((H, W), 1.0, np.float32), stamp + 1))
    after = gmap.snapshot()
    assert gmap.points_carved == 0
    old = np.isin(keys_of(after), keys_of(before))
    assert old.sum() == len(before)
    np.testing.assert_array_equal(after.weight[old], [weight_of[k] for k in keys_of(after)[old].tolist()])


def test_the_margin_spares_points_on_the_surface_and_invalid_depth_carves_nothing() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=True))
    stream(gmap, with_box=False, passes=1)
    n = len(gmap)
    for k, z in enumerate((WALL_Z + 0.15, WALL_Z + 0.19)):  # 2 voxels = 0.1 m < 5% of 4.15 .. 4.19 m
        gmap.integrate(keyframe(pose(), np.full((H, W), z, np.float32), 100 + k), carve=True)
    assert gmap.points_carved == 0 and len(gmap) > n
    depth = np.full((H, W), 8.5, np.float32)  # beyond max_depth_m: no valid return, nothing carved
    gmap.integrate(keyframe(pose(), depth, 200))
    depth = np.full((H, W), np.nan, np.float32)
    gmap.integrate(keyframe(pose(), depth, 201))
    assert gmap.points_carved == 0
    # rendered depth (carve=False, as the depth-points worker passes) never carves
    for k in range(10):
        gmap.integrate(keyframe(pose(), np.full((H, W), 6.0, np.float32), 300 + k), carve=False)
    assert gmap.points_carved == 0


def test_see_through_depths_guard_edges_holes_and_the_image_border() -> None:
    depth = np.full((6, 8), 3.0, np.float32)
    depth[2, 3] = 1.0  # a near pixel: its neighbours take its depth
    depth[4, 6] = 0.0  # a hole: its neighbours carve nothing
    z = see_through_depths(depth, 0.1, 8.0)
    assert z[0].max() == z[-1].max() == z[:, 0].max() == z[:, -1].max() == 0.0  # outer rows and columns
    assert z[1:4, 2:5].max() == 1.0 and z[3:6, 5:8].max() == 0.0 and z[1, 6] == 3.0


@pytest.mark.parametrize("columns", [True, False])
def test_box_rows_finds_every_voxel_in_the_box(monkeypatch: pytest.MonkeyPatch, columns: bool) -> None:
    if not columns:  # the per-x-slab runs for boxes of many columns
        monkeypatch.setattr(voxels, "MAX_BOX_COLUMNS", 1)
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-2.0, 2.0, (5000, 3))
    keys, ok = voxel_keys(xyz, 0.1)
    keys = np.unique(keys[ok])
    order = rng.permutation(keys.size)  # rows in any order
    row_keys = keys[order]
    sorted_rows = np.argsort(row_keys, kind="stable")
    lo, hi = np.array([-0.55, -1.0, 0.2]), np.array([0.7, 0.31, 1.5])
    rows = voxels.box_rows(row_keys[sorted_rows], sorted_rows, lo, hi, 0.1)
    assert np.unique(rows).size == rows.size
    idx = np.floor(xyz / 0.1)
    in_grid_box = np.all((idx >= np.floor(lo / 0.1)) & (idx <= np.floor(hi / 0.1)), axis=1)
    inside = np.unique(voxel_keys(xyz[in_grid_box], 0.1)[0])
    found = row_keys[rows]
    assert np.isin(inside, found).all()
    if columns:
        assert np.isin(found, inside).all()  # exactly the box
    assert voxels.box_rows(np.zeros(0, np.int64), np.zeros(0, np.int64), lo, hi, 0.1).size == 0


def test_remove_rows_moves_the_last_rows_and_keeps_the_index() -> None:
    keys = np.array([50, 10, 40, 20, 30, 60, 0, 0], np.int64)  # 6 rows in use, capacity 8
    value = np.array([5.0, 1.0, 4.0, 2.0, 3.0, 6.0, 0.0, 0.0])
    order = np.argsort(keys[:6], kind="stable")
    n, holes, sorted_keys, sorted_rows = remove_rows([keys, value, None], keys, 6, np.array([1, 5, 2]),
                                                     keys[:6][order].copy(), order.astype(np.int64))
    assert n == 3 and holes.tolist() == [1, 2]
    assert sorted(keys[:3].tolist()) == [20, 30, 50] and (keys[3:] == 0).all() and (value[3:] == 0).all()
    np.testing.assert_array_equal(value[:3] * 10, keys[:3])  # rows moved whole
    np.testing.assert_array_equal(sorted_keys, [20, 30, 50])
    np.testing.assert_array_equal(keys[sorted_rows], sorted_keys)


def test_snapshot_features_after_carving_equal_a_fresh_normalisation() -> None:
    """Removed rows are refilled from the end; the unit-feature blocks a snapshot reuses from the
    one before must see those rows as changed (feature stamps)."""
    rng = np.random.default_rng(2)
    gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.05, pixel_stride=1, carve=True))
    for k, view in enumerate(VIEWS * 2):
        kf = keyframe(view, render_depth(view, True), k)
        gmap.integrate(dataclasses.replace(kf, ov=rng.standard_normal((12, 16, 3)).astype(np.float16)))
    gmap.snapshot().unit_feature_blocks()  # computed, kept for the next snapshot
    for k, view in enumerate(VIEWS * 3):
        gmap.integrate(keyframe(view, render_depth(view, False), 100 + k))
        snap = gmap.snapshot()
        assert snap.feat is not None
        fresh = snap.feat.astype(np.float32)
        fresh /= np.maximum(np.linalg.norm(fresh, axis=1, keepdims=True), 1e-12)
        np.testing.assert_allclose(snap.unit_features_f32(), fresh, atol=1e-6)
    assert gmap.points_carved > 0

def test_changed_region_is_the_depth_points_box_or_the_frustum() -> None:
    from mapper.map.carving import changed_region, frustum_box

    K = np.array([50.0, 50.0, 32.0, 24.0])
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    depth = np.full((48, 64), 2.0)
    depth[:, :8] = np.nan  # invalid pixels count nowhere
    lo, hi = changed_region(K, pose, 64, 48, depth, 0.1, 8.0, stride=1)
    assert lo[2] == pytest.approx(5.0) and hi[2] == pytest.approx(5.0)  # a wall 2 m ahead
    assert lo[0] == pytest.approx(1.0 + (8.5 - 32.0) / 50.0 * 2.0)  # from the first valid column
    lo_c, hi_c = changed_region(K, pose, 64, 48, depth, 0.1, 8.0, include_camera=True, stride=1)
    assert lo_c[2] == pytest.approx(3.0) and np.all(lo_c <= lo) and np.all(hi_c >= hi)  # the camera too
    far = np.full((48, 64), 20.0)  # beyond max_depth_m: no valid pixel -> the frustum
    for d in (None, far):
        got = changed_region(K, pose, 64, 48, d, 0.1, 8.0)
        want = frustum_box(K, pose, 64, 48, 8.0)
        np.testing.assert_allclose(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1])
