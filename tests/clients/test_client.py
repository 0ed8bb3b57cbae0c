"""MapperClient against scripted in-process ROUTER servers: pairing, pipelining, lazy-pirate retries."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zmq

from clients.client import MapperClient
from protocol.errors import ProtocolError, RemoteError
from protocol.messages import Ack, Error, Frame, Message, Status, StatusRequest, decode, encode

Handler = Callable[[int, Message], Message | None]
"""(request number, request) -> reply, or None to drop the request (simulating a lost reply)."""


class FakeNode:
    """A ROUTER on an inproc endpoint served by a thread; replies come from ``handler``."""

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], name: str, handler: Handler) -> None:
        self.endpoint = f"inproc://{name}"
        self.handler = handler
        self.received: list[Message] = []
        self._sock = ctx.socket(zmq.ROUTER)
        self._sock.bind(self.endpoint)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        poller = zmq.Poller()
        poller.register(self._sock, zmq.POLLIN)
        while not self._stop.is_set():
            if not poller.poll(20):
                continue
            parts = self._sock.recv_multipart()
            msg = decode(parts[-1], direction="request")
            self.received.append(msg)
            reply = self.handler(len(self.received) - 1, msg)
            if reply is not None:
                self._sock.send_multipart([*parts[:-1], encode(reply)])
        self._sock.close(linger=0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@pytest.fixture()
def ctx() -> Iterator[zmq.Context[zmq.Socket[bytes]]]:
    context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    yield context
    context.destroy(linger=0)


def _frame(seq: int) -> Frame:
    return Frame(
        seq=seq, stamp_ns=seq, width=4, height=3, K=np.array([4.0, 4.0, 2.0, 1.5]),
        world_from_cam=np.eye(4), rgb=np.full((3, 4, 3), seq % 256, np.uint8),
    )  # fmt: skip


def _ack_all(_: int, msg: Message) -> Message:
    assert isinstance(msg, Frame)
    return Ack(
        seq=msg.seq, status="keyframe" if msg.seq % 2 == 0 else "accepted", map_version=msg.seq, id=msg.id
    )


def _status(msg: Message) -> Status:
    return Status(
        map_version=1, keyframes=2, frames_received=3, frames_rejected=0, ov_space=None,
        memory_bytes=10, uptime_s=1.0, id=getattr(msg, "id", None),
    )  # fmt: skip


def test_pipelined_frames_are_answered_in_order(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    node = FakeNode(ctx, "pipe", _ack_all)
    try:
        with MapperClient(ingest=node.endpoint, timeout_s=2.0, context=ctx) as client:
            frames: list[Frame | bytes] = [_frame(i) for i in range(20)]
            frames[5] = encode(_frame(5))  # raw bytes go through unchanged
            results = list(client.send_frames(frames, window=6))
        assert [r.index for r in results] == list(range(20))
        assert all(isinstance(r.reply, Ack) and r.reply.seq == r.index for r in results)
        assert [r.reply.status for r in results][:2] == ["keyframe", "accepted"]  # type: ignore[union-attr]
        # the client gave id-less Frame objects an id (on a copy), and left raw bytes alone
        assert all(m.id is not None for i, m in enumerate(node.received) if i != 5)  # type: ignore[attr-defined]
        assert node.received[5].id is None  # type: ignore[attr-defined]
        assert isinstance(frames[0], Frame) and frames[0].id is None
    finally:
        node.close()


def test_lost_reply_is_retried_on_a_fresh_socket(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    def drop_first(n: int, msg: Message) -> Message | None:
        return None if n == 0 else _status(msg)

    node = FakeNode(ctx, "retry", drop_first)
    try:
        with MapperClient(query=node.endpoint, timeout_s=0.2, retries=2, context=ctx) as client:
            status = client.status()
        assert status.keyframes == 2
        assert len(node.received) == 2 and node.received[0].id == node.received[1].id  # type: ignore[attr-defined]
    finally:
        node.close()


def test_pipelined_retry_resends_everything_in_flight(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    dropped: list[int] = []

    def drop_seq_3_once(_: int, msg: Message) -> Message | None:
        assert isinstance(msg, Frame)
        if msg.seq == 3 and not dropped:
            dropped.append(msg.seq)
            return None
        return _ack_all(0, msg)

    node = FakeNode(ctx, "pipe-retry", drop_seq_3_once)
    try:
        with MapperClient(ingest=node.endpoint, timeout_s=0.2, retries=1, context=ctx) as client:
            results = list(client.send_frames([_frame(i) for i in range(8)], window=4))
        assert all(r.reply.seq == r.index for r in results)  # type: ignore[union-attr]
        assert sorted(r.index for r in results) == list(range(8))  # frame 3 came back last, after its retry
        seqs = [m.seq for m in node.received]  # type: ignore[attr-defined]
        assert sorted(set(seqs)) == list(range(8)) and seqs.count(3) == 2
    finally:
        node.close()


def test_no_node_raises_timeout_error_naming_the_endpoint(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    node = FakeNode(ctx, "silent", lambda n, m: None)
    try:
        with MapperClient(query=node.endpoint, timeout_s=0.05, retries=2, context=ctx) as client:
            with pytest.raises(TimeoutError, match="inproc://silent.*2 retries"):
                client.status()
        assert len(node.received) == 3  # first try + 2 retries
    finally:
        node.close()


def test_error_replies(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    def refuse(_: int, msg: Message) -> Message:
        return Error(code="not_ready", message="later", id=getattr(msg, "id", None))

    node = FakeNode(ctx, "refuse", refuse)
    try:
        with MapperClient(ingest=node.endpoint, query=node.endpoint, timeout_s=2.0, context=ctx) as client:
            reply = client.request(StatusRequest())
            assert isinstance(reply, Error) and reply.code == "not_ready"  # request() returns errors
            with pytest.raises(RemoteError) as info:
                client.status()
            assert info.value.code == "not_ready" and info.value.message == "later"
            with pytest.raises(RemoteError):
                client.send_frame(_frame(0))
            results = list(client.send_frames([_frame(1), _frame(2)]))
            assert all(isinstance(r.reply, Error) for r in results)  # yielded, not raised
    finally:
        node.close()


def test_reply_with_wrong_id_or_type_is_a_protocol_error(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    node = FakeNode(ctx, "liar", lambda n, m: _status(StatusRequest(id=999)))
    try:
        with MapperClient(ingest=node.endpoint, query=node.endpoint, timeout_s=2.0, context=ctx) as client:
            with pytest.raises(ProtocolError, match="999"):
                client.status()
            with pytest.raises(ProtocolError, match="expected an ack or error"):
                client.send_frame(_frame(0))
    finally:
        node.close()


def test_abandoned_pipeline_does_not_leak_replies_into_the_next_request(
    ctx: zmq.Context[zmq.Socket[bytes]],
) -> None:
    node = FakeNode(ctx, "abandon", _ack_all)
    try:
        with MapperClient(ingest=node.endpoint, timeout_s=2.0, context=ctx) as client:
            stream = client.send_frames([_frame(i) for i in range(10)], window=10)
            first = next(stream)
            stream.close()  # the caller stops early with 9 frames in flight
            assert first.index == 0
            ack = client.send_frame(_frame(42))
            assert ack.seq == 42
    finally:
        node.close()


def test_invalid_arguments() -> None:
    with pytest.raises(ValueError):
        MapperClient(timeout_s=0)
    with pytest.raises(ValueError):
        MapperClient(retries=-1)
