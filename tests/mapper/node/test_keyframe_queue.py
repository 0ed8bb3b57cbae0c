"""Tests for mapper.node.keyframe_queue: the bounded queue, the worker loop, the rate-limited log."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mapper.map.window import Keyframe
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker


def test_queue_is_fifo_bounded_and_counts_drops() -> None:
    q: KeyframeQueue[int] = KeyframeQueue(3)
    for i in range(5):
        q.put(i)
    assert len(q) == 3 and q.queued == 5 and q.dropped == 2 and q.wake.is_set()
    assert q.pop() == 2 and q.drain() == [3, 4] and q.pop() is None and len(q) == 0
    with pytest.raises(ValueError, match="max_len"):
        KeyframeQueue(0)


def test_worker_loop_survives_errors_and_stops() -> None:
    stop, wake = threading.Event(), threading.Event()
    calls: list[int] = []
    errors: list[BaseException] = []

    def work() -> None:
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("boom")

    thread = threading.Thread(target=run_worker, args=(stop, wake, work, errors.append),
                              kwargs={"idle_wait_s": 0.01}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 5.0
    while len(calls) < 3 and time.monotonic() < deadline:
        wake.set()
        time.sleep(0.01)
    stop.set()
    wake.set()
    thread.join(timeout=5.0)
    assert not thread.is_alive() and len(calls) >= 3
    assert len(errors) == 1 and str(errors[0]) == "boom"


def test_limited_log_warns_once_per_interval_per_kind(caplog: pytest.LogCaptureFixture) -> None:
    limited = LimitedLog(logging.getLogger("test.limited"), interval_s=60.0)
    with caplog.at_level(logging.DEBUG, logger="test.limited"):
        for _ in range(3):
            limited.warning("a", "a %d", 1)
        limited.warning("b", "b")
    levels = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert levels == [("WARNING", "a 1"), ("DEBUG", "a 1"), ("DEBUG", "a 1"), ("WARNING", "b")]


def test_a_byte_budget_drops_the_oldest_and_keeps_the_newest() -> None:
    q: KeyframeQueue[bytes] = KeyframeQueue(100, max_bytes=10, size_of=len)
    for item in (b"aaaa", b"bbbb", b"cccc"):  # 12 bytes > 10: the oldest goes
        q.put(item)
    assert len(q) == 2 and q.bytes == 8 and q.dropped == 1
    q.put(b"x" * 50)  # larger than the budget alone: it stays, every older item goes
    assert len(q) == 1 and q.bytes == 50 and q.dropped == 3
    assert q.pop() == b"x" * 50 and q.bytes == 0 and q.pop() is None
    q.put(b"dd")
    assert q.drain() == [b"dd"] and q.bytes == 0
    with pytest.raises(ValueError, match="max_bytes"):
        KeyframeQueue(4, max_bytes=10)  # a budget needs a size


def test_the_evicted_views_queue_is_bounded_by_bytes(tmp_path: Path) -> None:
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from mapper.node.workers.evicted_views import keyframe_bytes

    config = config_from_dict({"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
                               "queries": {"evicted_views": "both", "evicted_views_max_pending_mb": 1.0}})
    node = MapperNode(config)
    try:
        worker = node.ctx.evicted_views
        assert worker is not None and worker.queue.max_bytes == 2**20
        rng = np.random.default_rng(0)
        for seq in range(4):  # 640 x 480 colour alone: 0.9 MB a keyframe
            kf = Keyframe(seq=seq, stamp_ns=seq, camera="cam", K=np.array([500.0, 500.0, 320.0, 240.0]),
                          world_from_cam=np.eye(4), rgb=rng.integers(0, 255, (480, 640, 3), dtype=np.uint8),
                          ov=np.zeros((120, 160, 8), np.float16))
            worker.put(kf, node.state.global_map)
        assert len(worker.queue) == 1 and worker.queue.dropped == 3
        assert worker.queue.bytes == keyframe_bytes(kf)
    finally:
        node.stop()
