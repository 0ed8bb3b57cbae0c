"""The learned model per robot window (:mod:`mapper.node.backends.robot_runtimes`): two robots 12 m
apart each get a runtime of their own on the one loaded network, holding only their own keyframes
(cost-volume bounds around their own room); ``govnesf`` answers in both places; a render goes to the
runtime of the robot nearest the camera; with one robot the given runtime serves alone."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.model.field import GovNeSF
from mapper.node.backends.learned import install_learned_backend
from mapper.node.backends.robot_runtimes import RobotRuntimes
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from protocol.messages import Frame, Segmentation, SegmentPoints, Status, StatusRequest, decode, encode
from tests.mapper.node.backends.test_learned_backend import frame, runtime_for

OFFSET_M = 12.0


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    from tests.mapper.node.backends.test_learned_backend import TINY

    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    config = config_from_dict({"map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False,
                               "window": {"max_keyframes": 4}, "global_map": {"integrate_queue": 0}})
    mapper = MapperNode(config)
    yield mapper
    mapper.stop()


def robot_frame(seq: int, robot: str) -> Frame:
    out = copy.copy(frame(seq))
    out.robot = robot
    if robot == "b":
        shift = np.eye(4)
        shift[0, 3] = OFFSET_M
        out.world_from_cam = shift @ out.world_from_cam
    return out


def test_each_robot_has_its_own_runtime(node: MapperNode, model: GovNeSF) -> None:
    primary = runtime_for(model)
    install_learned_backend(node, primary)
    for seq in range(6):
        for robot in ("a", "b"):
            node.handle_ingest(encode(robot_frame(seq, robot)))
    backend = node.segment.backends["govnesf"]
    robots = backend.runtime  # type: ignore[attr-defined]
    assert isinstance(robots, RobotRuntimes)
    runtimes = robots.runtimes()
    assert list(runtimes) == ["a", "b"] and runtimes["a"] is primary
    assert runtimes["b"].model is primary.model  # one network
    for robot, runtime in runtimes.items():
        runtime.sync()
        assert len(runtime) == len(node.state.window.robot_keyframes(robot)) == 4
        assert runtime.bounds is not None
    centre_a = np.asarray(runtimes["a"].bounds.origin_m)  # type: ignore[union-attr]
    centre_b = np.asarray(runtimes["b"].bounds.origin_m)  # type: ignore[union-attr]
    assert centre_b[0] - centre_a[0] == pytest.approx(OFFSET_M, abs=1.0)  # each volume around its room
    xyz = np.array([[0.0, 0.0, 0.5], [OFFSET_M, 0.0, 0.5], [OFFSET_M / 2, 0.0, 40.0]], np.float32)
    reply = decode(node.handle_query(encode(SegmentPoints(xyz=xyz, texts=["a", "bb"], method="govnesf"))),
                   direction="reply")
    assert isinstance(reply, Segmentation)
    assert reply.label[0] >= 0 and reply.label[1] >= 0 and reply.label[2] == -1
    # the answer in each room is its own robot's runtime's
    for i, runtime in ((0, runtimes["a"]), (1, runtimes["b"])):
        label, _, _ = runtime.segment(xyz[i : i + 1], ["a", "bb"])
        assert label[0] >= 0
    near_b = np.asarray(robot_frame(0, "b").world_from_cam)
    assert robots.render_runtime(near_b) is runtimes["b"]
    status = decode(node.handle_query(encode(StatusRequest())), direction="reply")
    assert isinstance(status, Status)
    stats = status.extra["model"]
    assert set(stats["robots"]) == {"a", "b"} and stats["views"] == 8


def test_one_robot_is_served_by_the_given_runtime(node: MapperNode, model: GovNeSF) -> None:
    primary = runtime_for(model)
    install_learned_backend(node, primary)
    for seq in range(4):
        node.handle_ingest(encode(frame(seq)))
    robots = node.segment.backends["govnesf"].runtime  # type: ignore[attr-defined]
    assert robots.runtimes() == {"": primary}
    xyz = np.array([[0.0, 0.0, 0.5], [0.2, -0.1, 0.6]], np.float32)
    want = primary.segment_cosines(xyz, ["a", "bb"])
    got = robots.segment_cosines(xyz, ["a", "bb"])
    for g, w in zip(got[:3], want[:3], strict=True):
        np.testing.assert_array_equal(g, w)
    assert "robots" not in robots.stats()
