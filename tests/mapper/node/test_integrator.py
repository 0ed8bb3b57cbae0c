"""The keyframe integrator (``global_map.integrate_queue``): a keyframe is in the window when it is
acked and in the global map shortly after; the backlog is bounded (the ingest thread waits for
room, nothing acked is dropped); ``save`` first integrates everything acked before it; ``status``
reports the integrator. No timing is asserted: the integrator is held with a blocking listener."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from clients.harness import synthetic_frame
from mapper.map.window import Keyframe
from mapper.node.service import MapperNode
from mapper.node.store import MapStore
from protocol.messages import Ack, Load, Ok, Save, Status, StatusRequest, decode, encode
from tests.node_helpers import in_process_node

N_FRAMES = 12
WAIT_S = 20.0  # generous deadline for polling loops (never a pass/fail timing)


def _node(tmp_path: Path, integrate_queue: int, **extra: Any) -> MapperNode:
    return in_process_node(
        tmp_path,
        serve_model=False,
        global_map={"integrate_queue": integrate_queue},
        window={"min_translation_m": 0.0},  # every frame a keyframe
        **extra,
    )


def _frames() -> list[bytes]:
    return [encode(synthetic_frame(seq, n_frames=N_FRAMES)) for seq in range(N_FRAMES)]


def _ingest(node: MapperNode, data: bytes) -> Ack:
    reply = decode(node.handle_ingest(data), direction="reply")
    assert isinstance(reply, Ack), reply
    return reply


def _status(node: MapperNode) -> dict[str, Any]:
    reply = decode(node.handle_query(encode(StatusRequest(id=1))), direction="reply")
    assert isinstance(reply, Status)
    return reply.extra


def _until(what: str, cond: Any) -> None:
    deadline = time.monotonic() + WAIT_S
    while not cond():
        assert time.monotonic() < deadline, f"never: {what}"
        time.sleep(0.01)


class _Gate:
    """A keyframe listener that holds the integrator until released (counts the keyframes)."""

    def __init__(self) -> None:
        self.open = threading.Event()
        self.seen: list[int] = []

    def __call__(self, keyframe: Keyframe, version: int) -> None:
        self.seen.append(keyframe.seq)
        self.open.wait(WAIT_S)


def _reference_map(tmp_path: Path, frames: list[bytes]) -> dict[str, np.ndarray]:
    """The global map of the same frames integrated inline (integrate_queue = 0), as saved."""
    node = _node(tmp_path / "ref", integrate_queue=0)
    for data in frames:
        assert _ingest(node, data).status == "keyframe"
    arrays, _ = node.state.global_map.to_arrays()
    return arrays


def test_acked_keyframe_is_in_the_window_at_once_and_integrated_after_a_drain(tmp_path: Path) -> None:
    node = _node(tmp_path, integrate_queue=64)
    gate = _Gate()
    node.ctx.keyframe_listeners.append(gate)
    node.start()
    try:
        frames = _frames()
        for count, data in enumerate(frames, 1):
            assert _ingest(node, data).status == "keyframe"
            assert len(node.state.window) == count  # in the window when acked
        integration = _status(node)["integration"]
        assert integration["background"] is True and integration["queue_length"] == 64
        assert integration["backlog"] >= len(frames) - 1  # the gate holds the integrator
        assert node.state.global_map.keyframes_integrated <= 1
        gate.open.set()
        node.ctx.drain_integrations()
        integration = _status(node)["integration"]
        assert integration["backlog"] == 0 and integration["integrated"] == len(frames)
        assert integration["errors"] == 0 and integration["inline"] == 0
        assert integration["lag_ms_p50"] is not None and integration["lag_ms_p95"] is not None
        assert node.state.global_map.keyframes_integrated == len(frames)
        assert gate.seen == list(range(len(frames)))  # listeners in ack order, after the integrate
        ours, _ = node.state.global_map.to_arrays()
    finally:
        gate.open.set()
        node.stop()
    reference = _reference_map(tmp_path, frames)
    assert ours.keys() == reference.keys()
    for key in reference:
        np.testing.assert_array_equal(ours[key], reference[key], err_msg=key)


def test_backlog_is_bounded_and_a_full_queue_holds_the_ack(tmp_path: Path) -> None:
    node = _node(tmp_path, integrate_queue=2)
    gate = _Gate()
    node.ctx.keyframe_listeners.append(gate)
    node.start()
    try:
        frames = _frames()
        _ingest(node, frames[0])
        _until("the integrator holds keyframe 0", lambda: gate.seen == [0])
        _ingest(node, frames[1])
        _ingest(node, frames[2])  # the queue (2) is full now
        assert _status(node)["integration"]["backlog"] == 3  # 1 being integrated + 2 queued
        acks: list[Ack] = []
        sender = threading.Thread(target=lambda: acks.extend(_ingest(node, d) for d in frames[3:6]))
        sender.start()
        sender.join(0.3)
        assert sender.is_alive() and not acks  # waiting for room: backpressure, not a drop
        assert len(node.state.window) == 4  # frame 3 is in the window, its ack waits
        assert _status(node)["integration"]["backlog"] <= 2 + 1 + 1
        gate.open.set()
        sender.join(WAIT_S)
        assert not sender.is_alive() and [a.status for a in acks] == ["keyframe"] * 3
        node.ctx.drain_integrations()
        integration = _status(node)["integration"]
        assert integration["backpressure_waits"] >= 1 and integration["backpressure_s"] > 0
        assert integration["backlog"] == 0 and integration["integrated"] == 6
        assert gate.seen == list(range(6))
    finally:
        gate.open.set()
        node.stop()


def test_save_contains_every_acked_keyframe(tmp_path: Path) -> None:
    node = _node(tmp_path, integrate_queue=64)
    gate = _Gate()
    node.ctx.keyframe_listeners.append(gate)
    node.start()
    frames = _frames()
    try:
        for data in frames:
            _ingest(node, data)
        assert _status(node)["integration"]["backlog"] > 0
        replies: list[Any] = []
        save = encode(Save(name="s", id=2))
        saver = threading.Thread(
            target=lambda: replies.append(decode(node.handle_query(save), direction="reply"))
        )
        saver.start()
        saver.join(0.2)
        assert saver.is_alive()  # the save waits for the backlog
        gate.open.set()
        saver.join(WAIT_S)
        assert len(replies) == 1 and isinstance(replies[0], Ok), replies
    finally:
        gate.open.set()
        node.stop()
    arrays, manifest = MapStore(tmp_path / "maps").load("s")
    assert len(manifest["keyframes"]) == len(frames)
    assert manifest["global_map"]["keyframes_integrated"] == len(frames)
    reference = _reference_map(tmp_path, frames)
    for key, value in reference.items():
        np.testing.assert_array_equal(arrays[key], value, err_msg=key)


def test_inline_mode_and_stop_drain(tmp_path: Path) -> None:
    inline = _node(tmp_path / "a", integrate_queue=0)
    inline.start()
    try:
        frames = _frames()[:4]
        for data in frames:
            _ingest(inline, data)
            # integrated before the ack
            assert inline.state.global_map.keyframes_integrated == len(inline.state.window)
        integration = _status(inline)["integration"]
        assert integration["background"] is False and integration["inline"] == 4
        assert integration["backlog"] == 0
    finally:
        inline.stop()
    # stop() finishes the queue before the final save
    node = _node(tmp_path / "b", integrate_queue=64, autosave_name="auto", save_on_exit=True)
    gate = _Gate()
    node.ctx.keyframe_listeners.append(gate)
    node.start()
    for data in frames:
        _ingest(node, data)
    gate.open.set()
    assert node.stop() == 0
    _, manifest = MapStore(tmp_path / "b" / "maps").load("auto")
    assert manifest["global_map"]["keyframes_integrated"] == len(frames)


def test_a_failing_listener_is_counted_and_the_backlog_still_drains(tmp_path: Path) -> None:
    node = _node(tmp_path, integrate_queue=8)

    def broken(keyframe: Keyframe, version: int) -> None:
        raise RuntimeError("listener bug")

    node.ctx.keyframe_listeners.append(broken)
    node.start()
    try:
        for data in _frames()[:3]:
            _ingest(node, data)
        node.ctx.drain_integrations()
        integration = _status(node)["integration"]
        assert integration["errors"] == 3 and integration["integrated"] == 3
        assert integration["backlog"] == 0
    finally:
        node.stop()


def test_keyframes_pending_at_a_load_stay_out_of_the_loaded_map(tmp_path: Path) -> None:
    frames = _frames()
    saved = _node(tmp_path / "saved", integrate_queue=0)
    for data in frames[6:]:
        _ingest(saved, data)
    saved.persistence.save_to("m", reason="test")
    expected, _ = saved.state.global_map.to_arrays()
    node = _node(tmp_path, integrate_queue=8, map_dir=str(tmp_path / "saved" / "maps"))
    gate = _Gate()
    node.ctx.keyframe_listeners.append(gate)
    node.start()
    try:
        _ingest(node, frames[0])
        _until("the integrator holds keyframe 0", lambda: gate.seen == [0])
        _ingest(node, frames[1])  # queued for the map that the load replaces
        reply = decode(node.handle_query(encode(Load(name="m", id=3))), direction="reply")
        assert isinstance(reply, Ok), reply
        gate.open.set()
        node.ctx.drain_integrations()
        assert gate.seen == [0]  # no listener call for a keyframe of the replaced map
        ours, _ = node.state.global_map.to_arrays()
        for key in ("global.keys", "global.xyz", "global.feat"):
            np.testing.assert_array_equal(ours[key], expected[key], err_msg=key)
        assert _status(node)["integration"]["backlog"] == 0
    finally:
        gate.open.set()
        node.stop()
