"""Dense depth from posed RGB by plane sweep (mapper.geometry.plane_sweep) and its use in the
triangulation plugin: a rendered textured plane with known depth, degenerate cases (pure rotation,
no texture, no sources, a source that does not see the view), multi-view geometric consistency,
the depth range, the config, and the plugin's dense prior and global-map points."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapper.geometry.config import StereoConfig
from mapper.geometry.plane_sweep import (
    StereoView,
    agreeing_views,
    depth_range,
    fill_depth,
    gray_image,
    sweep_depth,
)
from mapper.node.config import ConfigError, config_from_dict
from mapper.node.service import MapperNode
from mapper.node.workers.triangulation import SparseTriangulation, keyframe_key
from protocol.messages import Frame, encode
from tests.mapper.geometry.test_triangulation import PLANE_Z, H, K, W, make_texture, plane_depth, render_plane

# the textured plane z = 3 m of the triangulation tests: same camera, texture and renderer


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return make_texture()


def pose(yaw_deg: float, center: tuple[float, float, float]) -> np.ndarray:
    a = np.radians(yaw_deg)
    out = np.eye(4)
    out[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    out[:3, 3] = center
    return out


POSES = [pose(0.0, (0.0, 0.0, 0.0)), pose(-3.0, (0.35, 0.05, 0.0)), pose(4.0, (-0.3, 0.1, 0.0)),
         pose(-2.0, (0.15, -0.2, 0.1))]


def stereo_view(i: int, texture: np.ndarray) -> StereoView:
    return StereoView(K, POSES[i], gray_image(render_plane(POSES[i], texture)))


def test_textured_plane_gets_its_true_depth_almost_everywhere(texture: np.ndarray) -> None:
    ref = stereo_view(0, texture)
    out = sweep_depth(ref, [stereo_view(i, texture) for i in (1, 2, 3)], 1.0, 8.0, StereoConfig())
    truth = plane_depth(POSES[0])
    rel = np.abs(out.depth_m[out.valid] - truth[out.valid]) / truth[out.valid]
    assert out.sources == 3 and out.density > 0.6
    assert np.median(rel) < 0.01 and np.quantile(rel, 0.95) < 0.03
    assert (out.score[out.valid] >= StereoConfig().min_ncc).all() and (out.score[~out.valid] == -1).all()


def test_a_slanted_view_and_views_of_other_sizes_are_swept_too(texture: np.ndarray) -> None:
    # the reference looks at the plane at 25 degrees; a source renders at another size and focal length
    ref_pose = pose(25.0, (-0.8, 0.0, 0.2))
    ref = StereoView(K, ref_pose, gray_image(render_plane(ref_pose, texture)))
    src_pose = pose(20.0, (-0.4, 0.05, 0.2))
    big = cv2.resize(render_plane(src_pose, texture), (2 * W, 2 * H), interpolation=cv2.INTER_LINEAR)
    src = StereoView(2.0 * K, src_pose, gray_image(big))
    out = sweep_depth(ref, [src, stereo_view(0, texture)], 1.0, 8.0, StereoConfig(top_k=1))
    truth = plane_depth(ref_pose)
    rel = np.abs(out.depth_m[out.valid] - truth[out.valid]) / truth[out.valid]
    assert out.density > 0.4 and np.median(rel) < 0.02


def test_pure_rotation_gives_no_depth(texture: np.ndarray) -> None:
    # same centre, turned: every hypothesis projects to the same pixel, nothing is unique
    ref = stereo_view(0, texture)
    turned = pose(5.0, (0.0, 0.0, 0.0))
    src = StereoView(K, turned, gray_image(render_plane(turned, texture)))
    out = sweep_depth(ref, [src], 1.0, 8.0, StereoConfig(top_k=1))
    assert out.density < 0.01


def test_no_texture_no_sources_and_unseen_views_give_no_depth(texture: np.ndarray) -> None:
    flat = StereoView(K, POSES[0], np.full((H, W), 0.5, np.float32))
    flat_src = StereoView(K, POSES[1], np.full((H, W), 0.5, np.float32))
    assert sweep_depth(flat, [flat_src], 1.0, 8.0, StereoConfig(top_k=1)).density == 0.0
    none = sweep_depth(stereo_view(0, texture), [], 1.0, 8.0)
    assert none.density == 0.0 and none.depth_m.shape == (H, W) and none.sources == 0
    # fewer sources than top_k: no pixel can be scored
    assert sweep_depth(stereo_view(0, texture), [stereo_view(1, texture)], 1.0, 8.0,
                       StereoConfig(top_k=2)).density == 0.0
    # a source looking the other way (the plane is behind it): nothing projects in front of it
    behind = pose(180.0, (0.3, 0.0, 0.0))
    src = StereoView(K, behind, stereo_view(1, texture).gray)
    out = sweep_depth(stereo_view(0, texture), [src], 1.0, 8.0, StereoConfig(top_k=1))
    assert out.density == 0.0


def test_the_surface_outside_the_swept_range_is_not_reported(texture: np.ndarray) -> None:
    # the plane is 3 m away; sweeping 0.5-2 m puts every winner on the far end: dropped
    out = sweep_depth(stereo_view(0, texture), [stereo_view(i, texture) for i in (1, 2)], 0.5, 2.0)
    assert out.density < 0.02


def test_bad_inputs_raise_before_any_work(texture: np.ndarray) -> None:
    ref = stereo_view(0, texture)
    with pytest.raises(ValueError, match="near"):
        sweep_depth(ref, [stereo_view(1, texture)], 3.0, 2.0)
    with pytest.raises(ValueError, match="near"):
        sweep_depth(ref, [stereo_view(1, texture)], 0.0, 2.0)
    with pytest.raises(ValueError, match="fx, fy"):
        sweep_depth(StereoView(np.array([0.0, 100.0, 80.0, 60.0]), POSES[0], ref.gray), [], 1.0, 2.0)
    with pytest.raises(ValueError, match="world_from_cam"):
        sweep_depth(ref, [StereoView(K, np.full((4, 4), np.nan), ref.gray)], 1.0, 2.0)
    with pytest.raises(ValueError, match="gray"):
        sweep_depth(StereoView(K, POSES[0], ref.gray[None]), [], 1.0, 2.0)
    with pytest.raises(ValueError, match="rgb"):
        gray_image(np.zeros((4, 4), np.uint8))


def test_geometric_consistency_counts_agreeing_and_checking_views() -> None:
    d0, d1 = plane_depth(POSES[0]).astype(np.float32), plane_depth(POSES[1]).astype(np.float32)
    off = 1.3 * plane_depth(POSES[2])
    agree, checked = agreeing_views(K, POSES[0], d0, [(K, POSES[1], d1), (K, POSES[2], off)], 0.05)
    seen = checked > 0
    assert seen.mean() > 0.5
    assert (agree[seen] <= checked[seen]).all()
    # view 1 agrees wherever it sees the point; view 2's depth is 30% off: it never agrees
    assert np.median(agree[seen]) == 1 and agree.max() == 1
    # pixels without depth are never checked; a view without depth there does not check
    holes = d0.copy()
    holes[:, :40] = 0.0
    _, checked = agreeing_views(K, POSES[0], holes, [(K, POSES[1], np.zeros_like(d1))], 0.05)
    assert checked.max() == 0
    agree, checked = agreeing_views(K, POSES[0], holes, [(K, POSES[1], d1)], 0.05)
    assert checked[:, :40].max() == 0 and agree[10:110, 60:100].min() == 1
    # a view that has the point behind it does not check it
    _, checked = agreeing_views(K, POSES[0], d0, [(K, pose(180.0, (0.0, 0.0, 0.0)), d1)], 0.05)
    assert checked.max() == 0


def test_depth_range_follows_the_points_within_the_limits() -> None:
    cfg = StereoConfig()
    assert depth_range(np.array([2.0, 3.0]), cfg) is None  # fewer than min_range_points
    rng = np.random.default_rng(0)
    near, far = depth_range(rng.uniform(2.0, 4.0, 200), cfg)  # type: ignore[misc]
    assert near == pytest.approx(2.0 / cfg.range_margin, rel=0.05)
    assert far == pytest.approx(4.0 * cfg.range_margin, rel=0.05)
    near, far = depth_range(np.full(50, 10.0), cfg)  # type: ignore[misc]
    assert far == cfg.max_depth_m and near == pytest.approx(10.0 / cfg.range_margin)
    assert depth_range(np.full(50, 100.0), cfg) is None  # beyond max_depth_m: nothing to sweep
    assert depth_range(np.array([np.nan, -1.0, 0.0] * 10), cfg) is None


def test_filling_carries_depths_across_a_surface_of_one_colour_but_not_across_edges() -> None:
    # a slanted plane (inverse depth affine in the pixel) seen as one colour, depths on a sparse grid
    truth = plane_depth(pose(25.0, (-0.8, 0.0, 0.2))).astype(np.float32)
    sparse = np.zeros_like(truth)
    sparse[::6, ::6] = truth[::6, ::6]
    gray = np.full((H, W), 0.4, np.float32)
    filled = fill_depth(gray, sparse, 6)
    assert (filled[sparse > 0] == sparse[sparse > 0]).all()  # known depths are kept
    inner = filled[6:-6, 6:-6]
    assert (inner > 0).all()
    np.testing.assert_allclose(inner, truth[6:-6, 6:-6], rtol=0.01)
    # two surfaces of different colours and depths: no depth crosses the colour edge
    left = np.broadcast_to(np.arange(W)[None, :] < W // 2, (H, W))
    gray2 = np.where(left, 0.2, 0.8).astype(np.float32)
    depth2 = np.where(left, 2.0, 4.0).astype(np.float32)
    sparse2 = np.zeros_like(depth2)
    sparse2[::5, ::5] = depth2[::5, ::5]
    out = fill_depth(gray2, sparse2, 6)
    on = out > 0
    assert on.mean() > 0.9 and np.abs(out[on] - depth2[on]).max() < 1e-4
    # the same depths on ONE colour, the depth edge between two sample columns (75: 2 m, 80: 4 m):
    # the pixels between see both depths, they disagree, those pixels stay empty
    depth3 = np.where(np.arange(W)[None, :] < 78, 2.0, 4.0).astype(np.float32) * np.ones((H, 1), np.float32)
    sparse3 = np.zeros_like(depth3)
    sparse3[::5, ::5] = depth3[::5, ::5]
    out = fill_depth(np.full((H, W), 0.5, np.float32), sparse3, 6, max_spread=0.1)
    assert (out[:, 77:79] == 0).all()
    far = np.r_[0:70, 86:150]
    assert (out[6:-6, far] > 0).all() and np.abs(out[6:-6, far] - depth3[6:-6, far]).max() < 1e-4


def test_filling_edge_cases() -> None:
    gray = np.zeros((H, W), np.float32)
    empty = np.zeros((H, W), np.float32)
    assert (fill_depth(gray, empty, 5) == 0).all()
    one = empty.copy()
    one[60, 80] = 2.0
    np.testing.assert_array_equal(fill_depth(gray, one, 0), one)  # radius 0: unchanged
    assert (fill_depth(gray, one, 3, min_weight=10.0) == one).all()  # too little support: nothing filled
    with pytest.raises(ValueError, match="same"):
        fill_depth(gray, empty[:, :10], 3)
    with pytest.raises(ValueError, match="radius_px"):
        fill_depth(gray, empty, -1)


def test_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="stereo.patch_px"):
        config_from_dict({"stereo": {"patch_px": 4}})
    with pytest.raises(ConfigError, match="stereo.top_k"):
        config_from_dict({"stereo": {"top_k": 5, "max_sources": 4}})
    with pytest.raises(ConfigError, match="stereo.max_depth_m"):
        config_from_dict({"stereo": {"min_depth_m": 5.0, "max_depth_m": 4.0}})
    with pytest.raises(ConfigError, match="stereo.planes"):
        config_from_dict({"stereo": {"planes": 2}})
    assert config_from_dict({"stereo": {"enabled": False}}).stereo.enabled is False


# ---- the node plugin ---------------------------------------------------------------------------
class Sink:
    def __init__(self) -> None:
        self.priors: dict[tuple[str, int, int], np.ndarray | None] = {}

    def set_view_depth_prior(self, key: tuple[str, int, int], depth_m: np.ndarray | None) -> None:
        self.priors[key] = depth_m

    def set_view_extent(self, key: tuple[str, int, int], points_m: np.ndarray | None) -> None:
        pass


def plane_frame(i: int, texture: np.ndarray, depth: bool = False) -> Frame:
    p = POSES[i]
    return Frame(seq=i, stamp_ns=1000 + i, width=W, height=H, K=K.copy(), world_from_cam=p.copy(),
                 rgb=render_plane(p, texture),
                 depth_m=plane_depth(p).astype(np.float32) if depth else None,
                 ov=np.full((H // 8, W // 8, 4), 0.5, np.float16), ov_space="test-space")


def make_node(tmp_path: Path, stereo: dict[str, object]) -> MapperNode:
    return MapperNode(config_from_dict({
        "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False, "serve_model": False,
        "window": {"max_keyframes": 8, "min_translation_m": 0.05},
        "global_map": {"min_weight": 0.0, "rendered_depth": False},
        "triangulation": {"global_map_weight": 0.0},  # only the swept depths reach the map
        "stereo": stereo,
    }))


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    mapper = make_node(tmp_path, {"top_k": 1})
    yield mapper
    mapper.stop()


def test_plugin_sweeps_rgb_only_keyframes_into_a_dense_prior_and_map_points(
    node: MapperNode, texture: np.ndarray
) -> None:
    sink = Sink()
    tri = SparseTriangulation(node.ctx, runtime=sink)
    tri.install()
    node.handle_ingest(encode(plane_frame(0, texture, depth=True)))  # a partner whose depth checks
    for i in (1, 2, 3):
        node.handle_ingest(encode(plane_frame(i, texture)))
    assert tri.process_pending() == 3
    stereo = tri.stats()["stereo"]
    assert stereo["enabled"] and stereo["keyframes"] == 3 and stereo["depths_per_keyframe"] > 0.3 * H * W
    assert stereo["global_map_points"] > 0 and stereo["mean_ms"] > 0
    # the prior: dense, on the plane (the triangulated discs and the swept depths)
    prior = sink.priors[keyframe_key(plane_frame(3, texture))]
    assert prior is not None and prior.shape == (H, W) and (prior > 0).mean() > 0.3
    on = prior > 0
    truth = plane_depth(POSES[3])
    assert np.median(np.abs(prior[on] - truth[on]) / truth[on]) < 0.01
    # the swept depths as points (what rendered-depth points are checked against), with a sigma
    xyz, sigma = tri.geometry_points()
    n_tri = len(tri.points()[0])
    assert len(xyz) == n_tri + stereo["points"] and stereo["points"] > 1000
    assert np.median(np.abs(xyz[n_tri:, 2] - PLANE_Z)) < 0.03
    np.testing.assert_allclose(sigma[n_tri:].mean(), tri.stereo.sigma_rel * PLANE_Z, rtol=0.2)
    # the global map's points are on the plane
    snap = node.state.global_map.snapshot()
    assert len(snap) > 1000 and np.median(np.abs(snap.xyz[:, 2] - PLANE_Z)) < 0.03


def test_disabled_stereo_adds_no_swept_depth(tmp_path: Path, texture: np.ndarray) -> None:
    node = make_node(tmp_path, {"enabled": False})
    try:
        sink = Sink()
        tri = SparseTriangulation(node.ctx, runtime=sink)
        tri.install()
        node.handle_ingest(encode(plane_frame(0, texture, depth=True)))
        with_depth = len(node.state.global_map.snapshot())  # the depth frame's own points
        for i in (1, 2, 3):
            node.handle_ingest(encode(plane_frame(i, texture)))
        assert tri.process_pending() == 3
        assert tri.stats()["stereo"]["keyframes"] == 0
        assert len(node.state.global_map.snapshot()) == with_depth
    finally:
        node.stop()


def test_a_large_keyframe_is_swept_at_the_working_width(tmp_path: Path, texture: np.ndarray) -> None:
    node = make_node(tmp_path, {"top_k": 1, "max_width": 80})
    try:
        sink = Sink()
        tri = SparseTriangulation(node.ctx, runtime=sink)
        tri.install()
        for i in (0, 1, 2):
            node.handle_ingest(encode(plane_frame(i, texture, depth=i == 0)))
        tri.process_pending()
        assert tri.stats()["stereo"]["keyframes"] == 2
        prior = sink.priors[keyframe_key(plane_frame(2, texture))]
        assert prior is not None and prior.shape == (H, W)  # back at the keyframe's size
        on = prior > 0
        truth = plane_depth(POSES[2])
        assert on.mean() > 0.3 and np.median(np.abs(prior[on] - truth[on]) / truth[on]) < 0.02
    finally:
        node.stop()


def test_swept_points_keep_within_their_budget(tmp_path: Path, texture: np.ndarray) -> None:
    node = make_node(tmp_path, {"top_k": 1, "max_points": 100})
    try:
        tri = SparseTriangulation(node.ctx, runtime=Sink())
        tri.install()
        for i in (0, 1, 2, 3):
            node.handle_ingest(encode(plane_frame(i, texture, depth=i == 0)))
        tri.process_pending()
        stereo = tri.stats()["stereo"]
        # only the newest keyframe's points are left (one keyframe is never split)
        assert stereo["keyframes"] == 3 and stereo["depths_per_keyframe"] > 100
        assert stereo["points"] == len(tri.geometry_points()[0]) - len(tri.points()[0])
        assert stereo["points"] < 2 * stereo["depths_per_keyframe"]
    finally:
        node.stop()


def test_stacked_box_filter_and_top_k_equal_their_plain_definitions() -> None:
    from mapper.geometry import plane_sweep

    rng = np.random.default_rng(3)
    planes = rng.random((7, 13, 11)).astype(np.float32)
    for patch in (3, 5, 7):
        plain = np.stack([cv2.boxFilter(p, -1, (patch, patch), borderType=cv2.BORDER_REFLECT)
                          for p in planes])
        np.testing.assert_allclose(plane_sweep._box(planes, patch), plain, atol=1e-6)
    scores = rng.uniform(-1, 1, (5, 3, 4, 6)).astype(np.float32)
    scores[rng.random(scores.shape) < 0.3] = np.nan  # sources that do not count
    filled = np.where(np.isnan(scores), -np.inf, scores)
    ordered = -np.sort(-filled, axis=0)
    for k in (1, 2, 3, 5):
        expected = ordered[:k].mean(axis=0)
        expected = np.where(np.isfinite(expected), expected, -np.inf)
        np.testing.assert_allclose(plane_sweep._aggregate(scores, k), expected, atol=1e-6)


def test_a_backlog_skips_the_sweep_but_not_the_triangulation(tmp_path: Path, texture: np.ndarray) -> None:
    node = make_node(tmp_path, {"top_k": 1, "max_backlog": 1, "max_deferred": 0})
    try:
        tri = SparseTriangulation(node.ctx, runtime=Sink())
        tri.install()
        for i in (0, 1, 2, 3):
            node.handle_ingest(encode(plane_frame(i, texture, depth=i == 0)))
        # the batch: the depth keyframe, then three RGB-only ones with 3, 2 and 1 keyframes waiting
        assert tri.process_pending() == 3
        stereo = tri.stats()["stereo"]
        assert stereo["skipped_busy"] == 2 and stereo["keyframes"] == 1
        assert stereo["deferred"] == 0 and stereo["deferred_swept"] == 0  # max_deferred 0: never done
        assert tri.stats()["keyframes"] == 3 and len(tri.points()[0]) > 0  # all three triangulated
    finally:
        node.stop()


def test_sweeps_put_off_while_busy_are_done_once_no_keyframe_waits(
    tmp_path: Path, texture: np.ndarray
) -> None:
    node = make_node(tmp_path, {"top_k": 1, "max_backlog": 1})
    try:
        sink = Sink()
        tri = SparseTriangulation(node.ctx, runtime=sink)
        tri.install()
        for i in (0, 1, 2, 3):
            node.handle_ingest(encode(plane_frame(i, texture, depth=i == 0)))
        points_before = len(node.state.global_map)
        assert tri.process_pending() == 3
        stereo = tri.stats()["stereo"]
        # two put off while the batch waited, then swept (oldest first) once the queue was empty
        assert stereo["skipped_busy"] == 2 and stereo["deferred_swept"] == 2 and stereo["deferred"] == 0
        assert stereo["keyframes"] == 3 and stereo["deferred_forgotten"] == 0 and tri.pending == 0
        assert len(node.state.global_map) > points_before  # their depths reached the map
        prior = sink.priors[keyframe_key(plane_frame(2, texture))]  # and became priors
        truth = plane_depth(POSES[2])
        on = prior > 0
        assert on.mean() > 0.3 and np.median(np.abs(prior[on] - truth[on]) / truth[on]) < 0.02
    finally:
        node.stop()


def test_put_off_sweeps_beyond_max_deferred_or_before_a_load_are_forgotten(
    tmp_path: Path, texture: np.ndarray
) -> None:
    import dataclasses

    node = make_node(tmp_path, {"top_k": 1, "max_backlog": 1, "max_deferred": 1})
    try:
        tri = SparseTriangulation(node.ctx, runtime=Sink())
        tri.install()
        for i in (0, 1, 2, 3):
            node.handle_ingest(encode(plane_frame(i, texture, depth=i == 0)))
        tri.process_pending()
        stereo = tri.stats()["stereo"]
        assert stereo["deferred_forgotten"] == 1 and stereo["deferred_swept"] == 1
        # a put-off sweep of a map that a load replaced is forgotten, never fused into the new map
        for n, i in enumerate((1, 2)):  # two more RGB-only keyframes (poses seen before, new stamps)
            again = dataclasses.replace(plane_frame(i, texture), seq=4 + n, stamp_ns=2000 + n)
            node.handle_ingest(encode(again))
        for item in tri._queue.drain():  # as the worker would with more keyframes waiting: put off
            tri._in_batch = 3
            tri._process_one(*item)
        tri._in_batch = 0
        assert tri.pending == 1  # one remembered (max_deferred), the other forgotten
        tri.on_map_loaded(node.state.global_map, 10**9)
        assert tri.pending == 0 and tri.sweep_deferred() == 0
        stereo = tri.stats()["stereo"]
        assert stereo["deferred_forgotten"] == 3 and stereo["deferred_swept"] == 1
    finally:
        node.stop()


def test_put_off_sweeps_beyond_their_memory_budget_are_forgotten(tmp_path: Path, texture: np.ndarray) -> None:
    node = make_node(tmp_path, {"top_k": 1, "max_backlog": 1, "max_deferred_mb": 0.05})  # < one keyframe
    try:
        tri = SparseTriangulation(node.ctx, runtime=Sink())
        tri.install()
        for i in (0, 1, 2, 3):
            node.handle_ingest(encode(plane_frame(i, texture, depth=i == 0)))
        tri.process_pending()
        stereo = tri.stats()["stereo"]
        assert stereo["skipped_busy"] == 2 and stereo["deferred_forgotten"] == 2
        assert stereo["deferred_swept"] == 0
        assert tri._deferred.nbytes == 0 and tri.pending == 0
    finally:
        node.stop()


def test_features_that_arrive_later_reach_the_triangulated_and_swept_points(
    tmp_path: Path, texture: np.ndarray
) -> None:
    # a robot without depth and without onboard OV: the node's OV backend encodes the keyframes
    # later than the worker adds their points; the features must still reach those points
    import dataclasses

    node = MapperNode(config_from_dict({
        "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False, "serve_model": False,
        "window": {"max_keyframes": 8, "min_translation_m": 0.05},
        "global_map": {"min_weight": 0.0, "rendered_depth": False},
        "ov_backend": {"kind": "clip", "weights_path": str(tmp_path / "never-loaded.pt"),
                       "bpe_path": str(tmp_path / "never-loaded.txt.gz")},
        "stereo": {"top_k": 1},
    }))
    try:
        tri = SparseTriangulation(node.ctx, runtime=Sink())
        tri.install()
        for i in (0, 1, 2, 3):
            frame = plane_frame(i, texture, depth=i == 0)
            node.handle_ingest(encode(dataclasses.replace(frame, ov=None, ov_space=None)))
        assert tri.process_pending() == 3
        snap = node.state.global_map.snapshot()
        assert len(snap) > 1000 and snap.n_with_features == 0
        # the backend's swap, then its notice to the feature listeners
        for kf in list(node.state.window.keyframes):
            if kf.depth_m is not None:
                continue
            featured = dataclasses.replace(kf, ov=np.full((H // 8, W // 8, 4), 0.5, np.float16),
                                           ov_space="test-space")
            with node.state.lock:
                assert node.state.window.swap(kf, featured)
            for listener in node.ctx.feature_listeners:
                listener(featured)
        stats = tri.stats()
        assert stats["late_feature_points"] > 1000 and stats["failed"] == 0
        assert node.state.global_map.snapshot().n_with_features > 1000
        for listener in node.ctx.feature_listeners:  # told twice: nothing is fused twice
            listener(featured)
        assert tri.stats()["late_feature_points"] == stats["late_feature_points"]
    finally:
        node.stop()


def test_priors_take_the_whole_geometry_where_their_own_depth_has_holes(
    tmp_path: Path, texture: np.ndarray
) -> None:
    own_only = make_node(tmp_path / "own", {"top_k": 1, "prior_geometry": False})
    node = make_node(tmp_path / "geometry", {"top_k": 1, "prior_geometry_refresh": 0.0})
    try:
        priors = {}
        for mapper in (own_only, node):
            sink = Sink()
            tri = SparseTriangulation(mapper.ctx, runtime=sink)
            tri.install()
            mapper.handle_ingest(encode(plane_frame(0, texture, depth=True)))
            for i in (1, 2, 3):
                mapper.handle_ingest(encode(plane_frame(i, texture)))
            assert tri.process_pending() == 3
            priors[mapper is node] = (sink, tri)
        (sink_own, _), (sink, tri) = priors[False], priors[True]
        key = keyframe_key(plane_frame(1, texture))
        own, filled = sink_own.priors[key], sink.priors[key]
        assert own is not None and filled is not None and filled.shape == own.shape
        # the own depths are kept; holes take the geometry's surface, which is on the plane too
        np.testing.assert_array_equal(filled[own > 0], own[own > 0])
        assert (filled > 0).sum() >= (own > 0).sum()
        truth = plane_depth(POSES[1])
        on = filled > 0
        assert np.median(np.abs(filled[on] - truth[on]) / truth[on]) < 0.01
        stats = tri.stats()["stereo"]
        assert stats["prior_refreshes"] >= 1  # refresh 0: after every batch that changed the geometry
        assert tri.refresh_priors() == 0  # nothing changed since
        assert tri.refresh_priors(force=True) == 3  # the three RGB-only keyframes' priors
        # a load forgets them
        tri.on_map_loaded(node.state.global_map, 10)
        assert tri.refresh_priors(force=True) == 0
    finally:
        own_only.stop()
        node.stop()


def test_prior_geometry_config_is_validated() -> None:
    assert config_from_dict({}).stereo.prior_geometry is True
    with pytest.raises(ConfigError, match="stereo.prior_geometry_refresh"):
        config_from_dict({"stereo": {"prior_geometry_refresh": -1.0}})
