"""Tests of the global semantic point map: back-projection conventions, OV sampling, fusion,
incremental updates, the max_points bound, snapshots, persistence and thread safety."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from mapper.map.global_map import GlobalSemanticMap, voxel_keys, weighted_mean_fusion
from mapper.map.window import Keyframe
from mapper.node.config import GlobalMapConfig

W, H = 32, 24
K = np.array([30.0, 28.0, 16.0, 12.0])


def rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return m


def make_kf(
    depth: np.ndarray | None,
    *,
    world_from_cam: np.ndarray | None = None,
    ov: np.ndarray | None = None,
    stamp_ns: int = 0,
) -> Keyframe:
    h, w = (depth.shape if depth is not None else (H, W))
    return Keyframe(
        seq=stamp_ns, stamp_ns=stamp_ns, camera="cam0", K=K.copy(),
        world_from_cam=np.eye(4) if world_from_cam is None else world_from_cam,
        rgb=np.zeros((h, w, 3), np.uint8), depth_m=depth, ov=ov, ov_space="test" if ov is not None else None,
    )  # fmt: skip


def plane_depth(z_m: float = 2.0) -> np.ndarray:
    return np.full((H, W), z_m, np.float32)


def tilted_plane_depth(normal_cam: np.ndarray, offset_m: float) -> np.ndarray:
    """z-depth of the plane n . X = offset seen through every pixel centre."""
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(cols - K[2]) / K[0], (rows - K[3]) / K[1], np.ones_like(cols)], -1)  # z = 1
    return (offset_m / (rays @ normal_cam)).astype(np.float32)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_backprojection_uses_pixel_centres_k_and_pose() -> None:
    cfg = GlobalMapConfig(pixel_stride=3, grazing_power=0.0, min_weight=0.0)
    gmap = GlobalSemanticMap(cfg)
    world_from_cam = rot_z(30.0)
    world_from_cam[:3, 3] = [1.0, -2.0, 0.5]
    obs = gmap.observe(make_kf(plane_depth(2.0), world_from_cam=world_from_cam))
    assert not isinstance(obs, str)
    rows, cols = np.arange(1, H, 3), np.arange(1, W, 3)
    jj, ii = (a.ravel() for a in np.meshgrid(rows, cols, indexing="ij"))
    z = np.full(ii.shape, 2.0)
    cam = np.stack([(ii + 0.5 - K[2]) / K[0] * z, (jj + 0.5 - K[3]) / K[1] * z, z], 1)
    expected = cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    np.testing.assert_allclose(obs.xyz, expected, atol=1e-9)


def test_depth_range_and_invalid_depth_are_skipped() -> None:
    cfg = GlobalMapConfig(pixel_stride=1, min_depth_m=0.5, max_depth_m=3.0)
    depth = plane_depth(2.0)
    depth[0, :] = 0.0
    depth[1, :] = np.nan
    depth[2, :] = 5.0
    obs = GlobalSemanticMap(cfg).observe(make_kf(depth))
    assert not isinstance(obs, str) and obs.xyz.shape[0] == (H - 3) * W
    assert GlobalSemanticMap(cfg).observe(make_kf(np.zeros((H, W), np.float32))) == "no valid depth in range"


def test_weight_falls_with_distance_and_grazing_angle() -> None:
    cfg = GlobalMapConfig(pixel_stride=4, near_m=1.0, falloff_m=2.0, grazing_power=1.0, min_weight=0.0)
    gmap = GlobalSemanticMap(cfg)
    near = gmap.observe(make_kf(plane_depth(1.0)))
    far = gmap.observe(make_kf(plane_depth(4.0)))
    normal = unit(np.array([0.8, 0.0, 0.6]))
    depth = tilted_plane_depth(normal, 1.0)
    tilted = gmap.observe(make_kf(depth))
    assert not isinstance(near, str) and not isinstance(far, str) and not isinstance(tilted, str)
    # far: exp(-(d - 1) / 2) with d >= 4 m
    assert far.weight.max() <= np.exp(-1.5) + 1e-6 < near.weight.min()
    # tilted plane: weight = distance term * |cos(ray, plane normal)| (normals from the depth image);
    # where the depth changes by more than 10% between neighbours the normal counts as unknown (0.5)
    dist = np.linalg.norm(tilted.xyz, axis=1)
    cos = np.abs(tilted.xyz @ normal) / dist
    falloff = np.exp(-np.maximum(dist - 1.0, 0.0) / 2.0)
    rows, cols = np.arange(2, H, 4), np.arange(2, W, 4)
    d = depth[np.ix_(rows, cols)]
    jump = np.maximum.reduce([np.abs(depth[np.ix_(rows, cols + s)] - d) for s in (-1, 1)]
                             + [np.abs(depth[np.ix_(rows + s, cols)] - d) for s in (-1, 1)]) / d
    known = (jump <= 0.1).ravel()
    assert known.sum() > known.size // 2 and (~known).any()
    np.testing.assert_allclose(tilted.weight[known], (falloff * cos)[known], rtol=1e-4)
    np.testing.assert_allclose(tilted.weight[~known], 0.5 * falloff[~known], rtol=1e-4)
    assert cos.min() < 0.5


def test_ov_sampled_bilinearly_on_a_coarser_map() -> None:
    """ov at 1/8 resolution: left half feature e0, right half e1; fused features follow the side."""
    cfg = GlobalMapConfig(pixel_stride=1, voxel_size_m=0.02, grazing_power=0.0)
    gmap = GlobalSemanticMap(cfg)
    ov = np.zeros((H // 8, W // 8, 4), np.float16)
    ov[:, : ov.shape[1] // 2, 0] = 1.0
    ov[:, ov.shape[1] // 2:, 1] = 1.0
    gmap.integrate(make_kf(plane_depth(2.0), ov=ov))
    snap = gmap.snapshot()
    assert snap.feat is not None and snap.has_feature.all()
    feat = snap.unit_features_f32()
    left = snap.xyz[:, 0] < -0.3
    right = snap.xyz[:, 0] > 0.3
    assert left.any() and right.any()
    assert np.all(feat[left, 0] > 0.99) and np.all(feat[right, 1] > 0.99)
    # at the boundary (x = 0 in the image centre) the bilinear blend mixes both
    mid = np.abs(snap.xyz[:, 0]) < 0.05  # the pixel columns next to the image centre
    assert mid.any() and np.all(np.abs(feat[mid, 0] - feat[mid, 1]) < 0.5)


def test_weighted_mean_fusion_is_exact_running_mean() -> None:
    rng = np.random.default_rng(0)
    f1, f2 = rng.normal(size=(5, 8)).astype(np.float32), rng.normal(size=(5, 8)).astype(np.float32)
    w1, w2 = rng.uniform(0.1, 1, 5).astype(np.float32), rng.uniform(0.1, 1, 5).astype(np.float32)
    zero = np.zeros((5, 8), np.float16)
    nothing = np.zeros(5, np.float32)
    u1, n1, fw1 = weighted_mean_fusion(zero, nothing, nothing, f1 * w1[:, None], w1)
    u2, n2, fw2 = weighted_mean_fusion(u1, n1, fw1, f2 * w2[:, None], w2)
    expected = (f1 * w1[:, None] + f2 * w2[:, None]) / (w1 + w2)[:, None]
    assert u2.dtype == np.float16
    np.testing.assert_allclose(fw2, w1 + w2, rtol=1e-6)
    np.testing.assert_allclose(u2.astype(np.float32) * n2[:, None], expected, rtol=2e-3, atol=2e-3)


def test_integrate_is_incremental_and_keeps_points_of_old_frames() -> None:
    cfg = GlobalMapConfig(pixel_stride=2)
    gmap = GlobalSemanticMap(cfg)
    ov = np.ones((3, 4, 4), np.float16)
    gmap.integrate(make_kf(plane_depth(2.0), ov=ov, stamp_ns=1), map_version=1)
    first = gmap.snapshot()
    away = np.eye(4)
    away[:3, 3] = [10.0, 0.0, 0.0]  # sees a disjoint region
    stats = gmap.integrate(make_kf(plane_depth(2.0), world_from_cam=away, ov=ov, stamp_ns=2), map_version=2)
    second = gmap.snapshot()
    assert stats.voxels_new == stats.voxels_touched > 0
    assert len(second) == len(first) + stats.voxels_new and second.map_version == 2
    old = second.last_seen_ns == 1
    assert old.sum() == len(first)
    np.testing.assert_array_equal(second.xyz[old], first.xyz)  # untouched voxels unchanged
    np.testing.assert_array_equal(second.weight[old], first.weight)
    # the same view again touches the same voxels: no new ones, confidence and hits grow
    stats3 = gmap.integrate(make_kf(plane_depth(2.0), ov=ov, stamp_ns=3))
    third = gmap.snapshot()
    assert stats3.voxels_new == 0 and len(third) == len(second)
    again = third.last_seen_ns == 3
    assert np.all(third.hits[again] > second.hits[again])
    assert np.all(third.weight[again] > second.weight[again])


def test_frames_without_depth_or_ov() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2))
    stats = gmap.integrate(make_kf(None, ov=np.ones((3, 4, 4), np.float16)))
    assert stats.points == 0 and stats.skipped == "no depth" and len(gmap) == 0
    assert gmap.dim == 4  # the dimension is still learned
    gmap2 = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2))
    gmap2.integrate(make_kf(plane_depth(2.0)))  # geometry only
    snap = gmap2.snapshot()
    assert len(snap) > 0 and snap.feat is None and not snap.has_feature.any()
    gmap2.integrate(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 4), np.float16)))  # now with features
    snap = gmap2.snapshot()
    assert snap.feat is not None and snap.has_feature.all()
    assert np.all(snap.feat_weight < snap.weight)  # the geometry-only observation counted for confidence only
    with pytest.raises(ValueError, match="dimension 5"):
        gmap2.integrate(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 5), np.float16)))


def test_max_points_drops_least_recently_seen_voxels_first() -> None:
    cfg = GlobalMapConfig(pixel_stride=1, voxel_size_m=0.02, max_points=400, prune_to_fraction=0.5,
                          stale_half_life_keyframes=1.0, paging=False)  # fmt: skip
    gmap = GlobalSemanticMap(cfg)
    first = gmap.integrate(make_kf(plane_depth(2.0), stamp_ns=1))
    assert first.voxels_pruned > 0 and len(gmap) == 200
    away = np.eye(4)
    away[:3, 3] = [10.0, 0.0, 0.0]
    for stamp in (2, 3, 4):
        gmap.integrate(make_kf(plane_depth(2.0), world_from_cam=away, stamp_ns=stamp))
    snap = gmap.snapshot()
    assert len(snap) <= cfg.max_points and gmap.points_pruned > 0
    assert np.all(snap.xyz[:, 0] > 5.0)  # only the recently seen region survives
    assert gmap.stats()["global_points"] == len(snap)
    assert gmap.nbytes > 0 and gmap.allocated_bytes >= gmap.nbytes


def test_snapshot_is_immutable_and_cached_per_version() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2))
    gmap.integrate(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 4), np.float16)))
    snap = gmap.snapshot()
    assert gmap.snapshot() is snap  # same version: shared
    assert snap.unit_features_f32() is snap.unit_features_f32()
    with pytest.raises(ValueError):
        snap.xyz[0, 0] = 1.0
    xyz = snap.xyz.copy()
    gmap.integrate(make_kf(plane_depth(3.0), ov=np.ones((3, 4, 4), np.float16)))
    np.testing.assert_array_equal(snap.xyz, xyz)
    assert gmap.snapshot() is not snap and len(gmap.snapshot()) > len(snap)


def test_geometry_is_the_snapshots_points_and_keys_read_only() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2))
    xyz, keys = gmap.geometry()
    assert xyz.shape == (0, 3) and keys.shape == (0,)
    gmap.integrate(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 4), np.float16)))
    xyz, keys = gmap.geometry()  # no snapshot taken yet: copies of the points and keys
    snap = gmap.snapshot()
    assert snap.keys is not None
    np.testing.assert_array_equal(xyz, snap.xyz)
    np.testing.assert_array_equal(keys, snap.keys)
    with pytest.raises(ValueError):
        xyz[0, 0] = 1.0
    with pytest.raises(ValueError):
        keys[0] = 1
    again = gmap.geometry()  # the same version, snapshot cached: shares its arrays
    assert again[0] is snap.xyz and again[1] is snap.keys
    gmap.integrate(make_kf(plane_depth(3.0), ov=np.ones((3, 4, 4), np.float16)))
    later_xyz, later_keys = gmap.geometry()
    assert later_xyz.shape[0] == later_keys.shape[0] > snap.xyz.shape[0]
    np.testing.assert_array_equal(xyz, snap.xyz)  # earlier copies do not change


def test_save_restore_roundtrip_and_rekey() -> None:
    cfg = GlobalMapConfig(pixel_stride=2)
    gmap = GlobalSemanticMap(cfg)
    gmap.integrate(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 4), np.float16), stamp_ns=7), map_version=3)
    gmap.integrate(make_kf(plane_depth(1.5)), map_version=4)
    arrays, manifest = gmap.to_arrays()
    assert all(isinstance(a, np.ndarray) and a.dtype != object for a in arrays.values())
    other = GlobalSemanticMap(cfg)
    other.restore(arrays, manifest, map_version=9)
    a, b = gmap.snapshot(), other.snapshot()
    assert b.map_version == 9 and len(a) == len(b)
    order_a, order_b = np.lexsort(a.xyz.T), np.lexsort(b.xyz.T)
    np.testing.assert_array_equal(a.xyz[order_a], b.xyz[order_b])
    assert a.feat is not None and b.feat is not None
    np.testing.assert_array_equal(a.feat[order_a], b.feat[order_b])
    np.testing.assert_array_equal(a.weight[order_a], b.weight[order_b])
    # a coarser voxel size merges voxels on restore; the most confident one is kept
    coarse = GlobalSemanticMap(dataclasses.replace(cfg, voxel_size_m=0.2))
    coarse.restore(arrays, manifest, map_version=1)
    keys, _ = voxel_keys(a.xyz, 0.2)
    assert len(coarse) == np.unique(keys).size < len(a)


@pytest.mark.parametrize(
    "damage, fragment",
    [
        (lambda arr, man: arr.pop("global.xyz"), "xyz must be float32"),
        (lambda arr, man: arr.__setitem__("global.hits", arr["global.hits"].astype(np.float64)), "hits"),
        (lambda arr, man: man.__setitem__("format", "other"), "unknown format"),
        (lambda arr, man: man.__setitem__("points", "3"), "'points' must be"),
        (lambda arr, man: arr["global.xyz"].__setitem__((0, 0), np.nan), "finite"),
    ],
)
def test_restore_rejects_damaged_sections_and_changes_nothing(damage, fragment: str) -> None:  # noqa: ANN001
    cfg = GlobalMapConfig(pixel_stride=2)
    src = GlobalSemanticMap(cfg)
    src.integrate(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 4), np.float16)))
    arrays, manifest = src.to_arrays()
    damage(arrays, manifest)
    target = GlobalSemanticMap(cfg)
    target.integrate(make_kf(plane_depth(1.0)))
    before = target.snapshot()
    with pytest.raises(ValueError, match=fragment):
        target.restore(arrays, manifest, map_version=1)
    assert target.snapshot() is before


def test_concurrent_integrate_and_snapshots_are_consistent() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, voxel_size_m=0.03))
    errors: list[str] = []
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            snap = gmap.snapshot()
            n = len(snap)
            if snap.feat is not None and snap.feat.shape[0] != n or snap.weight.shape[0] != n:
                errors.append("inconsistent snapshot")
            if n and not np.isfinite(snap.unit_features_f32()).all():
                errors.append("non-finite features")

    thread = threading.Thread(target=reader)
    thread.start()
    try:
        for k in range(12):
            pose = rot_z(15.0 * k)
            gmap.integrate(make_kf(plane_depth(1.0 + 0.1 * k), world_from_cam=pose,
                                   ov=np.ones((3, 4, 4), np.float16), stamp_ns=k))  # fmt: skip
    finally:
        stop.set()
        thread.join()
    assert not errors and gmap.keyframes_integrated == 12


def _geometry(snap) -> tuple[np.ndarray, ...]:  # noqa: ANN001
    return snap.xyz, snap.weight, snap.hits, snap.last_seen_ns


def test_integrate_features_adds_features_without_geometry_weight() -> None:
    """Geometry-only integrates followed by integrate_features give the combined integrate's map:
    the same geometry (weight, hits, positions: nothing counted twice) and the same features.
    Without carving: a see-through scales the feature weight a voxel has at that moment, so
    features that arrive later escape the see-throughs in between (mapper.map.carving)."""
    cfg = GlobalMapConfig(voxel_size_m=0.1, pixel_stride=2, min_weight=0.0, carve=False)
    rng = np.random.default_rng(3)
    poses = [rot_z(0.0), rot_z(12.0), rot_z(-8.0)]
    for i, pose in enumerate(poses):
        pose[:3, 3] = [0.1 * i, -0.05 * i, 0.0]
    depths = [tilted_plane_depth(unit(np.array([0.1 * i, -0.2, 1.0])), 2.0 + 0.2 * i) for i in range(3)]
    ovs = [rng.standard_normal((6, 8, 5)).astype(np.float16) for _ in range(3)]
    with_ov = [make_kf(d, world_from_cam=p, ov=o, stamp_ns=i)
               for i, (d, p, o) in enumerate(zip(depths, poses, ovs, strict=True))]  # fmt: skip
    combined = GlobalSemanticMap(cfg)
    for kf in with_ov:
        combined.integrate(kf)
    late = GlobalSemanticMap(cfg)
    late.integrate(with_ov[0])  # the first frame carried ov, the other two did not
    for kf in with_ov[1:]:
        late.integrate(dataclasses.replace(kf, ov=None, ov_space=None))
    geometry_only = late.snapshot()
    assert geometry_only.n_with_features < len(geometry_only)
    for kf in with_ov[1:]:
        stats = late.integrate_features(kf, map_version=7)
        assert stats.points > 0 and stats.voxels_new == 0 and stats.with_features and stats.skipped is None
    got, ref = late.snapshot(), combined.snapshot()
    for a, b, c in zip(_geometry(got), _geometry(geometry_only), _geometry(ref), strict=True):
        np.testing.assert_array_equal(a, b)  # features-only: geometry untouched
        np.testing.assert_array_equal(a, c)  # and the same as the combined integrate
    assert got.feat is not None and ref.feat is not None
    np.testing.assert_array_equal(got.feat, ref.feat)
    np.testing.assert_array_equal(got.feat_weight, ref.feat_weight)
    assert got.map_version == 7 and late.keyframes_integrated == 3 and late._kf_counter == 3


def test_integrate_features_skips_voxels_not_in_the_map_and_refuses_bad_input() -> None:
    cfg = GlobalMapConfig(voxel_size_m=0.1, pixel_stride=2, min_weight=0.0)
    ov = np.ones((3, 4, 4), np.float32)
    gmap = GlobalSemanticMap(cfg)
    gmap.integrate(make_kf(plane_depth(2.0)))
    moved = np.eye(4)
    moved[:3, 3] = [50.0, 0.0, 0.0]
    far = make_kf(plane_depth(2.0), world_from_cam=moved, ov=ov)  # its voxels are not in the map
    stats = gmap.integrate_features(far)
    assert stats.points == 0 and stats.skipped == "none of its voxels is in the map any more"
    assert gmap.snapshot().n_with_features == 0 and len(gmap) > 0
    before = gmap.snapshot()
    with pytest.raises(ValueError, match="needs ov"):
        gmap.integrate_features(make_kf(plane_depth(2.0)))
    gmap.integrate_features(make_kf(plane_depth(2.0), ov=ov))
    with pytest.raises(ValueError, match="dimension 6 differs"):
        gmap.integrate_features(make_kf(plane_depth(2.0), ov=np.ones((3, 4, 6), np.float32)))
    after = gmap.snapshot()
    np.testing.assert_array_equal(after.weight, before.weight)
    assert after.n_with_features == len(after) and after.feat is not None and after.feat.shape[1] == 4
    assert gmap.integrate_features(make_kf(None, ov=ov)).skipped == "no depth"


def test_a_large_frame_fuses_at_a_coarser_stride_within_max_observed_pixels() -> None:
    """global_map.max_observed_pixels: the stride grows with the frame (ceil(sqrt(H W / max))), so a
    keyframe never fuses more pixels than that; a small frame keeps pixel_stride; an explicit
    pixel_stride is used as given."""
    from mapper.map.global_map import Observations, observe_keyframe

    cfg = GlobalMapConfig(pixel_stride=2, max_observed_pixels=100, grazing_power=0.0, min_weight=0.0)
    small = observe_keyframe(cfg, make_kf(plane_depth()))  # 32 x 24 = 768 pixels: stride 3 (ceil 2.77)
    big = observe_keyframe(cfg, make_kf(np.full((4 * H, 4 * W), 2.0, np.float32)))  # stride 12 (ceil 11.09)
    assert isinstance(small, Observations) and isinstance(big, Observations)
    assert len(small.xyz) == len(range(1, H, 3)) * len(range(1, W, 3)) <= 100
    assert len(big.xyz) == len(range(6, 4 * H, 12)) * len(range(6, 4 * W, 12)) <= 100
    loose = dataclasses.replace(cfg, max_observed_pixels=10_000)
    kept = observe_keyframe(loose, make_kf(plane_depth()))
    assert isinstance(kept, Observations) and len(kept.xyz) == (H // 2) * (W // 2)  # pixel_stride 2
    given = observe_keyframe(cfg, make_kf(plane_depth()), pixel_stride=1)
    assert isinstance(given, Observations) and len(given.xyz) == H * W
