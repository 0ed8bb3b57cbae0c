"""The plumbing the node's per-keyframe background workers share.

A worker (``mapper.node.workers.depth_points``: points from rendered depth;
``mapper.node.workers.ov_features``: OV features from the in-process encoder) is handed
keyframes on the ingest thread and does the slow work on its own thread (``node.workers``).
What they share lives here:

* :class:`KeyframeQueue`: a bounded FIFO; ``put`` is O(1) and never blocks ingest; beyond
  ``max_len`` items the oldest is dropped and counted; ``wake`` is set on every put;
* :func:`run_worker`: the worker loop (wake on new items or every ``idle_wait_s``, stop on the
  node's stop event, never die on an exception: the node shuts down when a thread dies);
* :class:`LimitedLog`: warnings at most once per interval per kind (the rest at debug level);
* :func:`with_current_features`: the window's copy of a queued keyframe once the in-process OV
  backend swapped a featured copy in.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

__all__ = ["KeyframeQueue", "LimitedLog", "run_worker", "with_current_features"]

T = TypeVar("T")

IDLE_WAIT_S = 0.5
"""A worker wakes at least this often to check for the stop event."""


class KeyframeQueue(Generic[T]):
    """Bounded FIFO between the ingest thread and one worker (thread-safe)."""

    def __init__(self, max_len: int, max_bytes: int = 0, size_of: Callable[[T], int] | None = None) -> None:
        if max_len < 1:
            raise ValueError(f"max_len {max_len} out of range: must be >= 1")
        if max_bytes < 0 or (max_bytes > 0 and size_of is None):
            raise ValueError(f"max_bytes {max_bytes}: must be >= 0, and > 0 only with size_of")
        self.max_len = max_len
        self.max_bytes = max_bytes
        """> 0: also drop the oldest while the queued items' ``size_of`` exceed this (the newest
        item always stays)."""
        self._size_of = size_of
        self.bytes = 0
        """What the queued items hold (``size_of``; 0 without it)."""
        self._items: deque[T] = deque()
        self._lock = threading.Lock()
        self.wake = threading.Event()
        """Set by every :meth:`put`; the worker waits on it."""
        self.queued = 0
        """Items ever put."""
        self.dropped = 0
        """Items dropped (oldest first) because the queue was full."""

    def put(self, item: T) -> None:
        """Append ``item`` (O(1)); drop the oldest beyond ``max_len``; wake the worker."""
        with self._lock:
            self._items.append(item)
            self.queued += 1
            self.bytes += self._size(item)
            while len(self._items) > self.max_len or (
                    self.max_bytes > 0 and self.bytes > self.max_bytes and len(self._items) > 1):
                self.bytes -= self._size(self._items.popleft())
                self.dropped += 1
        self.wake.set()

    def _size(self, item: T) -> int:
        return int(self._size_of(item)) if self._size_of is not None else 0

    def pop(self) -> T | None:
        """The oldest item, or None when empty."""
        with self._lock:
            if not self._items:
                return None
            item = self._items.popleft()
            self.bytes -= self._size(item)
            return item

    def drain(self) -> list[T]:
        """Every item, oldest first; the queue is empty afterwards."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
            self.bytes = 0
            return items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)


def run_worker(
    stop: threading.Event,
    wake: threading.Event,
    work: Callable[[], object],
    on_error: Callable[[BaseException], None],
    *,
    idle_wait_s: float = IDLE_WAIT_S,
) -> None:
    """Call ``work()`` whenever ``wake`` is set (and at least every ``idle_wait_s``) until ``stop``
    is set. An exception from ``work`` goes to ``on_error`` and the loop goes on."""
    while not stop.is_set():
        wake.wait(timeout=idle_wait_s)
        wake.clear()
        if stop.is_set():
            break
        try:
            work()
        except Exception as exc:  # never let the worker die: the node shuts down on a dead thread
            on_error(exc)


class LimitedLog:
    """``warning`` at most once per ``interval_s`` per kind; repeats within it go to ``debug``."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}

    def warning(self, kind: str, fmt: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._last.get(kind, -self.interval_s) >= self.interval_s:
            self._last[kind] = now
            self.logger.warning(fmt, *args)
        else:
            self.logger.debug(fmt, *args)


def with_current_features(node: Any, keyframe: Any) -> Any:
    """The window's current copy of ``keyframe`` (same camera, seq and stamp) when it has gained OV
    features since it was queued (the in-process OV backend, :mod:`mapper.node.workers.ov_features`,
    swaps in a featured copy), else ``keyframe``. ``node`` is a :class:`mapper.node.service.MapperNode`."""
    if keyframe.ov is not None:
        return keyframe
    with node.state.lock:
        for current in node.state.window.keyframes:
            if (current.camera, current.seq, current.stamp_ns, current.robot) == (
                keyframe.camera, keyframe.seq, keyframe.stamp_ns, getattr(keyframe, "robot", "")
            ) and current.ov is not None:
                return current
    return keyframe
