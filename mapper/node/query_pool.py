"""The heavy-request pool of the query endpoint: ``queries.workers`` threads over a bounded queue.

Heavy requests (``render``, ``segment_points``, ``query_points`` with many new prompts) are queued
here by the query thread; a full queue answers ``busy``. Each worker answers through the node's
``answer(msg, data) -> bytes`` (never raises) and hands the reply back to the query thread through
its own inproc PUSH socket (:attr:`QueryPool.reply_endpoint`), so the query ROUTER is only ever used
by the query thread.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import zmq

from mapper.node.context import NodeContext
from protocol.errors import ProtocolError
from protocol.messages import Message, encode

__all__ = ["QueryPool"]

log = logging.getLogger("mapper.node.service")


class QueryPool:
    """The pool's queue and counters; :meth:`work` is one worker thread's body."""

    def __init__(self, ctx: NodeContext, answer: Callable[[Message, bytes], bytes]) -> None:
        self.ctx = ctx
        self.answer = answer
        self._jobs: queue.Queue[tuple[list[bytes], Message, bytes]] = queue.Queue(
            maxsize=ctx.config.queries.queue_length
        )
        self._lock = threading.Lock()
        self._running = 0
        self._done = 0
        self._busy = 0
        self.reply_endpoint = f"inproc://mapper-query-replies-{id(self):x}"
        """Workers PUSH ``[*envelope, reply]`` here; the query thread PULLs and sends on its ROUTER."""

    def submit(self, envelope: list[bytes], msg: Message, data: bytes) -> bytes | None:
        """Queue a decoded heavy request (None: a worker replies), or the encoded ``busy`` error when
        the queue is full."""
        try:
            self._jobs.put_nowait((envelope, msg, data))
            return None
        except queue.Full:
            with self._lock:
                self._busy += 1
                running = self._running
        cfg = self.ctx.config.queries
        exc = ProtocolError(
            "busy",
            f"{msg.TYPE}: {running} heavy request(s) running and {cfg.queue_length} waiting "
            f"(queries.workers = {cfg.workers}, queries.queue_length = {cfg.queue_length}); retry later",
        )
        return encode(self.ctx.error(exc, data, "query"))

    def work(self, context: zmq.Context[zmq.Socket[bytes]]) -> None:
        """One worker thread: answer queued requests until the node stops; every reply goes back to
        the query thread through this worker's own PUSH socket (made in ``context``)."""
        push: zmq.Socket[bytes] = context.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.connect(self.reply_endpoint)
        stop = self.ctx.stop
        try:
            while not stop.is_set():
                try:
                    envelope, msg, data = self._jobs.get(timeout=self.ctx.config.poll_interval_s)
                except queue.Empty:
                    continue
                with self._lock:
                    self._running += 1
                started = time.monotonic()
                try:
                    reply = self.answer(msg, data)  # never raises
                finally:
                    with self._lock:
                        self._running -= 1
                        self._done += 1
                try:
                    push.send_multipart([*envelope, reply])
                except zmq.ZMQError as exc:  # the context is closing
                    log.warning("query worker: could not hand back a reply: %s", exc)
                self.ctx.pace(started)
        finally:
            push.close()

    def stats(self) -> dict[str, int]:
        """For ``status`` (``query_pool``): ``workers``, ``queue_length``, ``running``, ``queued``,
        ``done`` (answered by a worker) and ``busy`` (refused: queue full)."""
        with self._lock:
            return {
                "workers": self.ctx.config.queries.workers,
                "queue_length": self.ctx.config.queries.queue_length,
                "running": self._running,
                "queued": self._jobs.qsize(),
                "done": self._done,
                "busy": self._busy,
            }
