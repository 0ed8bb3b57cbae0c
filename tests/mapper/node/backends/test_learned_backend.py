"""Tests for mapper.node.backends.learned: handlers installed on an in-process node (bytes in, bytes out),
govnesf vs fall-through segmentation, not_ready replies, and no model work under the state lock."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.model.field import GovNeSF
from mapper.node.backends import PointAnswer
from mapper.node.backends.learned import install_learned_backend
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from protocol.messages import (
    Error,
    Frame,
    Message,
    Render,
    RenderResult,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    encode,
)
from tests.model_helpers import look_at, tiny_model_config

TINY = tiny_model_config()
SPACE = "test-space"


class FakeEncoder:
    space = SPACE
    dim = 4

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        return np.stack([np.eye(4, dtype=np.float32)[len(t) % 4] for t in texts])


def frame(seq: int, with_ov: bool = True) -> Frame:
    a = 0.6 * seq
    rng = np.random.default_rng(seq)
    return Frame(
        seq=seq,
        stamp_ns=seq,
        width=40,
        height=30,
        K=np.array([32.0, 32.0, 20.0, 15.0]),
        world_from_cam=look_at((2 * np.cos(a), 2 * np.sin(a), 1.2), (0.0, 0.0, 0.5)),
        rgb=rng.integers(0, 256, (30, 40, 3), dtype=np.uint8),
        depth_m=np.full((30, 40), 2.0, np.float32),
        ov=rng.standard_normal((5, 6, 4)).astype(np.float32) if with_ov else None,
        ov_space=SPACE if with_ov else None,
    )


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    config = config_from_dict(
        {
            "map_dir": str(tmp_path / "maps"),
            "autosave_name": "",
            "save_on_exit": False,
            "window": {"max_keyframes": 4},
        }
    )
    mapper = MapperNode(config)  # not started: handle_ingest / handle_query are called directly
    yield mapper
    mapper.stop()


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


def runtime_for(model: GovNeSF) -> ModelRuntime:
    return ModelRuntime(
        ModelRuntimeConfig(device="cpu"), model=model, text_encoder=lambda space: FakeEncoder()
    )


def query(node: MapperNode, msg: Message) -> Message:
    return decode(node.handle_query(encode(msg)), direction="reply")


def test_each_method_goes_to_its_own_backend(node: MapperNode, model: GovNeSF) -> None:
    """A backend registered for ``average`` serves that method; ``govnesf`` goes to the learned
    backend, never to the other one."""
    calls: list[str] = []

    class Average:
        ready = True

        def depth_tested(self, msg: SegmentPoints) -> bool:
            return False

        def segment(self, msg: SegmentPoints, want_cos: bool) -> PointAnswer:
            calls.append(msg.method)
            n = msg.xyz.shape[0]
            return PointAnswer(label=np.zeros(n, np.int32), score=np.full(n, 0.5, np.float32))

    node.segment.register("average", Average())
    install_learned_backend(node, runtime_for(model))
    for seq in range(3):
        node.handle_ingest(encode(frame(seq)))
    xyz = np.array([[0.0, 0.0, 0.5], [0.2, -0.1, 0.6], [0.0, 0.0, 40.0]], np.float32)
    reply = query(node, SegmentPoints(xyz=xyz, texts=["a", "bb"], method="average", id=7))
    assert isinstance(reply, Segmentation) and calls == ["average"] and np.all(reply.score == 0.5)
    reply = query(node, SegmentPoints(xyz=xyz, texts=["a", "bb"], method="govnesf", id=8))
    assert isinstance(reply, Segmentation) and reply.id == 8 and calls == ["average"]  # not the other backend
    assert reply.label.shape == (3,) and reply.label[2] == -1 and set(reply.label[:2]) <= {0, 1}
    assert "total" in reply.timing_ms


def test_render_reply_over_the_wire(node: MapperNode, model: GovNeSF) -> None:
    install_learned_backend(node, runtime_for(model))
    for seq in range(3):
        node.handle_ingest(encode(frame(seq)))
    request = Render(
        width=12,
        height=9,
        K=np.array([10.0, 10.0, 6.0, 4.5]),
        world_from_cam=look_at((2.2, 0.4, 1.1), (0.0, 0.0, 0.5)),
        outputs=["rgb", "depth", "label", "score"],
        texts=["a", "bb", "ccc"],
        id="r1",
    )
    reply = query(node, request)
    assert isinstance(reply, RenderResult) and reply.id == "r1"
    assert reply.rgb is not None and reply.rgb.shape == (9, 12, 3)
    assert reply.depth_m is not None and reply.depth_m.dtype == np.float32
    assert reply.label is not None and reply.score is not None and reply.score.shape == (9, 12, 3)
    status = query(node, StatusRequest())
    assert isinstance(status, Status) and "render" in status.extra["serving"]
    only_rgb = query(
        node, Render(width=4, height=3, K=request.K, world_from_cam=request.world_from_cam, outputs=["rgb"])
    )
    assert isinstance(only_rgb, RenderResult) and only_rgb.depth_m is None and only_rgb.label is None


def test_not_ready_replies_name_what_is_missing(node: MapperNode, model: GovNeSF, tmp_path: Path) -> None:
    missing = tmp_path / "ckpt" / "cpu-small.safetensors"
    install_learned_backend(node, ModelRuntime(ModelRuntimeConfig(checkpoint=str(missing), device="cpu")))
    node.handle_ingest(encode(frame(0)))
    pose = look_at((2.0, 0.0, 1.0), (0.0, 0.0, 0.5))
    reply = query(
        node,
        Render(width=4, height=3, K=np.array([4.0, 4.0, 2.0, 1.5]), world_from_cam=pose, outputs=["rgb"]),
    )
    assert isinstance(reply, Error) and reply.code == "not_ready" and str(missing) in reply.message
    reply = query(node, SegmentPoints(xyz=np.zeros((2, 3), np.float32), texts=["a"]))
    assert isinstance(reply, Error) and reply.code == "not_ready" and str(missing) in reply.message
    status = query(node, StatusRequest())
    assert isinstance(status, Status) and "render" not in status.extra["serving"]


def test_semantic_request_without_ov_is_not_ready_but_colour_renders(
    node: MapperNode, model: GovNeSF
) -> None:
    install_learned_backend(node, runtime_for(model))
    empty = query(node, SegmentPoints(xyz=np.zeros((2, 3), np.float32), texts=["a"]))
    assert isinstance(empty, Error) and empty.code == "not_ready" and "no keyframes" in empty.message
    for seq in range(2):
        node.handle_ingest(encode(frame(seq, with_ov=False)))
    pose = look_at((2.0, 0.0, 1.0), (0.0, 0.0, 0.5))
    K = np.array([4.0, 4.0, 2.0, 1.5])
    colour = query(node, Render(width=4, height=3, K=K, world_from_cam=pose, outputs=["rgb", "depth"]))
    assert isinstance(colour, RenderResult) and colour.rgb is not None
    semantic = query(
        node, Render(width=4, height=3, K=K, world_from_cam=pose, outputs=["label"], texts=["a"])
    )
    assert isinstance(semantic, Error) and semantic.code == "not_ready" and "ov" in semantic.message


def test_callbacks_do_no_model_work_under_the_state_lock(node: MapperNode, model: GovNeSF) -> None:
    runtime = runtime_for(model)
    install_learned_backend(node, runtime)
    for seq in range(6):
        node.handle_ingest(encode(frame(seq)))
    assert len(runtime) == 0 and runtime.pending == 4  # window of 4: recorded, nothing encoded yet
    too_big = query(
        node,
        Render(
            width=4096,
            height=4096,
            K=np.array([9.0, 9.0, 2.0, 2.0]),
            world_from_cam=np.eye(4),
            outputs=["rgb"],
        ),
    )
    assert (
        isinstance(too_big, Error)
        and too_big.code == "bad_request"
        and "max_render_pixels" in too_big.message
    )


@pytest.mark.parametrize("mode", ["auto", "on", "off", "auto-rgb-only"])
def test_render_takes_the_global_maps_surface_where_it_has_one(
    node: MapperNode, model: GovNeSF, mode: str
) -> None:
    from mapper.node.queries import map_surface_depth

    runtime = ModelRuntime(
        ModelRuntimeConfig(device="cpu", surface_from_map=mode.split("-")[0]), model=model,
        text_encoder=lambda space: FakeEncoder(),
    )  # fmt: skip
    install_learned_backend(node, runtime)
    for seq in range(3):
        node.handle_ingest(encode(frame(seq)))
    node.ctx.drain_integrations()
    if mode == "auto-rgb-only":  # auto: the window's keyframes mostly without depth -> march
        for seq in range(3, 8):
            rgb_only = frame(seq)
            rgb_only.depth_m = None
            node.handle_ingest(encode(rgb_only))
        node.ctx.drain_integrations()
    K, pose = np.array([10.0, 10.0, 6.0, 4.5]), look_at((2.2, 0.4, 1.1), (0.0, 0.0, 0.5))
    snap = node.state.global_map.snapshot()
    assert len(snap) > 0
    surface = map_surface_depth(snap, K, pose, 12, 9, runtime.config)
    assert (surface > 0).sum() > 20
    reply = query(node, Render(width=12, height=9, K=K, world_from_cam=pose, outputs=["rgb", "depth"]))
    assert isinstance(reply, RenderResult) and reply.depth_m is not None
    on = surface > 0
    if mode in ("auto", "on"):  # the map's depth where it has a surface, the model's march elsewhere
        np.testing.assert_allclose(reply.depth_m[on], surface[on], rtol=1e-5)
        assert reply.timing_ms["surface_pixels"] == on.sum()
    else:
        assert "surface_pixels" not in reply.timing_ms
        assert not np.allclose(reply.depth_m[on], surface[on], rtol=1e-3)


def _rgb_only_node(node: MapperNode, model: GovNeSF, **overrides: object) -> ModelRuntime:
    """Serve ``model`` on ``node`` with ``[model]`` overrides and stream 4 keyframes without depth."""
    from dataclasses import replace

    runtime = ModelRuntime(replace(ModelRuntimeConfig(device="cpu"), **overrides), model=model,
                           text_encoder=lambda space: FakeEncoder())  # fmt: skip
    install_learned_backend(node, runtime)
    for seq in range(4):  # RGB-only keyframes: the map's surfaces are not measured ones
        rgb_only = frame(seq)
        rgb_only.depth_m = None
        node.handle_ingest(encode(rgb_only))
    node.ctx.drain_integrations()
    return runtime


def test_rgb_only_render_takes_the_surfaces_of_the_measured_geometry(
    node: MapperNode, model: GovNeSF
) -> None:
    from mapper.node.queries import surface_depth

    # surface_from_map = "auto"; the pixels nothing covers marched (the nearest fill: its own test)
    runtime = _rgb_only_node(node, model, surface_nearest_fill_px=0.0)
    yy, zz = np.meshgrid(np.linspace(-1, 1, 60), np.linspace(0, 1.2, 40), indexing="ij")
    wall = np.column_stack([yy.ravel(), zz.ravel()])
    points = np.column_stack([np.full(len(wall), -0.3), wall])  # a plane x = -0.3 m, seen from +x
    node.ctx.surface_points.append(lambda: points)  # what the triangulation plugin provides
    K, pose = np.array([10.0, 10.0, 6.0, 4.5]), look_at((2.2, 0.0, 0.6), (0.0, 0.0, 0.6))
    footprint = runtime.config.surface_geometry_footprint * node.state.global_map.snapshot().voxel_size_m
    expected = surface_depth(points, footprint, K, pose, 12, 9, runtime.config)
    on = expected > 0
    assert on.sum() > 20
    reply = query(node, Render(width=12, height=9, K=K, world_from_cam=pose, outputs=["depth"]))
    assert isinstance(reply, RenderResult) and reply.depth_m is not None
    np.testing.assert_allclose(reply.depth_m[on], expected[on], rtol=1e-5)
    # (the wall's plane adds the pixels the points' splat does not reach: model.surface_planes)
    assert reply.timing_ms["surface_pixels"] == on.sum() + reply.timing_ms["plane_pixels"]
    assert reply.timing_ms["surface_from_geometry"] == 1.0
    np.testing.assert_allclose(reply.depth_m[on], 2.5, rtol=0.01)  # the plane is 2.5 m ahead


@pytest.mark.parametrize("planes", [True, False])
def test_rgb_only_render_takes_the_plane_of_the_geometry_across_a_gap(
    node: MapperNode, model: GovNeSF, planes: bool
) -> None:
    from mapper.node.queries import surface_depth

    runtime = _rgb_only_node(node, model, surface_planes=planes, surface_nearest_fill_px=0.0)
    # a wall x = -0.3 m with no measured points in the band 0.3 m < z < 0.9 m (flat-shaded there)
    yy, zz = np.meshgrid(np.linspace(-1, 1, 60), np.linspace(0, 1.2, 40), indexing="ij")
    wall = np.column_stack([np.full(yy.size, -0.3), yy.ravel(), zz.ravel()])
    points = wall[(wall[:, 2] < 0.3) | (wall[:, 2] > 0.9)]
    node.ctx.surface_points.append(lambda: points)
    K, pose = np.array([40.0, 40.0, 24.0, 18.0]), look_at((2.2, 0.0, 0.6), (0.0, 0.0, 0.6))
    footprint = runtime.config.surface_geometry_footprint * node.state.global_map.snapshot().voxel_size_m
    splat = surface_depth(points, footprint, K, pose, 48, 36, runtime.config)
    gap = np.zeros((36, 48), bool)
    gap[13:23, 20:28] = True  # rows of 0.3 m < z < 0.9 m around the image centre, on the wall
    assert (splat[gap] == 0).all()  # the points leave the band empty (too wide to fill)
    reply = query(node, Render(width=48, height=36, K=K, world_from_cam=pose, outputs=["depth"]))
    assert isinstance(reply, RenderResult) and reply.depth_m is not None
    on = splat > 0
    np.testing.assert_allclose(reply.depth_m[on], splat[on], rtol=1e-5)  # the points' own surfaces
    if planes:  # the band is rendered at the wall's plane, 2.5 m ahead
        assert reply.timing_ms["planes"] == 1.0 and reply.timing_ms["plane_pixels"] >= gap.sum()
        np.testing.assert_allclose(reply.depth_m[gap], 2.5, rtol=0.01)
        assert reply.timing_ms["surface_pixels"] == on.sum() + reply.timing_ms["plane_pixels"]
    else:
        assert "planes" not in reply.timing_ms and reply.timing_ms["surface_pixels"] == on.sum()


@pytest.mark.parametrize("fill", [True, False])
def test_rgb_only_render_fills_from_the_map_where_the_geometry_has_no_surface(
    node: MapperNode, model: GovNeSF, fill: bool
) -> None:
    """``model.surface_map_fill``: pixels the RGB-only geometry leaves take the global map's
    splatted surface (and only those: the geometry's own pixels keep the geometry's depth)."""
    from dataclasses import replace

    from mapper.node.queries import surface_depth

    config = replace(ModelRuntimeConfig(device="cpu"), surface_planes=False, surface_map_fill=fill,
                     surface_nearest_fill_px=0.0)
    runtime = ModelRuntime(config, model=model, text_encoder=lambda space: FakeEncoder())
    install_learned_backend(node, runtime)
    for seq in range(3):  # with depth: the global map gets surface points
        node.handle_ingest(encode(frame(seq)))
    node.ctx.drain_integrations()
    for seq in range(3, 8):  # then mostly RGB-only: renders take the measured geometry
        rgb_only = frame(seq)
        rgb_only.depth_m = None
        node.handle_ingest(encode(rgb_only))
    node.ctx.drain_integrations()
    snap = node.state.global_map.snapshot()
    points = snap.xyz[snap.xyz[:, 1] > 0.0]  # the geometry covers part of what the map covers
    node.ctx.surface_points.append(lambda: points)
    K, pose = np.array([10.0, 10.0, 6.0, 4.5]), look_at((2.2, 0.4, 1.1), (0.0, 0.0, 0.5))
    footprint = config.surface_geometry_footprint * snap.voxel_size_m
    geometry = surface_depth(points, footprint, K, pose, 12, 9, config)
    whole = surface_depth(snap.xyz, snap.voxel_size_m, K, pose, 12, 9, config)
    only_map = (geometry == 0) & (whole > 0)
    assert (geometry > 0).sum() > 5 and only_map.sum() > 5
    reply = query(node, Render(width=12, height=9, K=K, world_from_cam=pose, outputs=["depth"]))
    assert isinstance(reply, RenderResult) and reply.depth_m is not None
    on = geometry > 0
    np.testing.assert_allclose(reply.depth_m[on], geometry[on], rtol=1e-5)
    if fill:
        np.testing.assert_allclose(reply.depth_m[only_map], whole[only_map], rtol=1e-5)
        assert reply.timing_ms["surface_pixels"] == on.sum() + only_map.sum()
    else:
        assert reply.timing_ms["surface_pixels"] == on.sum()
        assert not np.allclose(reply.depth_m[only_map], whole[only_map], rtol=1e-3)  # marched there


@pytest.mark.parametrize("reach", [0.0, 2.0, 10_000.0])
def test_rgb_only_render_fills_the_rest_from_the_nearest_surface(
    node: MapperNode, model: GovNeSF, reach: float
) -> None:
    """``model.surface_nearest_fill_px``: pixels no measured surface covers take the nearest covered
    pixel's depth within that reach (0: marched); covered pixels keep theirs."""
    from mapper.geometry.splat import fill_nearest
    from mapper.node.queries import surface_depth

    runtime = _rgb_only_node(node, model, surface_planes=False, surface_nearest_fill_px=reach)
    config = runtime.config
    yy, zz = np.meshgrid(np.linspace(-1, 1, 60), np.linspace(0, 0.5, 20), indexing="ij")
    points = np.column_stack([np.full(yy.size, -0.3), yy.ravel(), zz.ravel()])  # the wall's lower part
    node.ctx.surface_points.append(lambda: points)
    K, pose = np.array([10.0, 10.0, 6.0, 4.5]), look_at((2.2, 0.0, 0.6), (0.0, 0.0, 0.6))
    footprint = config.surface_geometry_footprint * node.state.global_map.snapshot().voxel_size_m
    splat = surface_depth(points, footprint, K, pose, 12, 9, config)
    on = splat > 0
    assert 5 < on.sum() < on.size - 5  # the upper rows see no measured point
    reply = query(node, Render(width=12, height=9, K=K, world_from_cam=pose, outputs=["depth"]))
    assert isinstance(reply, RenderResult) and reply.depth_m is not None
    np.testing.assert_allclose(reply.depth_m[on], splat[on], rtol=1e-5)
    filled = fill_nearest(splat, reach) if reach > 0 else splat
    assert reply.timing_ms["surface_pixels"] == (filled > 0).sum()
    extra = (filled > 0) & ~on
    np.testing.assert_allclose(reply.depth_m[extra], filled[extra], rtol=1e-5)
    if reach >= 10_000:
        assert (filled > 0).all()
    if reach == 0:
        assert not extra.any()


def test_map_features_use_the_depth_test_while_the_window_has_depth(tmp_path: Path) -> None:
    """``global_map.learned_features_depth_test``: the blended features written into the map come
    from the model's depth-tested view selection while the window's keyframes carry input depth,
    from every view without depth or with the setting off."""
    from mapper.node.backends.learned import install_pre_eviction_features

    calls: list[bool] = []

    class Runtime:
        def point_features(self, xyz: np.ndarray, *, use_depth: bool = False) -> tuple[np.ndarray, ...]:
            calls.append(use_depth)
            return np.zeros((len(xyz), 4), np.float32), np.zeros(len(xyz), bool)

    for depth_test, with_depth, want in ((True, True, True), (True, False, False), (False, True, False)):
        config = config_from_dict({"map_dir": str(tmp_path / "maps"), "autosave_name": "",
                                   "save_on_exit": False,
                                   "global_map": {"learned_features_depth_test": depth_test}})
        mapper = MapperNode(config)
        try:
            worker = install_pre_eviction_features(mapper.ctx, Runtime())  # type: ignore[arg-type]
            for seq in range(3):
                f = frame(seq)
                if not with_depth:
                    f.depth_m = None
                mapper.handle_ingest(encode(f))
            calls.clear()
            worker.features(np.zeros((2, 3), np.float32))
            assert calls == [want], (depth_test, with_depth)
        finally:
            mapper.stop()


def test_mix_answers_blends_where_both_answer_and_keeps_each_alone() -> None:
    from mapper.node.answers.segment import mix_answers

    learned = PointAnswer(label=np.array([0, 1, -1], np.int32), score=np.array([0.9, 0.6, 0.0], np.float32),
                          seen=np.array([True, True, False]),
                          cos=np.array([[0.9, 0.1], [0.5, 0.6], [0.0, 0.0]], np.float32))
    averaging = PointAnswer(label=np.array([1, 0, 1], np.int32), score=np.array([0.8, 0.9, 0.7], np.float32),
                            seen=np.array([True, True, True]),
                            cos=np.array([[0.2, 0.8], [0.9, 0.1], [0.1, 0.7]], np.float32),
                            map_only=np.array([False, False, True]))
    mixed = mix_answers(learned, averaging, 0.5)
    # point 0: 0.55 / 0.45 -> text 0; point 1: 0.7 / 0.35 -> text 0; point 2: averaging's alone
    assert mixed.label.tolist() == [0, 0, 1]
    np.testing.assert_allclose(mixed.score, [0.55, 0.7, 0.7], atol=1e-6)
    assert mixed.answered().tolist() == [True, True, True]
    assert mixed.map_only is not None and mixed.map_only.tolist() == [False, False, True]
    assert mix_answers(learned, averaging, 0.0).label.tolist()[:2] == [0, 1]  # the model's where it answers
    no_cos = PointAnswer(label=learned.label, score=learned.score)
    assert mix_answers(no_cos, averaging, 0.5) is no_cos


def test_mix_answers_takes_a_weight_per_point() -> None:
    """``queries.learned_evicted_views`` mixes with a weight per point (the evicted views' share
    of its views): 0 keeps the model's answer, 1 takes the other's, in between the blend."""
    from mapper.node.answers.segment import mix_answers

    cos_l = np.array([[0.9, 0.1], [0.9, 0.1], [0.6, 0.4]], np.float32)
    cos_a = np.array([[0.1, 0.9], [0.1, 0.9], [0.2, 0.8]], np.float32)
    seen = np.ones(3, bool)
    learned = PointAnswer(label=np.zeros(3, np.int32), score=cos_l[:, 0].copy(), seen=seen, cos=cos_l)
    other = PointAnswer(label=np.ones(3, np.int32), score=cos_a[:, 1].copy(), seen=seen, cos=cos_a)
    mixed = mix_answers(learned, other, np.array([0.0, 1.0, 0.2], np.float32))
    assert mixed.label.tolist() == [0, 1, 0]  # point 2: 0.8 * (0.6, 0.4) + 0.2 * (0.2, 0.8) = (0.52, 0.48)
    np.testing.assert_allclose(mixed.cos[2], [0.52, 0.48], atol=1e-6)
    np.testing.assert_allclose(mixed.score[:2], [0.9, 0.9], atol=1e-6)



def test_toward_averaging_moves_by_how_far_the_averaging_is_more_decided() -> None:
    """``queries.learned_toward_average``: the learned answer stays where the averaging's margin is
    not ``ratio`` times its own; where it leads that by ``d``, the mix takes ``min(1, d / ramp)``
    of it; a point only the averaging answers takes its answer; the flags mark changed labels."""
    from mapper.node.answers.segment import toward_averaging

    cos_l = np.array([[0.6, 0.2], [0.45, 0.4], [0.45, 0.4], [0.0, 0.0], [0.5, 0.1]], np.float32)
    cos_a = np.array([[0.3, 0.5], [0.2, 0.6], [0.38, 0.42], [0.1, 0.7], [0.0, 0.0]], np.float32)
    label_l = np.array([0, 0, 0, -1, 0], np.int32)
    label_a = np.array([1, 1, 1, 1, -1], np.int32)
    score_l, score_a = cos_l.max(1), cos_a.max(1)
    label, score, took = toward_averaging(label_l, score_l, cos_l, label_a, score_a, cos_a, 1.0, 0.2)
    # 0: learned margin 0.4 >= 0.2: stays; 1: 0.05 vs 0.4, w = 1: the averaging's (0.2, 0.6);
    # 2: 0.05 vs 0.04: stays; 3: only the averaging answers; 4: only the learned one
    assert label.tolist() == [0, 1, 0, 1, 0]
    np.testing.assert_allclose(score, [0.6, 0.6, 0.45, 0.7, 0.5], atol=1e-6)
    assert took.tolist() == [False, True, False, True, False]
    # ratio 10: point 1's averaging margin (0.4) is below 10 x 0.05: the learned answer stays
    label, _, took = toward_averaging(label_l, score_l, cos_l, label_a, score_a, cos_a, 10.0, 0.2)
    assert label.tolist() == [0, 0, 0, 1, 0] and took.tolist() == [False, False, False, True, False]
    # a partial weight: margins 0.05 (learned) and 0.15 (averaging), scale 0.2: w = 0.5
    half_l, half_a = np.array([[0.45, 0.4]], np.float32), np.array([[0.3, 0.45]], np.float32)
    one, top = np.array([0], np.int32), np.array([0.45], np.float32)
    label, score, took = toward_averaging(one, top, half_l, one + 1, top, half_a, 1.0, 0.2)
    assert label.tolist() == [1] and took.tolist() == [True]  # (0.375, 0.425)
    np.testing.assert_allclose(score, [0.425], atol=1e-6)


class _WallRuntime:
    """A runtime whose render sees a wall at z = 2 (opacity 0 in the first column) and whose
    blended feature at a point is (x, y, z, 1)."""

    def __init__(self) -> None:
        self.rendered: list[tuple[np.ndarray, int, int]] = []

    def render(self, K: np.ndarray, pose: np.ndarray, w: int, h: int, outputs: Sequence[str],
               volume_views: int | None = None) -> object:
        from types import SimpleNamespace

        self.rendered.append((np.asarray(K), w, h))
        opacity = np.ones((h, w), np.float32)
        opacity[:, 0] = 0.0
        return SimpleNamespace(depth_m=np.full((h, w), 2.0, np.float32), opacity=opacity)

    def point_features(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([xyz, np.ones((len(xyz), 1), np.float32)], axis=1), np.ones(len(xyz), bool)


def test_learned_view_map_takes_the_blend_at_each_cells_rendered_surface() -> None:
    """Each cell of the grid: its ray through the cell centre (K scaled to the grid) meets the
    rendered surface, and the blended feature there is the cell's; cells whose ray meets no
    surface (opacity below the threshold) are not valid."""
    from types import SimpleNamespace

    from mapper.node.backends.learned import learned_view_map

    K = np.array([80.0, 80.0, 80.0, 60.0])
    pose = np.eye(4)
    pose[:3, 3] = [0.5, 0.0, 0.0]
    keyframe = SimpleNamespace(rgb=np.zeros((120, 160, 3), np.uint8), K=K, world_from_cam=pose)
    runtime = _WallRuntime()
    got = learned_view_map(runtime, keyframe, (15, 20), 0.5)  # type: ignore[arg-type]
    assert got is not None
    feats, valid = got
    assert feats.shape == (15, 20, 4) and valid.shape == (15, 20)
    assert not valid[:, 0].any() and valid[:, 1:].all()
    np.testing.assert_allclose(runtime.rendered[0][0], [10.0, 10.0, 10.0, 7.5])  # K at 1/8
    # the cell (row 7, col 10): its centre (10.5, 7.5) in the grid is pixel (84, 60) of the image
    want = np.array([0.5 + (84.0 - 80.0) / 80.0 * 2.0, (60.0 - 60.0) / 80.0 * 2.0, 2.0, 1.0])
    np.testing.assert_allclose(feats[7, 10], want, atol=1e-5)
    assert np.allclose(feats[:, 1:, 2], 2.0) and (feats[:, 0] == 0).all()
