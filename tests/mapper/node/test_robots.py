"""Several robots at once into one node (``Frame.robot``): two simulated robots stream interleaved
frames in two rooms 12 m apart. Each robot's window holds only its own keyframes, the same ones as
when its room is streamed alone; both rooms reach the one global map (room A's part as when room A
is streamed alone); queries answer in both rooms from the windows; ``status`` counts keyframes per
robot; a bad robot name, or one robot beyond ``window.max_robots``, is refused and changes nothing;
a saved map keeps its keyframes' robots."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from clients.sim.export import RecordConfig, SimStream
from mapper.node.service import MapperNode
from protocol.messages import (
    Ack,
    Error,
    Frame,
    Load,
    Ok,
    Save,
    Segmentation,
    SegmentPoints,
    StatusRequest,
    decode,
    encode,
)
from tests.node_helpers import in_process_node

OFFSET_M = 12.0
FRAMES = 14
WINDOW = {"max_keyframes": 5, "max_robots": 2}


class Room:
    def __init__(self, seed: int, offset_m: float) -> None:
        config = RecordConfig(seed=seed, style="apartment", frames=FRAMES, width=64, height=48, depth=True,
                              ov=True, novel_views=0, previews=0)
        stream = SimStream.build(config)
        shift = np.eye(4)
        shift[0, 3] = offset_m
        self.frames: list[Frame] = []
        for frame, _ in stream.frames():
            frame.world_from_cam = shift @ frame.world_from_cam
            self.frames.append(frame)
        xyz, _, _ = stream.scene.sample_surface(300, seed=seed)
        self.xyz = (xyz + shift[:3, 3]).astype(np.float32)
        self.low, self.high = self.xyz.min(axis=0) - 1.0, self.xyz.max(axis=0) + 1.0


@pytest.fixture(scope="module")
def rooms() -> tuple[Room, Room]:
    return Room(1, 0.0), Room(2, OFFSET_M)


def named(frames: list[Frame], robot: str) -> list[Frame]:
    out = []
    for frame in frames:
        mine = copy.copy(frame)
        mine.robot = robot
        out.append(mine)
    return out


def node_for(tmp_path: Path) -> MapperNode:
    return in_process_node(tmp_path, global_map={"integrate_queue": 0}, window=WINDOW)


def send(node: MapperNode, frame: Frame | dict[str, Any]) -> Any:
    data = msgpack.packb(frame, use_bin_type=True) if isinstance(frame, dict) else encode(frame)
    return decode(node.handle_ingest(data), direction="reply")


def interleaved(node: MapperNode, a: list[Frame], b: list[Frame]) -> None:
    for fa, fb in zip(a, b, strict=True):
        for frame in (fa, fb):
            reply = send(node, frame)
            assert isinstance(reply, Ack) and reply.status in ("keyframe", "accepted"), reply


def in_box(xyz: np.ndarray, room: Room) -> np.ndarray:
    return np.all((xyz >= room.low) & (xyz <= room.high), axis=1)


def ask(node: MapperNode, msg: Any) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def test_two_robots_in_two_rooms(tmp_path: Path, rooms: tuple[Room, Room]) -> None:
    room_a, room_b = rooms
    both = node_for(tmp_path / "both")
    interleaved(both, named(room_a.frames, "a"), named(room_b.frames, "b"))
    alone = node_for(tmp_path / "alone")
    for frame in room_a.frames:  # the default robot
        assert isinstance(send(alone, frame), Ack)
    windows = both.state.window
    kf_a, kf_b = windows.robot_keyframes("a"), windows.robot_keyframes("b")
    # each window holds its own robot's keyframes only, the ones its room alone makes
    assert {k.robot for k in kf_a} == {"a"} and {k.robot for k in kf_b} == {"b"}
    assert [k.seq for k in kf_a] == [k.seq for k in alone.state.window.keyframes]
    assert all(k.world_from_cam[0, 3] < OFFSET_M / 2 < j.world_from_cam[0, 3] for k in kf_a for j in kf_b)
    status = ask(both, StatusRequest())
    assert status.extra["robots"] == {"a": len(kf_a), "b": len(kf_b)}
    assert status.keyframes == len(kf_a) + len(kf_b)
    assert status.extra["max_robots"] == 2
    # both rooms are in the one map, room A's part as when room A streamed alone
    xyz = both.state.global_map.snapshot().xyz
    alone_xyz = alone.state.global_map.snapshot().xyz
    assert in_box(xyz, room_b).sum() > 1000
    np.testing.assert_array_equal(np.sort(xyz[in_box(xyz, room_a)], axis=0), np.sort(alone_xyz, axis=0))
    # the windows answer in both rooms: room A's points as when room A streamed alone
    texts = ["chair", "table", "wall", "floor"]
    got = ask(both, SegmentPoints(xyz=room_a.xyz, texts=texts, method="average"))
    want = ask(alone, SegmentPoints(xyz=room_a.xyz, texts=texts, method="average"))
    assert isinstance(got, Segmentation) and isinstance(want, Segmentation)
    assert np.count_nonzero(want.source == 1) > 50
    np.testing.assert_array_equal(got.source, want.source)
    np.testing.assert_array_equal(got.label, want.label)
    got = ask(both, SegmentPoints(xyz=room_b.xyz, texts=texts, method="average"))
    assert isinstance(got, Segmentation) and np.count_nonzero(got.source == 1) > 50


def test_a_bad_robot_name_or_one_robot_too_many_changes_nothing(tmp_path: Path,
                                                                 rooms: tuple[Room, Room]) -> None:
    room_a, room_b = rooms
    node = node_for(tmp_path)
    interleaved(node, named(room_a.frames[:3], "a"), named(room_b.frames[:3], "b"))
    before = (node.state.map_version, node.state.window.keyframes, len(node.state.global_map),
              node.state.window.robots)
    bad = named(room_a.frames[3:4], "a")[0].to_wire()
    for name in ("a b", "x" * 33, 7):
        reply = send(node, {**bad, "robot": name})
        assert isinstance(reply, Error) and reply.code == "bad_request" and "robot" in reply.message, reply
    third = named(room_a.frames[5:6], "c")[0]
    reply = send(node, third)
    assert isinstance(reply, Error) and reply.code == "bad_request" and "max_robots" in reply.message, reply
    after = (node.state.map_version, node.state.window.keyframes, len(node.state.global_map),
             node.state.window.robots)
    assert after == before
    assert isinstance(send(node, named(room_a.frames[8:9], "a")[0]), Ack)  # the known robots go on


def test_a_saved_map_keeps_its_robots(tmp_path: Path, rooms: tuple[Room, Room]) -> None:
    room_a, room_b = rooms
    node = node_for(tmp_path)
    interleaved(node, named(room_a.frames[:6], "a"), named(room_b.frames[:6], "b"))
    counts = node.state.window.counts()
    assert isinstance(ask(node, Save(name="two")), Ok)
    fresh = node_for(tmp_path)
    assert isinstance(ask(fresh, Load(name="two")), Ok)
    assert fresh.state.window.counts() == counts
    assert [(k.robot, k.seq) for k in fresh.state.window.keyframes] == \
        [(k.robot, k.seq) for k in node.state.window.keyframes]
    small = in_process_node(tmp_path, global_map={"integrate_queue": 0}, window={**WINDOW, "max_robots": 1})
    reply = ask(small, Load(name="two"))
    assert isinstance(reply, Error) and reply.code == "bad_request" and "max_robots" in reply.message
    assert len(small.state.window) == 0 and small.state.map_version == 0
