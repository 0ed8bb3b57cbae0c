"""Limits: a client that never reads its replies (or vanishes) never blocks the node or grows its
memory: its replies are dropped and counted while other clients are served; the events queue is
bounded (oldest dropped, counted)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq

from clients.client import MapperClient
from mapper.node.answers.status import rss_bytes as _rss_bytes
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from protocol.messages import Status, StatusRequest, decode, encode
from tests.node_helpers import in_process_node

GARBAGE = b"\x81\xa1v\x01"  # a msgpack map without a type: every copy gets a small error reply


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    mapper = in_process_node(
        tmp_path,
        ingest_endpoint=f"ipc://{tmp_path}/ingest.sock",
        query_endpoint=f"ipc://{tmp_path}/query.sock",
        limits={"sndhwm": 8, "rcvhwm": 8},
    )
    mapper.start()
    try:
        yield mapper
    finally:
        mapper.stop()


def _status(node: MapperNode) -> Status:
    with MapperClient(node.config.ingest_endpoint, node.config.query_endpoint, timeout_s=5.0, retries=0) as c:
        return c.status()


def test_a_client_that_never_reads_does_not_block_the_node_or_grow_its_memory(node: MapperNode) -> None:
    ctx = zmq.Context.instance()
    hog = ctx.socket(zmq.DEALER)
    hog.setsockopt(zmq.RCVHWM, 1)
    hog.setsockopt(zmq.RCVBUF, 4096)
    hog.setsockopt(zmq.SNDTIMEO, 5000)
    hog.setsockopt(zmq.LINGER, 0)
    hog.connect(node.config.ingest_endpoint)
    rss_before = _rss_bytes()
    sent = 6000
    answered_meanwhile = 0
    try:
        for i in range(sent):
            hog.send_multipart([b"", GARBAGE])  # blocks (up to 5 s) only if the node stops reading
            if i % 1000 == 999:
                assert _status(node).frames_received >= 0  # another client is answered meanwhile
                answered_meanwhile += 1
        deadline = time.monotonic() + 30.0
        while True:
            status = _status(node)
            if status.frames_received >= sent or time.monotonic() > deadline:
                break
            time.sleep(0.05)
    finally:
        hog.close(linger=0)
    rss_after = _rss_bytes()
    assert answered_meanwhile == sent // 1000
    assert status.frames_received == sent and status.extra["errors"]["bad_request"] == sent
    dropped = status.extra["replies_dropped"].get("ingest:full", 0)
    # the hog took at most a bounded number of replies (its queue + the socket buffers); the rest
    # were dropped at the node's high-water mark instead of queued
    assert dropped > sent // 2, status.extra["replies_dropped"]
    assert status.extra["limits"]["sndhwm"] == 8
    if rss_before is not None and rss_after is not None:
        assert rss_after - rss_before < 64 * 2**20, (rss_before, rss_after)


def test_clients_that_vanish_mid_stream_leave_the_node_serving(node: MapperNode) -> None:
    ctx = zmq.Context.instance()
    for _ in range(5):
        ghost = ctx.socket(zmq.DEALER)
        ghost.connect(node.config.ingest_endpoint)
        for _ in range(200):
            ghost.send_multipart([b"", GARBAGE])
        ghost.close(linger=1000)  # the peer is gone, never reading; unread requests die with it
    last, stable_since = -1, time.monotonic()
    while time.monotonic() - stable_since < 0.5:  # until the node has handled what reached it
        status = _status(node)
        if status.frames_received != last:
            last, stable_since = status.frames_received, time.monotonic()
        time.sleep(0.05)
    assert 0 < status.frames_received <= 1000
    assert status.extra["errors"]["bad_request"] == status.frames_received
    dropped = status.extra["replies_dropped"]  # replies it could not deliver: counted, by kind
    assert set(dropped) <= {"ingest:full", "ingest:gone"}, dropped
    assert sum(dropped.values()) <= status.frames_received


def test_events_queue_is_bounded_oldest_dropped_and_counted(tmp_path: Path) -> None:
    config = config_from_dict(
        {"map_dir": str(tmp_path / "maps"), "limits": {"events_queue_max": 3}}  # events on, not started
    )
    node = MapperNode(config)
    for version in range(1, 11):
        node.ctx.publish(version, version)
    status = decode(node.handle_query(encode(StatusRequest())), direction="reply")
    assert isinstance(status, Status)
    assert status.extra["events_dropped"] == 7
    kept = [node.ctx.events.pop() for _ in range(4)]
    assert [e.map_version for e in kept if e is not None] == [8, 9, 10] and kept[-1] is None


def test_queries_are_paced_only_while_frames_arrive(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = config_from_dict(
        {"map_dir": str(tmp_path / "maps"), "limits": {"query_share": 0.25, "query_pause_max_s": 0.5}}
    )
    node = MapperNode(config)
    pauses: list[float] = []
    monkeypatch.setattr(node.ctx.stop, "wait", lambda timeout: pauses.append(timeout))
    node.ctx.pace(started=-0.04, now=0.0)  # no frame ever: no pause
    assert pauses == []
    node.handle_ingest(GARBAGE)  # a message on the ingest endpoint (even a bad one) marks it active
    now = node.ctx.ingest_last + 0.1
    node.ctx.pace(started=now - 0.04, now=now)  # 40 ms of work at share 0.25 -> 120 ms pause
    assert pauses == [pytest.approx(0.12)]
    node.ctx.pace(started=now - 1.0, now=now)  # 1 s of work -> capped at query_pause_max_s
    assert pauses[-1] == 0.5
    idle = node.ctx.ingest_last + config.limits.ingest_active_s + 0.01  # no frame for a while
    node.ctx.pace(started=idle - 0.04, now=idle)
    assert len(pauses) == 2
    unpaced = MapperNode(
        config_from_dict({"map_dir": str(tmp_path / "maps"), "limits": {"query_share": 1.0}})
    )
    unpaced.handle_ingest(GARBAGE)
    monkeypatch.setattr(unpaced.ctx.stop, "wait", lambda timeout: pauses.append(timeout))
    unpaced.ctx.pace(started=unpaced.ctx.ingest_last - 0.04, now=unpaced.ctx.ingest_last)
    assert len(pauses) == 2
