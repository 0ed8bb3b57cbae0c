"""The query endpoint's worker pool: light requests are never queued behind heavy ones, heavy
requests beyond the bounded queue get ``busy``, and every request is answered exactly once."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

from mapper.node.service import MapperNode
from protocol.messages import Error, Message, Ok, Render, Status, StatusRequest, decode, encode
from tests.node_helpers import in_process_node

TIMEOUT_MS = 10_000


def _node(tmp_path: Path, **queries: Any) -> MapperNode:
    return in_process_node(tmp_path, serve_model=False, queries=queries)


@pytest.fixture()
def dealer() -> Iterator[zmq.Socket[bytes]]:
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
    sock: zmq.Socket[bytes] = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    yield sock
    sock.close()


def _render(rid: str) -> bytes:
    return encode(Render(width=4, height=3, K=np.array([4.0, 4.0, 2.0, 1.5]), world_from_cam=np.eye(4),
                         outputs=["depth"], id=rid))  # fmt: skip


def _recv(sock: zmq.Socket[bytes]) -> Message:
    assert sock.poll(TIMEOUT_MS), "no reply within 10 s"
    return decode(sock.recv(), direction="reply")


class _SlowHandler:
    """A heavy handler that blocks until released; counts the requests it served."""

    def __init__(self) -> None:
        self.entered = threading.Semaphore(0)
        self.release = threading.Event()
        self.served: list[str] = []
        self._lock = threading.Lock()

    def __call__(self, msg: Message) -> Message:
        self.entered.release()
        assert self.release.wait(timeout=30)
        with self._lock:
            self.served.append(str(getattr(msg, "id", None)))
        return Ok(message="rendered")


def test_status_is_answered_while_a_heavy_request_is_in_flight(
    tmp_path: Path, dealer: zmq.Socket[bytes]
) -> None:
    node = _node(tmp_path, workers=1, queue_length=2)
    slow = _SlowHandler()
    node.register_query_handler(Render, slow)
    node.start()
    try:
        dealer.connect(node.config.query_endpoint)
        dealer.send(_render("r1"))
        assert slow.entered.acquire(timeout=10)  # the render is running on a worker
        dealer.send(encode(StatusRequest(id="s1")))
        status = _recv(dealer)  # answered while the render still blocks
        assert isinstance(status, Status) and status.id == "s1"
        pool = status.extra["query_pool"]
        assert pool["running"] == 1 and pool["workers"] == 1 and pool["queue_length"] == 2
        assert not slow.served
        slow.release.set()
        done = _recv(dealer)
        assert isinstance(done, Ok) and done.id == "r1" and slow.served == ["r1"]
    finally:
        slow.release.set()
        node.stop()


def test_heavy_requests_beyond_the_queue_get_busy_and_all_are_answered_once(
    tmp_path: Path, dealer: zmq.Socket[bytes]
) -> None:
    node = _node(tmp_path, workers=1, queue_length=1)
    slow = _SlowHandler()
    node.register_query_handler(Render, slow)
    node.start()
    try:
        dealer.connect(node.config.query_endpoint)
        dealer.send(_render("r1"))
        assert slow.entered.acquire(timeout=10)  # r1 runs
        dealer.send(_render("r2"))  # waits in the queue (length 1)
        dealer.send(_render("r3"))  # no room: busy at once
        busy = _recv(dealer)
        assert isinstance(busy, Error) and busy.code == "busy" and busy.id == "r3"
        assert "queue_length = 1" in busy.message
        slow.release.set()
        replies = [_recv(dealer), _recv(dealer)]
        assert sorted(str(r.id) for r in replies) == ["r1", "r2"]  # type: ignore[attr-defined]
        assert all(isinstance(r, Ok) for r in replies)
        assert not dealer.poll(200)  # nothing else arrives
        dealer.send(encode(StatusRequest(id="s")))
        status = _recv(dealer)
        assert isinstance(status, Status)
        assert status.extra["errors"] == {"busy": 1}
        assert status.extra["query_pool"]["busy"] == 1 and status.extra["query_pool"]["done"] == 2
        assert sorted(slow.served) == ["r1", "r2"]
    finally:
        slow.release.set()
        node.stop()


def test_every_request_of_a_mixed_burst_is_answered_exactly_once(
    tmp_path: Path, dealer: zmq.Socket[bytes]
) -> None:
    node = _node(tmp_path, workers=2, queue_length=64)
    node.register_query_handler(Render, lambda msg: Ok(message="fast"))
    node.start()
    try:
        dealer.connect(node.config.query_endpoint)
        sent = []
        for i in range(40):
            rid = f"q{i}"
            dealer.send(_render(rid) if i % 2 else encode(StatusRequest(id=rid)))
            sent.append(rid)
        dealer.send(b"\x00not msgpack")  # a bad request is answered too (without an id)
        got = [_recv(dealer) for _ in range(41)]
        ids = [str(getattr(m, "id", None)) for m in got]
        assert sorted(i for i in ids if i != "None") == sorted(sent)
        bad = [m for m in got if getattr(m, "id", None) is None]
        assert len(bad) == 1 and isinstance(bad[0], Error) and bad[0].code == "bad_request"
        for m in got:
            if isinstance(m, Ok):
                assert int(str(m.id)[1:]) % 2 == 1
        assert not dealer.poll(200)
    finally:
        node.stop()


def test_without_workers_heavy_requests_are_answered_in_order_on_the_query_thread(
    tmp_path: Path, dealer: zmq.Socket[bytes]
) -> None:
    node = _node(tmp_path, workers=0)
    served_on: list[str] = []

    def render(msg: Message) -> Message:
        served_on.append(threading.current_thread().name)
        return Ok()

    node.register_query_handler(Render, render)
    node.start()
    try:
        dealer.connect(node.config.query_endpoint)
        for i in range(5):
            dealer.send(_render(f"r{i}") if i != 2 else encode(StatusRequest(id="r2")))
        ids = [str(_recv(dealer).id) for _ in range(5)]  # type: ignore[attr-defined]
        assert ids == [f"r{i}" for i in range(5)]
        assert served_on == ["mapper-query"] * 4
    finally:
        node.stop()


def test_pool_settings_are_validated(tmp_path: Path) -> None:
    from mapper.errors import ConfigError

    with pytest.raises(ConfigError, match="queries.queue_length"):
        _node(tmp_path, queue_length=0)
    with pytest.raises(ConfigError, match="queries.workers"):
        _node(tmp_path, workers=-1)


class _Prompts:
    """A text encoder that knows the prompts it embedded (``uncached_chars``, as the real ones)."""

    space = "test-prompt-routing"
    dim = 4

    def __init__(self) -> None:
        self.known: set[str] = set()

    def encode(self, texts: list[str]) -> np.ndarray:
        self.known.update(texts)
        return np.full((len(texts), 4), 0.5, np.float32)

    def uncached_chars(self, texts: list[str]) -> int:
        return sum(len(t) for t in dict.fromkeys(texts) if t not in self.known)


def test_query_points_with_many_new_prompt_characters_is_answered_by_the_pool(
    tmp_path: Path, dealer: zmq.Socket[bytes]
) -> None:
    from mapper.node.queries import DEFAULT_NEGATIVES, normalise_query
    from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
    from protocol.messages import QueryPoints

    encoder = _Prompts()
    register_text_encoder(encoder.space, lambda: encoder)
    node = _node(tmp_path, workers=1, queue_length=2, light_text_chars=100)
    node.state.ov_space = encoder.space
    threads: list[str] = []
    gate = threading.Event()

    def handler(msg: Message) -> Message:
        threads.append(threading.current_thread().name)
        if getattr(msg, "id", None) == "long":
            assert gate.wait(timeout=30)
        prompts = [*msg.texts, *DEFAULT_NEGATIVES]  # type: ignore[attr-defined]
        encoder.encode([normalise_query(t) for t in prompts])  # as query_points embeds them
        return Ok(message="answered")

    node.register_query_handler(QueryPoints, handler)
    node.start()
    long_prompt = "a chair with a tall back and four legs " * 20  # 780 characters, not embedded yet
    try:
        dealer.connect(node.config.query_endpoint)
        dealer.send(encode(QueryPoints(texts=["find the chair"], id="short")))
        assert isinstance(_recv(dealer), Ok)  # 5 + 37 new characters of prompts: light
        dealer.send(encode(QueryPoints(texts=[long_prompt], id="long")))
        waited = threading.Event()
        for _ in range(1000):  # until the long one is in its handler (10 s at most)
            if len(threads) >= 2 or waited.wait(0.01):
                break
        assert len(threads) == 2
        dealer.send(encode(StatusRequest(id="s")))
        status = _recv(dealer)  # answered while the long one waits in its handler on a worker
        assert isinstance(status, Status) and status.extra["query_pool"]["running"] == 1
        gate.set()
        assert isinstance(_recv(dealer), Ok)
        dealer.send(encode(QueryPoints(texts=[long_prompt], id="again")))  # embedded now: light
        assert isinstance(_recv(dealer), Ok)
        assert threads[0] == threads[2] != threads[1] and threads[1].startswith("mapper-query-worker")
    finally:
        gate.set()
        node.stop()
        unregister_text_encoder(encoder.space)


def test_light_text_chars_is_checked() -> None:
    from mapper.errors import ConfigError
    from mapper.node.config import config_from_dict

    assert config_from_dict({}).queries.light_text_chars == 256
    with pytest.raises(ConfigError, match="queries.light_text_chars"):
        config_from_dict({"queries": {"light_text_chars": -1}})
