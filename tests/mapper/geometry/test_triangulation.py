"""Sparse geometry from posed RGB (mapper.geometry.triangulation) and its node plugin
(mapper.node.workers.triangulation): exact two-view answers, degenerate cases (pure rotation,
parallel rays, points behind a camera), a rendered textured plane, the plugin's queue, budget,
global-map points and view ranges, and the runtime's bounds that follow those ranges."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from mapper.geometry.config import TriangulationConfig
from mapper.geometry.pose_refine import perturbed, pose_change
from mapper.geometry.triangulation import (
    FeatureExtractor,
    PosedView,
    SparsePoints,
    fundamental_from_poses,
    match_pair,
    photo_consistent,
    project,
    select_partners,
    triangulate_keyframe,
    triangulate_pair,
)
from mapper.map.global_map import GlobalSemanticMap
from mapper.node.config import ConfigError, config_from_dict
from mapper.node.service import MapperNode
from mapper.node.workers import triangulation as triangulation_plugin
from mapper.node.workers.triangulation import SparseTriangulation, keyframe_key
from protocol.messages import Frame, Load, Ok, Save, Status, StatusRequest, decode, encode

ROOT = Path(__file__).resolve().parents[3]
K = np.array([100.0, 100.0, 80.0, 60.0])
W, H = 160, 120


def pose(R: np.ndarray, center: tuple[float, float, float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = center
    return out


def rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def view(world_from_cam: np.ndarray) -> PosedView:
    return PosedView(K, world_from_cam, W, H)


def random_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-1.0, 1.0, n), rng.uniform(-0.7, 0.7, n), rng.uniform(2.0, 5.0, n)])


# ---- exact two-view answers ------------------------------------------------------------------------
def test_fundamental_from_poses_satisfies_the_epipolar_constraint_exactly() -> None:
    a, b = view(pose(np.eye(3), (0, 0, 0))), view(pose(rot_y(-8.0), (0.4, 0.05, -0.1)))
    xyz = random_points(50)
    uv_a, uv_b = project(a.K, a.world_from_cam, xyz)[0], project(b.K, b.world_from_cam, xyz)[0]
    F = fundamental_from_poses(a, b)
    xa = np.column_stack([uv_a, np.ones(50)])
    xb = np.column_stack([uv_b, np.ones(50)])
    residual = np.abs(np.sum(xb * (xa @ F.T), axis=1)) / np.linalg.norm(F)
    assert residual.max() < 1e-12
    # a wrong pixel is not on its epipolar line
    assert abs(float((xb[0] + [3.0, 0.0, 0.0]) @ F @ xa[0])) > 1e-6


def test_two_views_recover_known_points_in_float64() -> None:
    a, b = view(pose(np.eye(3), (0, 0, 0))), view(pose(rot_y(-10.0), (0.5, 0.0, 0.1)))
    xyz = random_points(40, seed=1)
    uv_a, uv_b = project(a.K, a.world_from_cam, xyz)[0], project(b.K, b.world_from_cam, xyz)[0]
    pts = triangulate_pair(a, b, uv_a, uv_b, TriangulationConfig(max_sigma_m=1.0))
    np.testing.assert_array_equal(pts.index, np.arange(40))
    np.testing.assert_allclose(pts.xyz, xyz, atol=1e-9)
    assert pts.reprojection_px.max() < 1e-8
    # parallax: the angle between the rays from both centres, computed independently
    ra, rb = xyz - a.center, xyz - b.center
    cos = np.sum(ra * rb, 1) / np.linalg.norm(ra, axis=1) / np.linalg.norm(rb, axis=1)
    expected = np.degrees(np.arccos(cos))
    np.testing.assert_allclose(pts.parallax_deg, expected, atol=1e-9)
    # uncertainty: range * (pixel sigma / f) / sin(parallax), larger for farther points
    rng_m = np.maximum(np.linalg.norm(ra, axis=1), np.linalg.norm(rb, axis=1))
    np.testing.assert_allclose(pts.sigma_m, rng_m * (0.5 / 100.0) / np.sin(np.radians(expected)), rtol=1e-9)


def test_pure_rotation_gives_no_partner_no_match_and_no_point() -> None:
    a, b = view(pose(np.eye(3), (1.0, 2.0, 0.5))), view(pose(rot_y(15.0), (1.0, 2.0, 0.5)))
    cfg = TriangulationConfig()
    assert select_partners(a, [b], cfg) == []
    assert not np.any(fundamental_from_poses(a, b))
    xyz = random_points(30) + [1.0, 2.0, 0.5]
    uv_a, uv_b = project(a.K, a.world_from_cam, xyz)[0], project(b.K, b.world_from_cam, xyz)[0]
    assert len(triangulate_pair(a, b, uv_a, uv_b, cfg)) == 0  # rays meet only at the centre
    rng = np.random.default_rng(0)
    image = (rng.uniform(0, 255, (H, W, 3))).astype(np.uint8)
    ex = FeatureExtractor(cfg)
    f = ex.detect(image)
    assert len(f) > 10 and len(match_pair(ex, a, f, b, f, cfg)) == 0


def test_near_parallel_rays_are_rejected_by_the_parallax_check() -> None:
    a, b = view(pose(np.eye(3), (0, 0, 0))), view(pose(np.eye(3), (0.1, 0.0, 0.0)))
    xyz = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 20.0], [0.3, 0.1, 40.0]])  # 2.9, 0.29, 0.14 degrees
    uv_a, uv_b = project(a.K, a.world_from_cam, xyz)[0], project(b.K, b.world_from_cam, xyz)[0]
    cfg = TriangulationConfig(max_sigma_m=1e3, max_depth_m=1e3, min_parallax_deg=1.0)
    pts = triangulate_pair(a, b, uv_a, uv_b, cfg)
    np.testing.assert_array_equal(pts.index, [0])
    assert len(triangulate_pair(a, b, uv_a, uv_b, TriangulationConfig(max_sigma_m=1e3, max_depth_m=1e3,
                                                                      min_parallax_deg=0.1))) == 3


def test_points_behind_a_camera_are_rejected() -> None:
    a, b = view(pose(np.eye(3), (0, 0, 0))), view(pose(np.eye(3), (0.5, 0.0, 0.0)))
    cfg = TriangulationConfig(max_sigma_m=1.0)
    front, behind = np.array([[0.1, 0.1, 3.0]]), np.array([[0.1, 0.1, -3.0]])
    for xyz, kept in ((front, 1), (behind, 0)):
        uv_a, uv_b = project(a.K, a.world_from_cam, xyz)[0], project(b.K, b.world_from_cam, xyz)[0]
        assert len(triangulate_pair(a, b, uv_a, uv_b, cfg)) == kept
    # in front of a, behind b (b turned around)
    c = view(pose(rot_y(180.0), (0.5, 0.0, 0.0)))
    uv_a, uv_c = project(a.K, a.world_from_cam, front)[0], project(c.K, c.world_from_cam, front)[0]
    assert len(triangulate_pair(a, c, uv_a, uv_c, cfg)) == 0


def test_bad_correspondences_fail_the_reprojection_check() -> None:
    a, b = view(pose(np.eye(3), (0, 0, 0))), view(pose(np.eye(3), (0.5, 0.0, 0.0)))
    xyz = random_points(20, seed=3)
    uv_a, uv_b = project(a.K, a.world_from_cam, xyz)[0], project(b.K, b.world_from_cam, xyz)[0]
    uv_b[:10, 1] += 6.0  # off the epipolar line: no point can reproject onto both
    pts = triangulate_pair(a, b, uv_a, uv_b, TriangulationConfig(max_sigma_m=1.0))
    np.testing.assert_array_equal(pts.index, np.arange(10, 20))
    with pytest.raises(ValueError, match="same shape"):
        triangulate_pair(a, b, uv_a, uv_b[:3], TriangulationConfig())


def test_partners_need_overlap_and_baseline_and_rank_wider_baselines_first() -> None:
    new = view(pose(np.eye(3), (0, 0, 0)))
    near = view(pose(np.eye(3), (0.02, 0, 0)))  # below min_baseline_m
    small = view(pose(np.eye(3), (0.15, 0, 0)))
    wide = view(pose(np.eye(3), (0.6, 0, 0)))
    away = view(pose(rot_y(180.0), (0.3, 0, 0)))  # looks the other way: no overlap
    cfg = TriangulationConfig(max_partners=2)
    assert select_partners(new, [near, small, away, wide], cfg) == [3, 1]
    assert select_partners(new, [near, away], cfg) == []


# ---- a rendered textured plane ---------------------------------------------------------------------
PLANE_Z = 3.0


def plane_depth(world_from_cam: np.ndarray) -> np.ndarray:
    """(H, W) true z-depth of the plane z = PLANE_Z in the view."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - K[2]) / K[0], (v - K[3]) / K[1], np.ones_like(u)], axis=-1)
    rays = rays @ world_from_cam[:3, :3].T  # camera z = 1: the ray parameter is the z-depth
    return (PLANE_Z - world_from_cam[2, 3]) / rays[..., 2]


def render_plane(world_from_cam: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the plane z = PLANE_Z textured over x, y in [-3, 3] m (bilinear)."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([(u - K[2]) / K[0], (v - K[3]) / K[1], np.ones_like(u)], axis=-1)
    rays = rays @ world_from_cam[:3, :3].T
    c = world_from_cam[:3, 3]
    t = (PLANE_Z - c[2]) / rays[..., 2]
    hit = c + t[..., None] * rays
    size = texture.shape[0]
    mx = ((hit[..., 0] + 3.0) / 6.0 * size - 0.5).astype(np.float32)
    my = ((hit[..., 1] + 3.0) / 6.0 * size - 0.5).astype(np.float32)
    gray = cv2.remap(texture, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.repeat(gray[..., None], 3, axis=2)


def make_texture() -> np.ndarray:
    """(1024, 1024) uint8 smooth random texture of the plane (also used by test_plane_sweep.py)."""
    rng = np.random.default_rng(7)
    noise = rng.uniform(0, 255, (96, 96)).astype(np.float32)
    return cv2.resize(noise, (1024, 1024), interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return make_texture()


PLANE_POSES = [pose(rot_y(deg), (x, 0.05 * i, 0.0)) for i, (x, deg) in enumerate([(0.0, 0.0), (0.35, -3.0),
                                                                                 (-0.3, 4.0), (0.7, -6.0)])]


def test_rendered_plane_is_triangulated_onto_the_plane(texture: np.ndarray) -> None:
    cfg = TriangulationConfig()
    ex = FeatureExtractor(cfg)
    views = [view(p) for p in PLANE_POSES]
    feats = [ex.detect(render_plane(p, texture)) for p in PLANE_POSES]
    partners = select_partners(views[3], views[:3], cfg)
    assert sorted(partners) == [0, 1, 2]
    pts = triangulate_keyframe(ex, views[3], feats[3], [(views[i], feats[i]) for i in partners], cfg)
    assert pts.partners == 3 and pts.matches >= len(pts) > 50
    err = np.abs(pts.xyz[:, 2] - PLANE_Z)
    assert np.median(err) < 0.01 and np.quantile(err, 0.95) < 0.05
    assert (pts.n_views >= cfg.min_views).all() and (pts.sigma_m <= cfg.max_sigma_m).all()
    # the depth and pixel reported are those of the new view
    uv, z = project(K, PLANE_POSES[3], pts.xyz)
    np.testing.assert_allclose(z, pts.depth_m, atol=1e-12)
    assert np.abs(uv - pts.uv).max() <= cfg.max_reprojection_px


def test_photometric_check_accepts_the_true_depth_and_rejects_a_wrong_one(texture: np.ndarray) -> None:
    cfg = TriangulationConfig()
    a, b = view(PLANE_POSES[0]), view(PLANE_POSES[1])
    ga = cv2.cvtColor(render_plane(PLANE_POSES[0], texture), cv2.COLOR_RGB2GRAY).astype(np.float32)
    gb = cv2.cvtColor(render_plane(PLANE_POSES[1], texture), cv2.COLOR_RGB2GRAY).astype(np.float32)
    uv = np.array([[60.5, 50.5], [100.5, 70.5], [80.5, 30.5]])
    assert photo_consistent(a, ga, b, gb, uv, np.full(3, PLANE_Z), cfg).all()
    assert not photo_consistent(a, ga, b, gb, uv, np.full(3, 1.7), cfg).any()


def test_photometric_check_on_images_kept_smaller_than_sent(texture: np.ndarray) -> None:
    """The same check on 4x larger views whose photometric images were kept at half their size
    (``Features.gray_scale``): the same verdicts as on the small images."""
    cfg = TriangulationConfig(detect_max_side=2 * max(W, H))
    ex = FeatureExtractor(cfg)
    big = [cv2.resize(render_plane(p, texture), (4 * W, 4 * H), interpolation=cv2.INTER_CUBIC)
           for p in PLANE_POSES[:2]]  # fmt: skip
    fa, fb = ex.detect(big[0]), ex.detect(big[1])
    assert fa.gray is not None and fb.gray is not None and fa.gray_scale == (0.5, 0.5)
    a, b = (PosedView(K * 4.0, PLANE_POSES[i], 4 * W, 4 * H) for i in (0, 1))
    uv = np.array([[60.5, 50.5], [100.5, 70.5], [80.5, 30.5]]) * 4.0
    kw = {"scale_a": fa.gray_scale, "scale_b": fb.gray_scale}
    assert photo_consistent(a, fa.gray, b, fb.gray, uv, np.full(3, PLANE_Z), cfg, **kw).all()
    assert not photo_consistent(a, fa.gray, b, fb.gray, uv, np.full(3, 1.7), cfg, **kw).any()


def test_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="triangulation.detector"):
        config_from_dict({"triangulation": {"detector": "surf"}})
    with pytest.raises(ConfigError, match="triangulation.ncc_patch_px"):
        config_from_dict({"triangulation": {"ncc_patch_px": 6}})
    with pytest.raises(ConfigError, match="probe_far_m"):
        config_from_dict({"triangulation": {"probe_near_m": 3.0, "probe_far_m": 2.0}})
    assert config_from_dict({"triangulation": {"detector": "orb"}}).triangulation.detector == "orb"


def test_orb_detector_also_triangulates_the_plane(texture: np.ndarray) -> None:
    cfg = TriangulationConfig(detector="orb", min_views=2)
    ex = FeatureExtractor(cfg)
    views = [view(p) for p in PLANE_POSES[2:]]  # 1 m apart: 19 degrees of parallax on the plane
    feats = [ex.detect(render_plane(p, texture)) for p in PLANE_POSES[2:]]
    assert feats[0].descriptors.dtype == np.uint8
    pts = triangulate_keyframe(ex, views[1], feats[1], [(views[0], feats[0])], cfg)
    assert len(pts) > 10 and np.median(np.abs(pts.xyz[:, 2] - PLANE_Z)) < 0.03


def test_geometry_module_loads_without_torch() -> None:
    code = ("import sys, mapper.geometry.triangulation, mapper.geometry.plane_sweep, "
            "mapper.node.workers.triangulation\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


# ---- the node plugin ---------------------------------------------------------------------------
class ExtentSink:
    def __init__(self) -> None:
        self.extents: dict[tuple[str, int, int], np.ndarray | None] = {}
        self.priors: dict[tuple[str, int, int], np.ndarray | None] = {}

    def set_view_depth_prior(self, key: tuple[str, int, int], depth_m: np.ndarray | None) -> None:
        self.priors[key] = depth_m

    def set_view_extent(self, key: tuple[str, int, int], points_m: np.ndarray | None) -> None:
        self.extents[key] = points_m


def plane_frame(i: int, texture: np.ndarray, depth: bool = False, ov: bool = True) -> Frame:
    p = PLANE_POSES[i]
    rgb = render_plane(p, texture)
    feats = np.full((H // 8, W // 8, 4), 0.5, np.float16) if ov else None
    return Frame(seq=i, stamp_ns=1000 + i, width=W, height=H, K=K.copy(), world_from_cam=p.copy(), rgb=rgb,
                 depth_m=np.full((H, W), PLANE_Z, np.float32) if depth else None, ov=feats,
                 ov_space="test-space" if ov else None)


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    config = config_from_dict({
        "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False, "serve_model": False,
        "window": {"max_keyframes": 8, "min_translation_m": 0.05},
        "global_map": {"min_weight": 0.0, "rendered_depth": False},
        "triangulation": {"max_pending": 3},
    })
    mapper = MapperNode(config)
    yield mapper
    mapper.stop()


def test_plugin_triangulates_rgb_only_keyframes_off_the_ack_path(
    node: MapperNode, texture: np.ndarray
) -> None:
    sink = ExtentSink()
    tri = SparseTriangulation(node.ctx, runtime=sink)
    tri.install()
    assert "triangulation" in node.ctx.status_providers
    assert any(n == "triangulation" for n, _ in node.ctx.workers)
    node.handle_ingest(encode(plane_frame(0, texture, depth=True)))  # with depth: a candidate only
    for i in (1, 2, 3):
        node.handle_ingest(encode(plane_frame(i, texture)))
    assert tri.pending == 3 and tri.processed == 0  # the ack did not wait
    assert tri.process_pending() == 3
    stats = tri.stats()
    assert stats["keyframes"] == 3 and stats["points"] == len(tri.points()[0]) > 0
    assert stats["points_per_keyframe"] > 0 and stats["mean_ms"] > 0 and stats["failed"] == 0
    xyz, sigma = tri.points()
    assert np.median(np.abs(xyz[:, 2] - PLANE_Z)) < 0.02 and (sigma > 0).all()
    # the keyframe's extent for the volume bounds: its points
    last = tri.keyframe_points(plane_frame(3, texture))
    assert last is not None and len(last) >= tri.config.bounds_min_points
    counts = {keyframe_key(plane_frame(i, texture)): len(tri.keyframe_points(plane_frame(i, texture)) or ())
              for i in (1, 2, 3)}
    assert set(sink.extents) == set(counts)  # every RGB-only keyframe, once some depth is known
    np.testing.assert_array_equal(sink.extents[keyframe_key(plane_frame(3, texture))], last.xyz)
    room_depths = [np.quantile(tri.keyframe_points(plane_frame(i, texture)).depth_m, 0.9)  # type: ignore[union-attr]
                   for i in (1, 2, 3) if counts[keyframe_key(plane_frame(i, texture))] >= 12]
    for i in (1, 2, 3):
        key = keyframe_key(plane_frame(i, texture))
        if counts[key] < tri.config.bounds_min_points:  # too few points: the frustum to the room's depth
            ext = sink.extents[key]
            assert ext is not None and ext.shape == (200, 3)
            z = project(K, PLANE_POSES[i], ext)[1]
            assert z.max() == pytest.approx(np.median(room_depths))
    # the sparse depth prior: the points' depths on discs of radius 2 px around their pixels, 0 elsewhere
    prior = sink.priors[keyframe_key(plane_frame(3, texture))]
    assert prior is not None and prior.shape == (H, W)
    cols, rows = np.floor(last.uv).astype(int).T
    np.testing.assert_allclose(prior[rows, cols], last.depth_m, atol=0.05)  # max of overlapping discs
    on = prior > 0
    assert np.abs(prior[on] - plane_depth(PLANE_POSES[3])[on]).max() < 0.1
    assert 0.002 < on.mean() <= 13 * len(last) / (H * W)  # at most a 13-pixel disc per point
    # the global map gained points on the plane (with the keyframes' features)
    snap = node.state.global_map.snapshot()
    assert stats["global_map_points"] > 0 and snap.xyz.shape[0] > 0
    assert np.median(np.abs(snap.xyz[:, 2] - PLANE_Z)) < 0.03


def test_plugin_queue_is_bounded(node: MapperNode, texture: np.ndarray) -> None:
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(max_pending=2))
    tri.install()
    for i in range(4):
        node.handle_ingest(encode(plane_frame(i, texture)))
    assert tri.pending == 2 and tri.stats()["dropped"] == 2  # the oldest dropped, counted
    assert tri.process_pending() == 2 and tri.pending == 0


def test_plugin_point_budget_drops_the_oldest_keyframes_points(node: MapperNode, texture: np.ndarray) -> None:
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(max_points=30, min_views=2))
    tri.install()
    node.handle_ingest(encode(plane_frame(0, texture, depth=True)))
    for i in (1, 2, 3):
        node.handle_ingest(encode(plane_frame(i, texture)))
        tri.process_pending()
    counts = [len(tri.keyframe_points(plane_frame(i, texture)) or ()) for i in (1, 2, 3)]
    stats = tri.stats()
    assert stats["points_evicted"] > 0 and stats["points"] == sum(counts) == len(tri.points()[0])
    assert counts[2] > 0 and (stats["points"] <= 30 or counts[:2] == [0, 0])  # the newest always stays
    assert tri.keyframe_points(plane_frame(1, texture)) is None  # the oldest went first


def test_disabled_triangulation_queues_nothing(node: MapperNode, texture: np.ndarray) -> None:
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(enabled=False))
    tri.install()
    node.handle_ingest(encode(plane_frame(1, texture)))
    assert tri.pending == 0 and tri.process_pending() == 0


def test_keyframes_without_enough_points_get_the_frustum_to_the_rooms_depth(node: MapperNode) -> None:
    sink = ExtentSink()
    tri = SparseTriangulation(node.ctx, runtime=sink)
    assert tri._extents is not None
    a, b, c = (view(pose(np.eye(3), (x, 0.0, 0.0))) for x in (0.0, 0.3, 0.6))
    tri._extents.set(("cam0", 0, 0), a, SparsePoints.empty())  # nothing known yet: waits
    assert sink.extents == {}
    xyz = random_points(20, seed=4)
    uv, z = project(K, b.world_from_cam, xyz)
    ones = np.ones(20)
    pts = SparsePoints(xyz, 0.01 * ones, 5.0 * ones, 0.0 * ones, np.full(20, 3, np.int32), uv, z)
    tri._extents.set(("cam0", 1, 1), b, pts)
    np.testing.assert_array_equal(sink.extents[("cam0", 1, 1)], xyz)
    far = np.quantile(z, 0.9)
    waited = sink.extents[("cam0", 0, 0)]  # the waiting keyframe got the room's depth
    assert waited is not None and project(K, a.world_from_cam, waited)[1].max() == pytest.approx(far)
    tri._extents.set(("cam0", 2, 2), c, SparsePoints.empty())
    later = sink.extents[("cam0", 2, 2)]
    assert later is not None and project(K, c.world_from_cam, later)[1].max() == pytest.approx(far)


def test_a_new_global_map_clears_the_candidates_and_the_sparse_map(
    node: MapperNode, texture: np.ndarray
) -> None:
    tri = SparseTriangulation(node.ctx)
    tri.install()
    for i in (0, 1, 2):
        node.handle_ingest(encode(plane_frame(i, texture)))
    tri.process_pending()
    assert tri.stats()["memory_bytes"] > 0 and len(tri._candidates) == 3
    node.state.global_map = GlobalSemanticMap(node.config.global_map)  # what a map load does
    node.handle_ingest(encode(plane_frame(3, texture)))
    tri.process_pending()
    assert len(tri._candidates) == 1 and tri.points()[0].shape == (0, 3)  # no partner from the old map
    assert tri.keyframe_points(plane_frame(2, texture)) is None


def _query(node: MapperNode, msg: Save | Load | StatusRequest) -> Status | Ok:
    reply = decode(node.handle_query(encode(msg)), direction="reply")
    assert isinstance(reply, Status | Ok), reply
    return reply


def test_a_map_load_drops_the_replaced_maps_candidates_and_points_at_once(
    node: MapperNode, texture: np.ndarray
) -> None:
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(max_pending=8))
    tri.install()
    node.handle_ingest(encode(plane_frame(0, texture, depth=True)))
    for i in (1, 2):
        node.handle_ingest(encode(plane_frame(i, texture)))
    assert tri.process_pending() == 2 and len(tri.points()[0]) > 0
    before = {i: tri.keyframe_points(plane_frame(i, texture)) for i in (1, 2)}
    saved = _query(node, StatusRequest())
    assert isinstance(saved, Status) and isinstance(_query(node, Save(name="m")), Ok)
    node.handle_ingest(encode(plane_frame(3, texture)))  # acked before the load, still queued
    assert tri.pending == 1 and tri.stats()["memory_bytes"] > 0
    assert isinstance(_query(node, Load(name="m")), Ok)
    # no worker ran since the load: nothing of the replaced map is held or reported any more
    stats = tri.stats()
    assert stats["memory_bytes"] == 0 and stats["points"] == 0 and len(tri._candidates) == 0
    assert tri.points()[0].shape == (0, 3) and tri.keyframe_points(plane_frame(2, texture)) is None
    loaded = _query(node, StatusRequest())
    assert isinstance(loaded, Status) and loaded.memory_bytes == saved.memory_bytes
    points_after_load = len(node.state.global_map)
    # the keyframe queued for the replaced map: skipped; the loaded window's keyframes are worked on
    # again: the same candidates and sparse points as before the save, nothing fused twice
    assert tri.pending == 4 and tri.process_pending() == 2
    stats = tri.stats()
    assert stats["stale"] == 1 and stats["restored"] == 2 and len(tri._candidates) == 3
    for i in (1, 2):
        again, was = tri.keyframe_points(plane_frame(i, texture)), before[i]
        assert again is not None and was is not None and len(again) == len(was)
        np.testing.assert_array_equal(again.xyz, was.xyz)
    assert len(tri.points()[0]) > 0
    assert len(node.state.global_map) == points_after_load
    # keyframes acked after the load are the new map's candidates, triangulated with the loaded ones
    node.handle_ingest(encode(plane_frame(3, texture)))
    assert tri.process_pending() == 1 and len(tri._candidates) == 4
    assert tri._map is node.state.global_map and len(node.state.global_map) > points_after_load


def test_a_load_during_a_triangulation_keeps_nothing_of_it(
    node: MapperNode, texture: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    tri = SparseTriangulation(node.ctx)
    tri.install()
    node.handle_ingest(encode(plane_frame(0, texture, depth=True)))
    node.handle_ingest(encode(plane_frame(1, texture)))
    assert tri.process_pending() == 1 and isinstance(_query(node, Save(name="m")), Ok)
    node.handle_ingest(encode(plane_frame(2, texture)))
    real = triangulation_plugin.triangulate_keyframe
    found: list[int] = []

    def load_meanwhile(*args: Any, **kwargs: Any) -> SparsePoints:
        points = real(*args, **kwargs)
        found.append(len(points))
        _query(node, Load(name="m"))
        return points

    monkeypatch.setattr(triangulation_plugin, "triangulate_keyframe", load_meanwhile)
    assert tri.process_pending() == 0  # triangulated, but for the map the load replaced
    assert found[0] > 0 and tri.stats()["stale"] == 1 and tri.stats()["failed"] == 0
    assert tri.stats()["memory_bytes"] == 0 and tri.keyframe_points(plane_frame(2, texture)) is None
    assert tri.points()[0].shape == (0, 3) and len(tri._candidates) == 0


def test_pending_counts_the_batch_in_progress(node: MapperNode, texture: np.ndarray) -> None:
    # the worker drains the queue into a batch: until each keyframe of it is done, it is pending
    # (a client that waits for pending == 0 must not see 0 while the batch is being worked on)
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(max_pending=8))
    tri.install()
    for i in range(4):
        node.handle_ingest(encode(plane_frame(i, texture)))
    seen: list[int] = []
    original = tri._process_one

    def spy(keyframe: Any, version: int, target: GlobalSemanticMap, restored: bool = False) -> int:
        seen.append(tri.pending)
        return original(keyframe, version, target, restored)

    tri._process_one = spy  # type: ignore[method-assign]
    assert tri.pending == 4
    tri.process_pending()
    assert seen == [4, 3, 2, 1] and tri.pending == 0


def test_a_stopping_node_leaves_the_rest_of_the_batch(node: MapperNode, texture: np.ndarray) -> None:
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(max_pending=8))
    tri.install()
    for i in range(3):
        node.handle_ingest(encode(plane_frame(i, texture)))
    stop = threading.Event()
    stop.set()
    tri.run(stop)  # returns at once (stop is set) and keeps the event for the batches
    assert tri.process_pending() == 0
    assert tri.stats()["left_at_stop"] == 3 and tri.pending == 0 and tri.processed == 0


def test_serve_plugins_follow_the_config(tmp_path: Path) -> None:
    """install_serve_stages installs what the config asks for, as `govnesf serve` does."""
    from mapper.node.serve import install_serve_stages
    from mapper.node.workers.triangulation import SparseTriangulation

    def build(**extra: object) -> MapperNode:
        return MapperNode(config_from_dict({
            "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False,
            "serve_model": False, **extra,
        }))  # fmt: skip

    on = build()
    try:
        plugins = install_serve_stages(on)
        assert plugins.runtime is None and plugins.rendered_depth is None and plugins.ov_backend is None
        assert isinstance(plugins.triangulation, SparseTriangulation)  # enabled by default
    finally:
        on.stop()
    off = build(triangulation={"enabled": False})
    try:
        assert install_serve_stages(off).triangulation is None
    finally:
        off.stop()


def test_large_images_are_detected_at_most_detect_max_side_and_keypoints_map_back(
    texture: np.ndarray,
) -> None:
    """A 4x larger copy of an image is detected on a downscaled image (``detect_max_side``), not at
    2x its size, and its keypoints land where the small image's are (in its own pixels)."""
    from mapper.geometry.triangulation import detection_size

    small = render_plane(PLANE_POSES[0], texture)  # (H, W, 3) uint8
    h, w = small.shape[:2]
    big = cv2.resize(small, (4 * w, 4 * h), interpolation=cv2.INTER_NEAREST)
    cfg = TriangulationConfig(detect_max_side=2 * max(w, h))
    assert detection_size(4 * w, 4 * h, cfg.detect_upscale, cfg.detect_max_side) == (2 * w, 2 * h)
    ex = FeatureExtractor(cfg)
    f_small, f_big = ex.detect(small), ex.detect(big)
    assert len(f_small) > 50 and len(f_big) > 50
    # the photometric image is kept at most detect_max_side too (uint8): 2x the small one, not 4x
    assert f_big.gray is not None and f_big.gray.shape == (2 * h, 2 * w) and f_big.gray.dtype == np.uint8
    assert f_big.gray_scale == (0.5, 0.5) and f_small.gray_scale == (1.0, 1.0)
    assert f_small.gray is not None and f_small.gray.shape == (h, w)
    # every big keypoint / 4 has a small keypoint within 1.5 px (the same detection image)
    d = np.linalg.norm(f_big.uv[:, None, :] / 4.0 - f_small.uv[None, :, :], axis=2).min(axis=1)
    assert np.median(d) < 0.5 and np.mean(d < 1.5) > 0.9
    with pytest.raises(ConfigError, match="detect_max_side"):
        config_from_dict({"triangulation": {"detect_max_side": 10}})


def test_plugin_refines_a_keyframe_pose_sent_with_odometry_error(
    node: MapperNode, texture: np.ndarray
) -> None:
    """triangulation.refine_poses: a keyframe rendered at its true pose but sent 3 cm / 1.4 degrees off
    is triangulated at a pose nearer the truth; the window keeps the pose as sent; status reports it."""
    config = TriangulationConfig(min_views=2, refine_poses=True)
    tri = SparseTriangulation(node.ctx, config=config)
    tri.install()
    for i in (0, 1, 2):
        node.handle_ingest(encode(plane_frame(i, texture)))
    tri.process_pending()
    sent = perturbed(PLANE_POSES[3], np.array([0.02, 0.02, 0.01]), np.radians([0.8, -0.8, 0.8]))
    frame = dataclasses.replace(plane_frame(3, texture), world_from_cam=sent)
    node.handle_ingest(encode(frame))
    tri.process_pending()
    key = keyframe_key(frame)
    refined = tri.poses.refined()
    assert key in refined
    dt0, dr0 = pose_change(PLANE_POSES[3], sent)
    dt, dr = pose_change(PLANE_POSES[3], refined[key])
    # one plane seen over a narrow field constrains the rotation well, the centre less (a shift
    # looks almost like a turn; the prior holds what the points cannot tell apart)
    assert dr < 0.5 * dr0 and dt < dt0, (dt, dr, dt0, dr0)
    window = [k for k in node.state.window.keyframes if k.seq == 3]
    np.testing.assert_array_equal(window[0].world_from_cam, sent)  # the pose as sent is kept
    poses = tri.stats()["poses"]
    assert poses["refined"] >= 1 and poses["median_translation_cm"] > 0
    # its points lie on the plane at the refined pose
    points = tri.keyframe_points(frame)
    assert points is not None and np.median(np.abs(points.xyz[:, 2] - PLANE_Z)) < 0.02


def test_plugin_leaves_poses_alone_when_refinement_is_off(node: MapperNode, texture: np.ndarray) -> None:
    tri = SparseTriangulation(node.ctx, config=TriangulationConfig(min_views=2))
    tri.install()
    for i in (0, 1, 2, 3):
        node.handle_ingest(encode(plane_frame(i, texture)))
    tri.process_pending()
    assert tri.poses.refined() == {} and tri.stats()["poses"]["attempted"] == 0


def test_plugin_adjusts_the_window_of_poses_from_dense_matches(node: MapperNode) -> None:
    """triangulation.pose_method = "window": a simulated room's RGB-only keyframes sent with 2 cm /
    1 degree of error per frame are used nearer the truth (joint adjustment of each new keyframe with
    the ones before it, mapper.geometry.window_adjust); the window keeps the poses as sent; status
    counts them; a map load forgets the adjusted window. (A plane alone would not do: its matches
    cannot tell a turn from a shift.)"""
    from clients.harness import sim_stream
    from clients.sim.sensor import noisy_poses

    stream = sim_stream(5, 48, 160, 120, depth=False, ov=False)
    sent = noisy_poses(stream.poses, 0.02, 1.0, seed=5)
    config = TriangulationConfig(refine_poses=True, pose_method="window")
    tri = SparseTriangulation(node.ctx, config=config)
    tri.install()
    frames = []
    for k, (frame, _) in enumerate(stream.frames()):
        if k % 2 or k >= 40:
            continue
        frame = dataclasses.replace(frame, world_from_cam=sent[k])
        frames.append((k, frame))
        node.handle_ingest(encode(frame))
        tri.process_pending()
    refined = tri.poses.refined()
    pairs = [(stream.poses[k], sent[k], refined[keyframe_key(f)])
             for k, f in frames if keyframe_key(f) in refined]
    assert len(pairs) >= 0.75 * len(frames)
    before = np.median([pose_change(t, s)[1] for t, s, _ in pairs])
    after = np.median([pose_change(t, r)[1] for t, _, r in pairs])
    assert after < 0.7 * before, (before, after)
    for k, f in frames[-3:]:
        kept = [w for w in node.state.window.keyframes if w.seq == f.seq]
        np.testing.assert_array_equal(kept[0].world_from_cam, sent[k])  # the pose as sent is kept
    poses = tri.stats()["poses"]
    assert poses["attempted"] == len(frames) and poses["refined"] == len(refined)
    tri.poses.clear()
    assert tri.poses.refined() == {}
