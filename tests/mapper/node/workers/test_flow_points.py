"""The dense-flow worker (mapper.node.workers.flow_points) in a node: off the ack path, points on the
plane into the global map with the keyframes' features, status, the bounded queue, map loads, the
rendered-depth check's points, and the serve stages."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from mapper.node.config import config_from_dict
from mapper.node.serve import install_serve_stages
from mapper.node.service import MapperNode
from mapper.node.workers.depth_points import RenderedDepthPoints
from mapper.node.workers.flow_points import DenseFlowPoints
from protocol.messages import encode
from tests.mapper.geometry.test_triangulation import PLANE_Z, make_texture, plane_frame


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return make_texture()


def make_node(tmp_path: Path, **dense_flow: object) -> MapperNode:
    return MapperNode(config_from_dict({
        "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False, "serve_model": False,
        "window": {"max_keyframes": 8, "min_translation_m": 0.05},
        "global_map": {"min_weight": 0.0, "rendered_depth": False},
        "triangulation": {"enabled": False},
        "dense_flow": {"enabled": True, **dense_flow},
    }))


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    mapper = make_node(tmp_path)
    yield mapper
    mapper.stop()


def test_rgb_only_keyframes_get_dense_points_on_the_plane_off_the_ack_path(
    node: MapperNode, texture: np.ndarray
) -> None:
    flow = DenseFlowPoints(node.ctx)
    flow.install()
    assert "dense_flow" in node.ctx.status_providers and any(n == "dense-flow" for n, _ in node.ctx.workers)
    node.handle_ingest(encode(plane_frame(0, texture, depth=True)))  # with depth: a partner candidate only
    for i in (1, 2, 3):
        node.handle_ingest(encode(plane_frame(i, texture)))
    assert flow.pending == 4 and flow.processed == 0  # the acks did not wait
    assert node.ctx.pending_work()["dense_flow"] == 4 and node.ctx.geometry_pending() >= 4
    assert flow.process_pending() == 3
    stats = flow.stats()
    assert stats["keyframes"] == 3 and stats["pending"] == 0 and stats["failed"] == 0
    assert stats["points"] == len(flow.geometry_points()[1]) > 1000
    assert stats["partners_per_keyframe"] >= 1 and stats["mean_ms"] > 0
    xyz, sigma = flow.geometry_points()
    assert np.median(np.abs(xyz[:, 2] - PLANE_Z)) < 0.03 and (sigma > 0).all()
    snap = node.state.global_map.snapshot()
    assert stats["global_map_points"] > 1000 and snap.xyz.shape[0] > 1000
    assert np.median(np.abs(snap.xyz[:, 2] - PLANE_Z)) < 0.03
    # the render path's measured surfaces include them
    assert sum(len(provide()) for provide in node.ctx.surface_points) == len(xyz)


def test_the_rendered_depth_check_sees_the_flow_points(node: MapperNode, texture: np.ndarray) -> None:
    flow = DenseFlowPoints(node.ctx)
    flow.install()
    for i in (0, 1, 2):
        node.handle_ingest(encode(plane_frame(i, texture)))
    flow.process_pending()
    xyz, _ = RenderedDepthPoints(node.ctx, runtime=None)._sparse_points()  # type: ignore[arg-type]  # not rendering
    assert len(xyz) == len(flow.geometry_points()[0]) > 0


def test_queue_is_bounded_and_counts_what_it_drops(tmp_path: Path, texture: np.ndarray) -> None:
    mapper = make_node(tmp_path, max_pending=2)
    try:
        flow = DenseFlowPoints(mapper.ctx)
        flow.install()
        for i in (0, 1, 2, 3):
            mapper.handle_ingest(encode(plane_frame(i, texture)))
        assert flow.pending == 2 and flow.stats()["dropped"] == 2
    finally:
        mapper.stop()


def test_a_keyframe_without_partners_gives_no_points(node: MapperNode, texture: np.ndarray) -> None:
    flow = DenseFlowPoints(node.ctx)
    flow.install()
    node.handle_ingest(encode(plane_frame(0, texture)))
    assert flow.process_pending() == 1
    assert flow.stats()["no_partner"] == 1 and flow.stats()["points"] == 0


def test_a_new_map_forgets_the_candidates_and_points(node: MapperNode, texture: np.ndarray) -> None:
    flow = DenseFlowPoints(node.ctx)
    flow.install()
    for i in (0, 1, 2):
        node.handle_ingest(encode(plane_frame(i, texture)))
    flow.process_pending()
    assert len(flow.geometry_points()[0]) > 0
    flow.on_map_loaded(node.state.global_map, 10**6)
    assert len(flow.geometry_points()[0]) == 0 and not flow._candidates
    # a loaded window's keyframes are the next keyframes' partners: the first one after the load
    # finds partners and adds points, none added for the loaded keyframes themselves
    with node.state.lock:
        loaded = node.state.window.keyframes
    flow.on_map_loaded(node.state.global_map, 10**6 + 1, loaded)
    assert len(flow._candidates) == len(loaded) == 3 and len(flow.geometry_points()[0]) == 0
    no_partner = flow.stats()["no_partner"]
    flow.on_keyframe(plane_frame(3, texture), 10**6 + 2)
    flow.process_pending()
    assert len(flow.geometry_points()[0]) > 0 and flow.stats()["no_partner"] == no_partner


def test_disabled_worker_queues_nothing_and_serve_installs_it_only_when_enabled(
    tmp_path: Path, texture: np.ndarray
) -> None:
    off = make_node(tmp_path / "off", enabled=False)
    on = make_node(tmp_path / "on")
    try:
        assert install_serve_stages(off).dense_flow is None and "dense_flow" not in off.ctx.status_providers
        stages = install_serve_stages(on)
        assert stages.dense_flow is not None and "dense_flow" in on.ctx.status_providers
        flow = DenseFlowPoints(off.ctx, config=off.config.dense_flow)
        flow.on_keyframe(plane_frame(1, texture), 1)
        assert flow.pending == 0
    finally:
        off.stop()
        on.stop()
