"""Tests for global-map points from rendered depth (mapper.node.workers.depth_points) and the pieces it uses:
depth-only renders, the support mask, confidence-weighted integration, the node's keyframe
listeners and workers, frustum bounds (geometry.frustum_points, data.source_batch)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.map.global_map import GlobalSemanticMap
from mapper.map.window import Keyframe, KeyframeWindow
from mapper.model.field import GovNeSF
from mapper.model.ops.geometry import frustum_points, invert_pose, project_points
from mapper.node.backends.learned import install_learned_backend
from mapper.node.config import ConfigError, GlobalMapConfig, WindowConfig, config_from_dict
from mapper.node.service import MapperNode
from mapper.node.workers.depth_points import RenderedDepthPoints, render_keyframe_depth
from mapper.runtime.model_runtime import ModelRuntimeConfig
from protocol.messages import Frame, Status, StatusRequest, decode, encode
from tests.mapper.runtime.test_model_runtime import TINY, keyframe, make_runtime, orbit
from tests.model_helpers import look_at


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


# ---- geometry / data -----------------------------------------------------------------------------
def test_frustum_points_project_inside_the_image_at_the_requested_depths() -> None:
    K = torch.tensor([30.0, 30.0, 20.0, 15.0], dtype=torch.float64)
    pose = torch.from_numpy(look_at((1.0, -2.0, 1.2), (0.0, 0.0, 0.5)))
    pts = frustum_points(K, pose, 40, 30, 0.5, 4.0)
    assert pts.shape == (8 * 5 * 5, 3)
    uv, z = project_points(pts, K, invert_pose(pose))
    assert abs(float(z.min()) - 0.5) < 1e-9 and abs(float(z.max()) - 4.0) < 1e-9
    assert bool((uv[:, 0] >= -1e-6).all() & (uv[:, 0] <= 40 + 1e-6).all())
    assert bool((uv[:, 1] >= -1e-6).all() & (uv[:, 1] <= 30 + 1e-6).all())
    with pytest.raises(ValueError, match="near_m < far_m"):
        frustum_points(K, pose, 40, 30, 2.0, 1.0)


# ---- runtime: depth-only renders, support mask ------------------------------------------------------
def _filled_runtime(model: GovNeSF, n: int = 4, **overrides: object):  # type: ignore[no-untyped-def]
    runtime = make_runtime(model, **overrides)
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    runtime.attach(window)
    for i in range(n):
        window.consider(keyframe(i, orbit(i)))
    return runtime


@pytest.mark.parametrize("skip", [False, True])
def test_depth_only_render_equals_the_depth_of_a_full_render(model: GovNeSF, skip: bool) -> None:
    runtime = _filled_runtime(model, empty_space_skipping=skip)
    K, pose = [12.0, 12.0, 8.0, 6.0], look_at((2.1, 0.5, 1.1), (0.0, 0.0, 0.5))
    full = runtime.render(K, pose, 16, 12, ["rgb", "depth"])
    depth_only = runtime.render(K, pose, 16, 12, ["depth"])
    assert depth_only.depth_m is not None and full.depth_m is not None
    np.testing.assert_array_equal(depth_only.depth_m, full.depth_m)
    np.testing.assert_array_equal(depth_only.opacity, full.opacity)
    assert depth_only.rgb is None and depth_only.stats["appearance_evals"] == 0
    assert full.stats["appearance_evals"] > 0


def test_support_mask_zeroes_density_where_too_few_views_see_the_volume(model: GovNeSF) -> None:
    K, pose = [12.0, 12.0, 8.0, 6.0], look_at((2.1, 0.5, 1.1), (0.0, 0.0, 0.5))
    base = _filled_runtime(model).render(K, pose, 16, 12, ["depth"], empty_space_skipping=False)
    everything = _filled_runtime(model, min_view_support=100).render(K, pose, 16, 12, ["depth"],
                                                                      empty_space_skipping=False)
    assert base.opacity.max() > 0.0
    assert everything.opacity.max() == 0.0 and not everything.depth_m.any()  # type: ignore[union-attr]
    with pytest.raises(ConfigError, match="min_view_support"):
        ModelRuntimeConfig(min_view_support=0).validate()


# ---- global map: confidence, stride override, keyframe clock -------------------------------------
def _wall_keyframe(depth: float = 2.0, ov: bool = True) -> Keyframe:
    return Keyframe(seq=0, stamp_ns=0, camera="cam0", K=np.array([10.0, 10.0, 8.0, 6.0]),
                    world_from_cam=np.eye(4), rgb=np.zeros((12, 16, 3), np.uint8),
                    depth_m=np.full((12, 16), depth, np.float32),
                    ov=np.ones((3, 4, 2), np.float32) if ov else None)


def test_confidence_scales_weights_and_stride_override_counts_every_pixel() -> None:
    cfg = GlobalMapConfig(voxel_size_m=0.01, pixel_stride=4, grazing_power=0.0, min_weight=0.0, near_m=10.0)
    kf = _wall_keyframe()
    plain = GlobalSemanticMap(cfg)
    half = GlobalSemanticMap(cfg)
    assert plain.integrate(kf).points == 3 * 4
    conf = np.full((12, 16), 0.5, np.float32)
    stats = half.integrate(kf, pixel_stride=1, confidence=conf, count_keyframe=False)
    assert stats.points == 12 * 16
    a, b = plain.snapshot(), half.snapshot()
    assert np.allclose(a.weight, 1.0) and np.allclose(b.weight, 0.5)
    assert half._kf_counter == 0 and plain._kf_counter == 1
    zero = GlobalSemanticMap(GlobalMapConfig(min_weight=0.02))
    skipped = zero.integrate(kf, confidence=np.zeros((12, 16), np.float32)).skipped
    assert skipped == "every observation below min_weight"
    with pytest.raises(ValueError, match="confidence"):
        zero.integrate(kf, confidence=np.ones((3, 3), np.float32))
    assert len(zero) == 0


def test_rendered_depth_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="rendered_min_opacity"):
        config_from_dict({"global_map": {"rendered_min_opacity": 1.5}})
    with pytest.raises(ConfigError, match="rendered_depth_stride"):
        config_from_dict({"global_map": {"rendered_depth_stride": 0}})


# ---- the worker on an in-process node ------------------------------------------------------------
class _Encoder:
    space = "test-space"
    dim = 6

    def encode(self, texts):  # type: ignore[no-untyped-def]
        return np.eye(len(texts), 6, dtype=np.float32)


def _frame(seq: int, depth: bool = False) -> Frame:
    kf = keyframe(seq, orbit(seq), depth_m=2.0 if depth else None)
    return Frame(seq=seq, stamp_ns=seq, width=40, height=30, K=kf.K, world_from_cam=kf.world_from_cam,
                 rgb=kf.rgb, depth_m=kf.depth_m, ov=kf.ov, ov_space=kf.ov_space)


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    config = config_from_dict({
        "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False,
        "window": {"max_keyframes": 6, "min_translation_m": 0.05},
        "global_map": {"rendered_min_opacity": 0.0, "rendered_min_views": 3, "rendered_depth_stride": 2,
                       "min_weight": 0.0, "rendered_max_pending": 5},
    })
    mapper = MapperNode(config)
    yield mapper
    mapper.stop()


def _install(node: MapperNode, model: GovNeSF) -> RenderedDepthPoints:
    runtime = make_runtime(model, min_opacity=0.0)
    runtime._loaded.text_encoder = lambda space: _Encoder()  # type: ignore[assignment]
    points = install_learned_backend(node, runtime)
    assert isinstance(points, RenderedDepthPoints)
    return points


def test_frames_without_depth_get_points_once_enough_views(node: MapperNode, model: GovNeSF) -> None:
    points = _install(node, model)
    node.handle_ingest(encode(_frame(0, depth=True)))  # has depth: not queued
    node.handle_ingest(encode(_frame(1)))
    assert points.pending == 1 and len(node.state.global_map) > 0
    before = len(node.state.global_map)
    assert points.process_pending() == 0 and points.pending == 1  # 2 views < rendered_min_views
    node.handle_ingest(encode(_frame(2)))
    assert points.process_pending() == 2 and points.pending == 0
    snap = node.state.global_map.snapshot()
    assert len(snap) > before and snap.has_feature.any()
    stats = points.stats()
    assert stats["integrated"] == 2 and stats["points"] > 0 and stats["failed"] == 0
    status = decode(node.handle_query(encode(StatusRequest())), direction="reply")
    assert isinstance(status, Status) and status.extra["rendered_depth"]["integrated"] == 2


def test_queue_is_bounded_and_a_load_drops_stale_keyframes(node: MapperNode, model: GovNeSF) -> None:
    points = _install(node, model)
    for seq in range(8):
        node.handle_ingest(encode(_frame(seq)))
    assert points.pending == 5 and points.dropped == 3 and points.queued == 8
    node.state.global_map = GlobalSemanticMap(node.config.global_map)  # as a map load does
    assert points.process_pending() == 0 and points.stale == 5 and points.integrated == 0
    assert len(node.state.global_map) == 0


def test_worker_thread_integrates_in_the_background_and_stops(node: MapperNode, model: GovNeSF) -> None:
    points = _install(node, model)
    assert ("depth-points", points.run) in node.ctx.workers
    stop = threading.Event()
    thread = threading.Thread(target=points.run, args=(stop,), daemon=True)
    thread.start()
    for seq in range(4):
        node.handle_ingest(encode(_frame(seq)))
    deadline = time.monotonic() + 30.0
    while points.integrated < 4 and time.monotonic() < deadline:
        time.sleep(0.05)
    stop.set()
    thread.join(timeout=5.0)
    assert points.integrated == 4 and not thread.is_alive()


def test_render_keyframe_depth_scales_K_with_the_stride(model: GovNeSF) -> None:
    runtime = _filled_runtime(model, min_opacity=0.0)
    kf = keyframe(9, orbit(9), depth_m=None)
    cfg = GlobalMapConfig(rendered_depth_stride=4, rendered_min_opacity=0.0, rendered_weight=0.5)
    rendered = render_keyframe_depth(runtime, kf, cfg)
    assert rendered.depth_m.shape == (7, 10) and rendered.rgb.shape == (7, 10, 3)
    np.testing.assert_allclose(rendered.K, np.asarray(kf.K) * np.array([10 / 40, 7 / 30, 10 / 40, 7 / 30]))
    assert float(rendered.confidence.max()) <= 0.5 + 1e-6 and rendered.ov is kf.ov


def test_render_keyframe_depth_drops_the_pixels_at_occlusion_edges(model: GovNeSF) -> None:
    """``rendered_edge_rel``: the render with the pixels :func:`depth_edges` marks set to 0 (no point);
    0 keeps every pixel with enough opacity."""
    from mapper.node.workers.depth_points import RenderedKeyframe, depth_edges

    runtime = _filled_runtime(model, min_opacity=0.0)
    kf = keyframe(9, orbit(9), depth_m=None)

    def rendered(rel: float) -> RenderedKeyframe:
        cfg = GlobalMapConfig(rendered_min_opacity=0.0, rendered_edge_rel=rel)
        return render_keyframe_depth(runtime, kf, cfg)

    full = rendered(0.0)
    for rel in (0.01, 0.1):
        cut = rendered(rel)
        edges = depth_edges(full.depth_m, rel)
        np.testing.assert_array_equal(cut.depth_m, np.where(edges, 0.0, full.depth_m))
        np.testing.assert_array_equal(cut.confidence, full.confidence)
    assert depth_edges(full.depth_m, 0.01).any()  # this scene has some


def test_render_keyframe_depth_renders_from_the_overlapping_keyframes_volume(model: GovNeSF) -> None:
    runtime = _filled_runtime(model, min_opacity=0.0)
    kf = keyframe(9, orbit(9), depth_m=None)
    seen: list[object] = []
    render = runtime.render

    def spy(*args: object, **kwargs: object) -> object:
        seen.append(kwargs.get("volume_views"))
        return render(*args, **kwargs)  # type: ignore[arg-type]

    runtime.render = spy  # type: ignore[method-assign]
    by_volume = {}
    for views in (3, 0):
        cfg = GlobalMapConfig(rendered_depth_stride=4, rendered_min_opacity=0.0, rendered_volume_views=views,
                              rendered_edge_rel=0.0)
        by_volume[views] = render_keyframe_depth(runtime, kf, cfg).depth_m
    assert seen == [3, 0]
    direct = render(np.asarray(kf.K) * np.array([10 / 40, 7 / 30, 10 / 40, 7 / 30]), kf.world_from_cam, 10, 7,
                    outputs=("depth",), volume_views=3)
    np.testing.assert_array_equal(by_volume[3], np.where(direct.opacity >= 0.0, direct.depth_m, 0.0))
    assert not np.array_equal(by_volume[3], by_volume[0])
    for bad in (-1, 257, 2.5, True):
        with pytest.raises(ConfigError, match="rendered_volume_views"):
            GlobalMapConfig(rendered_volume_views=bad).validate("test")  # type: ignore[arg-type]


def test_features_swapped_in_after_queueing_are_used(node: MapperNode, model: GovNeSF) -> None:
    """A keyframe queued without ov whose window copy later gains features (the in-process OV
    backend swaps in a featured copy) is fused with those features."""
    import dataclasses

    points = _install(node, model)
    for seq in range(3):
        f = _frame(seq)
        node.handle_ingest(encode(dataclasses.replace(f, ov=None, ov_space=None)))
    assert points.pending == 3
    with node.state.lock:
        window = node.state.window
        featured = [dataclasses.replace(k, ov=np.ones((5, 6, 6), np.float32), ov_space="test-space")
                    for k in window.keyframes]
        window.replace(featured)
    assert points.process_pending() == 3
    assert node.state.global_map.snapshot().has_feature.any()
