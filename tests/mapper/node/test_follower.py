"""A read-only follower (``follow_map``): it serves the writer's saved map, loads each new save,
keeps its copy when a save is damaged, rejects frames and refuses ``save`` / ``load``."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.harness import DEMO_OV_SPACE, synthetic_frame
from mapper.node.config import ConfigError, config_from_dict
from mapper.node.service import MapperNode
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import (
    Ack,
    Error,
    Load,
    Ok,
    Points,
    QueryPoints,
    Save,
    Segmentation,
    SegmentPoints,
    StatusRequest,
    decode,
    encode,
)
from tests.node_helpers import DemoOneHotEncoder, in_process_node

N_FRAMES = 30
TEXTS = ["sky", "dark", "light"]


@pytest.fixture(autouse=True)
def _encoder() -> Iterator[None]:
    register_text_encoder(DEMO_OV_SPACE, DemoOneHotEncoder)
    yield
    unregister_text_encoder(DEMO_OV_SPACE)


def _writer(tmp_path: Path) -> MapperNode:
    return in_process_node(tmp_path, window={"max_keyframes": 6}, global_map={"integrate_queue": 0})


def _follower(tmp_path: Path) -> MapperNode:
    return in_process_node(tmp_path, window={"max_keyframes": 6}, global_map={"integrate_queue": 0},
                           follow_map="latest")


def _ask(node: MapperNode, msg: Any) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def _stream(node: MapperNode, seqs: range) -> None:
    for seq in seqs:
        reply = decode(node.handle_ingest(encode(synthetic_frame(seq, N_FRAMES, 64, 48))), direction="reply")
        assert isinstance(reply, Ack) and reply.status != "rejected", reply


def _labels(node: MapperNode, xyz: np.ndarray) -> np.ndarray:
    reply = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method="average_depth"))
    assert isinstance(reply, Segmentation), reply
    return reply.label.copy()


def test_a_follower_serves_each_save_of_the_writer_and_nothing_else(tmp_path: Path) -> None:
    writer, follower = _writer(tmp_path), _follower(tmp_path)
    try:
        assert follower.follower is not None and writer.follower is None
        assert follower.follower.poll_once() is False  # nothing saved yet: empty, waiting
        _stream(writer, range(0, 15))
        assert isinstance(_ask(writer, Save(name="latest")), Ok)
        assert follower.follower.poll_once() is True
        assert follower.follower.poll_once() is False  # the same file: not loaded twice
        snap = writer.state.global_map.snapshot()
        xyz = snap.xyz[:: max(1, len(snap) // 400)].copy()
        np.testing.assert_array_equal(_labels(follower, xyz), _labels(writer, xyz))
        assert len(follower.state.global_map) == len(writer.state.global_map)
        assert follower.state.map_version == writer.state.map_version
        points = _ask(follower, QueryPoints(texts=["dark"]))
        theirs = _ask(writer, QueryPoints(texts=["dark"]))
        assert isinstance(points, Points) and len(points.xyz) > 0
        np.testing.assert_array_equal(points.xyz, theirs.xyz)
        # the writer goes on and saves again: the follower takes the new copy
        _stream(writer, range(15, N_FRAMES))
        assert isinstance(_ask(writer, Save(name="latest")), Ok)
        assert follower.follower.poll_once() is True
        assert len(follower.state.global_map) == len(writer.state.global_map)
        status = _ask(follower, StatusRequest())
        follow = status.extra["follow"]
        assert follow["map"] == "latest" and follow["loads"] == 2 and follow["failed"] == 0
        assert follow["loaded_map_version"] == writer.state.map_version and follow["copy_age_s"] >= 0
    finally:
        writer.stop()
        follower.stop()


def test_a_follower_rejects_frames_and_refuses_save_and_load(tmp_path: Path) -> None:
    writer, follower = _writer(tmp_path), _follower(tmp_path)
    try:
        _stream(writer, range(0, 8))
        _ask(writer, Save(name="latest"))
        assert follower.follower is not None and follower.follower.poll_once()
        before = (len(follower.state.global_map), follower.state.map_version)
        ack = decode(follower.handle_ingest(encode(synthetic_frame(20, N_FRAMES, 64, 48))), direction="reply")
        assert isinstance(ack, Ack) and ack.status == "rejected" and "follow_map" in (ack.reason or "")
        for request in (Save(name="mine"), Load(name="latest")):
            reply = _ask(follower, request)
            assert isinstance(reply, Error) and reply.code == "bad_request" and "read-only" in reply.message
        assert (len(follower.state.global_map), follower.state.map_version) == before
        assert not (tmp_path / "maps" / "mine.govmap").exists()
    finally:
        writer.stop()
        follower.stop()


def test_a_damaged_save_leaves_the_follower_its_copy(tmp_path: Path) -> None:
    writer, follower = _writer(tmp_path), _follower(tmp_path)
    try:
        _stream(writer, range(0, 10))
        _ask(writer, Save(name="latest"))
        assert follower.follower is not None and follower.follower.poll_once()
        count = len(follower.state.global_map)
        (tmp_path / "maps" / "latest.govmap").write_bytes(b"not a map")
        assert follower.follower.poll_once() is False
        assert len(follower.state.global_map) == count  # still serving the copy it had
        follow = follower.follower.stats()
        assert follow["failed"] == 1 and follow["last_error"] and follow["loads"] == 1
        _ask(writer, Save(name="latest"))  # the next good save is taken
        assert follower.follower.poll_once() is True and follower.follower.stats()["last_error"] == ""
    finally:
        writer.stop()
        follower.stop()


def test_follow_config_is_checked(tmp_path: Path) -> None:
    base = {"map_dir": str(tmp_path)}
    assert config_from_dict({**base, "follow_map": "latest"}).follow_map == "latest"
    with pytest.raises(ConfigError, match="a follower never saves"):
        config_from_dict({**base, "follow_map": "latest", "autosave_name": "latest"})
    with pytest.raises(ConfigError, match="follow_map"):
        config_from_dict({**base, "follow_map": "../elsewhere"})
    with pytest.raises(ConfigError, match="follow_interval_s"):
        config_from_dict({**base, "follow_map": "latest", "follow_interval_s": 0.0})


def test_a_started_follower_picks_up_saves_on_its_own(tmp_path: Path) -> None:
    import time

    writer = _writer(tmp_path)
    follower = in_process_node(tmp_path, window={"max_keyframes": 6}, follow_map="latest",
                               follow_interval_s=0.05, serve_model=False)
    try:
        _stream(writer, range(0, 10))
        _ask(writer, Save(name="latest"))
        follower.start()  # the first copy is loaded before it serves
        assert len(follower.state.global_map) == len(writer.state.global_map)
        _stream(writer, range(10, 20))
        _ask(writer, Save(name="latest"))
        deadline = time.monotonic() + 30.0
        while _ask(follower, StatusRequest()).extra["follow"]["loads"] < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _ask(follower, StatusRequest()).extra["follow"]["loads"] == 2
        assert len(follower.state.global_map) == len(writer.state.global_map)
    finally:
        writer.stop()
        follower.stop()


def test_status_during_a_load_does_not_wait_for_it(tmp_path: Path) -> None:
    # status reads the follower's counters while it holds the node's state lock, which a load takes:
    # the counters must never be held across a load (that order once deadlocked a started follower)
    import threading

    writer, follower = _writer(tmp_path), _follower(tmp_path)
    try:
        _stream(writer, range(0, 8))
        _ask(writer, Save(name="latest"))
        assert follower.follower is not None
        real = follower.persistence.load_map
        entered, release = threading.Event(), threading.Event()

        def slow_load(name: str) -> str:
            entered.set()
            release.wait(10.0)
            with follower.state.lock:  # as a load takes the state lock
                pass
            return real(name)

        follower.persistence.load_map = slow_load  # type: ignore[method-assign]
        poll = threading.Thread(target=follower.follower.poll_once, daemon=True)
        poll.start()
        assert entered.wait(10.0)
        answered = threading.Event()

        def ask_status() -> None:
            _ask(follower, StatusRequest())
            answered.set()

        threading.Thread(target=ask_status, daemon=True).start()
        assert answered.wait(10.0), "status waited for the load"
        release.set()
        poll.join(30.0)
        assert not poll.is_alive() and follower.follower.stats()["loads"] == 1
    finally:
        writer.stop()
        follower.stop()
