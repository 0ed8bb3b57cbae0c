"""Tests for mapper.node.keyframe_queue: the bounded queue, the worker loop, the rate-limited log."""

from __future__ import annotations

import logging
import threading
import time

import pytest

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
