"""The long-running mapper node's transport: sockets, threads, dispatch and security.

:class:`MapperNode` receives, dispatches and replies; it answers nothing itself. What requests
share (map state, store, integrator, events, pacing, text encoders, logging) is its
:class:`mapper.node.context.NodeContext` (``node.ctx``); each request type is answered in its own
module of :mod:`mapper.node.answers`; the ways of answering points and renders are backends
(:mod:`mapper.node.backends`); background work is done by workers (:mod:`mapper.node.workers`).

Threads and sockets (a ZeroMQ socket is only ever used by the thread that created it):

- **ingest thread**: ROUTER bound on ``ingest_endpoint``; decodes each ``frame``, updates the
  keyframe window (:func:`mapper.node.ingest.ingest_frame`) and replies with exactly one ``ack`` or
  ``error``.
- **integrator thread** (``global_map.integrate_queue`` > 0, the default): fuses each acked
  keyframe into the global map, in ack order, shortly after its ack, then calls the keyframe
  listeners (:mod:`mapper.node.integration`). Its queue is bounded: when it is full the ingest
  thread waits for room before the next ack (backpressure, counted), so nothing acked is dropped.
- **query thread**: ROUTER bound on ``query_endpoint``; dispatches each request through
  :attr:`MapperNode.query_handlers` (message class -> handler) and replies exactly once. Heavy
  requests (:attr:`MapperNode.heavy_request_types`: ``render``, ``segment_points``) go to the
  **query workers** (``queries.workers`` threads, a queue of ``queries.queue_length``; ``busy``
  beyond it), which hand their replies back through inproc PUSH -> PULL sockets to the query
  thread, the only user of the ROUTER; so ``status`` / ``query_points`` / ``save`` / ``load``
  never wait behind a render. A ``query_points`` whose prompts hold more than
  ``queries.light_text_chars`` characters not embedded yet goes to the pool too (embedding many
  long prompts takes seconds), and so does a request that waits for the node to settle
  (``settle_timeout_s``).
- **events thread** (optional): PUB bound on ``events_endpoint``; publishes ``map_updated``
  notices handed to it through a queue by whichever thread changed the map.
- **workers** (``ctx.workers``): the answer refresh and the installed background workers.
- **main thread**: :meth:`MapperNode.run` waits for SIGINT/SIGTERM, does periodic autosaves and,
  on shutdown, stops the threads, does the final save and returns exit code 0.

Ingest and queries never wait on each other's sockets; they share the map state behind one lock,
held only for the short state updates (decoding, file I/O and replies happen outside it).

Replies on a ROUTER reuse the request's envelope: every frame but the last is routing
(identities, and the empty delimiter REQ peers add), the last frame is the message. So DEALER
peers (with or without an empty delimiter) and REQ peers all get their reply. Replies to one
connection leave in the order its requests arrived (each socket is served by one thread), except
that a heavy request's reply may leave after those of light requests sent after it (replies
carry the request ``id``; docs/reference/protocol.md, Transport).

Robustness: every message is handled inside a catch-all; a ``ProtocolError`` becomes its wire
error, anything else an ``internal`` error (logged with traceback), and the node keeps serving.
A rejected message changes nothing but the counters.

Extension points: ``register_query_handler(MsgClass, handler)`` replaces a request type's
handler; ``node.segment.register(method, backend)`` serves a ``segment_points`` method and
``node.render.backend`` renders (the learned model:
:func:`mapper.node.backends.learned.install_learned_backend`);
``ctx.keyframe_listeners``, ``ctx.load_listeners``, ``ctx.feature_listeners``, ``ctx.workers``,
``ctx.status_providers`` and ``ctx.memory_providers`` are how workers plug in.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

import zmq

from mapper.node.answers.persistence import Persistence
from mapper.node.answers.query_points import QueryPointsAnswers
from mapper.node.answers.render import RenderAnswers
from mapper.node.answers.segment import SegmentAnswers
from mapper.node.answers.status import StatusAnswers
from mapper.node.config import NodeConfig
from mapper.node.context import NodeContext, QueryHandler, is_not_ready, warm_all_kernels
from mapper.node.follower import install_follower
from mapper.node.ingest import ingest_frame
from mapper.node.query_pool import QueryPool
from mapper.node.security import CurveServer, exposure_problem, security_mode
from mapper.node.state import MapState
from mapper.node.store import StoreError
from protocol.errors import ProtocolError
from protocol.messages import (
    Ack,
    Error,
    Frame,
    Load,
    Message,
    QueryPoints,
    Render,
    Save,
    SegmentPoints,
    StatusRequest,
    decode,
    encode,
)

__all__ = ["HARD_LIMIT_FACTOR", "MapperNode", "QueryHandler", "limit_blas_threads"]

log = logging.getLogger("mapper.node.service")

HARD_LIMIT_FACTOR = 4
"""ZeroMQ drops messages above ``HARD_LIMIT_FACTOR * max_message_bytes`` at the transport (the
peer is disconnected, no reply) so a hostile sender cannot make the node allocate without bound;
between ``max_message_bytes`` and that, the node answers ``too_large``."""


def limit_blas_threads(threads: int) -> None:
    """Every BLAS library loaded in this process (numpy's, OpenCV's) to at most ``threads`` threads
    (``limits.blas_threads``; 0 = unchanged). Process-wide and lasting (libraries loaded later keep
    their own count: the node calls this when made and when started); without ``threadpoolctl`` a
    warning, nothing else."""
    if threads <= 0:
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a core dependency
        log.warning("threadpoolctl is missing: numpy's BLAS threads are left as they are")
        return
    threadpool_limits(limits=threads, user_api="blas")


class MapperNode:
    """The node's transport. ``start()`` binds the sockets (raising if one cannot be bound),
    ``run()`` serves until a signal or :meth:`request_stop`, ``stop()`` shuts down. Also usable
    in-process: :meth:`handle_ingest` and :meth:`handle_query` take and return encoded messages."""

    def __init__(self, config: NodeConfig) -> None:
        limit_blas_threads(config.limits.blas_threads)
        self.ctx = NodeContext(config)
        """What every request shares (:class:`mapper.node.context.NodeContext`)."""
        self.persistence = Persistence(self.ctx)
        self.follower = install_follower(self.ctx, self.persistence)
        """With ``follow_map``: the read-only copy's loader (:mod:`mapper.node.follower`), else None."""
        self.query_points = QueryPointsAnswers(self.ctx)
        self.segment = SegmentAnswers(self.ctx)
        """``segment_points`` by method (backends: ``node.segment.register``)."""
        self.render = RenderAnswers(self.ctx)
        """``render`` (its backend: ``node.render.backend``)."""
        self.status = StatusAnswers(self.ctx, self._transport_status)
        self.query_handlers: dict[type[Message], QueryHandler] = {
            StatusRequest: self.status.handle,
            Save: self.persistence.handle_save,
            Load: self.persistence.handle_load,
            QueryPoints: self.query_points.handle,
            SegmentPoints: self.segment.handle,
            Render: self.render.handle,
        }
        """Dispatch table of the query endpoint: request class -> handler."""
        self.heavy_request_types: set[type[Message]] = {Render, SegmentPoints}
        """Requests answered by the query worker pool (``queries.workers`` threads, bounded queue:
        ``busy`` beyond it), so that light requests never wait behind them."""
        self.pool = QueryPool(self.ctx, self._answer_query)
        """The heavy-request workers (:class:`mapper.node.query_pool.QueryPool`)."""
        self._context = zmq.Context()
        self._threads: list[threading.Thread] = []
        self._curve: CurveServer | None = None
        """CURVE keys and ZAP authenticator when ``curve_dir`` is set (made by :meth:`start`)."""
        self._last_curve_check = time.monotonic()
        self._bind_errors: list[str] = []
        self._stopped = False

    @property
    def config(self) -> NodeConfig:
        return self.ctx.config

    @property
    def state(self) -> MapState:
        """The map state (``ctx.state``)."""
        return self.ctx.state

    def register_query_handler(self, message_type: type[Message], handler: QueryHandler) -> None:
        """Serve ``message_type`` requests on the query endpoint with ``handler`` (replacing any)."""
        self.query_handlers[message_type] = handler

    # -- lifecycle ----------------------------------------------------------------------------

    def _fail_start(self, message: str) -> RuntimeError:
        """Undo a partial start; the error to raise."""
        if self._curve is not None:
            self._curve.stop()
        self._context.term()
        self._stopped = True
        return RuntimeError(message)

    def _start_security(self, endpoints: list[str]) -> None:
        """Refuse an exposed bind without keys; start CurveZMQ with ``curve_dir``."""
        cfg = self.config
        problem = exposure_problem(endpoints, cfg.curve_dir, cfg.insecure)
        if problem:
            raise self._fail_start(problem)
        if cfg.curve_dir:
            try:
                self._curve = CurveServer(self._context, cfg.curve_dir)
                self._curve.start()
            except Exception as exc:  # a key file problem (ConfigError) or the authenticator
                raise self._fail_start(f"CurveZMQ (curve_dir {cfg.curve_dir!r}): {exc}") from None
        elif security_mode(endpoints, None) == "insecure":
            log.warning(
                "INSECURE: serving %s without CurveZMQ authentication (insecure = true): anyone who can "
                "reach these addresses can stream frames, query, save and load maps "
                "(docs/how-to/robot-network.md)",
                ", ".join(e for e in endpoints if security_mode([e], None) == "insecure"),
            )

    def _spawn(self, target: Callable[..., None], name: str, *args: Any) -> threading.Thread:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)
        return thread

    def start(self) -> None:
        """Start the socket threads; return once every socket is bound. Raises ``RuntimeError``
        naming the endpoint when a bind fails (e.g. address in use). With ``load_autosave_on_start``
        the autosaved map is loaded first (see :meth:`Persistence.load_autosave`).

        Refuses (``RuntimeError``) a non-loopback bind without ``curve_dir`` unless ``insecure``
        (:func:`mapper.node.security.exposure_problem`); with ``curve_dir`` the key files must load."""
        cfg = self.config
        limit_blas_threads(cfg.limits.blas_threads)  # again: plugins may have loaded another BLAS (OpenCV's)
        self._start_security(self._endpoints())
        self.persistence.load_autosave()
        if self.follower is not None:  # a follower serves its first copy from the start
            self.follower.poll_once()
        # before the socket threads, so the first keyframe already goes to it; on stop it finishes
        # its queue (what the ingest thread submits after that is integrated inline)
        integrator = self.ctx.integration.start(self.ctx.stop)
        if integrator is not None:
            self._threads.append(integrator)
        sockets: list[tuple[str, Callable[[threading.Event], None]]] = [
            ("ingest", self._ingest_loop),
            ("query", self._query_loop),
        ]
        if cfg.events_endpoint:
            sockets.append(("events", self._events_loop))
        ready: list[threading.Event] = []
        for name, target in sockets:
            bound = threading.Event()
            self._spawn(target, f"mapper-{name}", bound)
            ready.append(bound)
        for bound in ready:
            bound.wait(timeout=10.0)
        if self._bind_errors or not all(b.is_set() for b in ready):
            self._stop_threads()
            raise self._fail_start("; ".join(self._bind_errors) or "socket threads did not start in 10 s")
        for index in range(cfg.queries.workers):
            self._spawn(self.pool.work, f"mapper-query-worker-{index}", self._context)
        # query_points' kernels (about 0.2 s from numba's cache) and the backends'
        threading.Thread(target=warm_all_kernels, args=(list(self.ctx.kernel_modules),),
                         name="mapper-kernel-warmup", daemon=True).start()
        for name, work in self.ctx.workers:
            self._spawn(work, f"mapper-{name}", self.ctx.stop)
        log.info("serving: ingest %s, query %s, events %s, map_dir %s, security %s", cfg.ingest_endpoint,
                 cfg.query_endpoint, cfg.events_endpoint or "(off)", os.path.abspath(cfg.map_dir),
                 self._security_mode())

    def request_stop(self) -> None:
        """Ask :meth:`run` to shut down (thread-safe, signal-safe)."""
        self.ctx.stop.set()

    def run(self) -> int:
        """Serve until :meth:`request_stop` (or a signal, see :meth:`install_signal_handlers`);
        then shut down. Returns the exit code."""
        last_report = time.monotonic()
        reported = (-1, -1)
        while not self.ctx.stop.wait(timeout=0.5):
            dead = [t.name for t in self._threads if not t.is_alive()]
            if dead:
                log.error("socket thread(s) %s stopped unexpectedly; shutting down", ", ".join(dead))
                self.stop()
                return 1
            self.persistence.maybe_autosave()
            self._maybe_reload_curve()
            now = time.monotonic()
            if now - last_report >= 30.0:
                last_report = now
                with self.state.lock:
                    current = (self.state.frames_received, self.state.map_version)
                    line = self.state.summary_line()
                if current != reported:
                    reported = current
                    log.info("%s", line)
        return self.stop()

    def stop(self) -> int:
        """Stop the threads, close the sockets, do the final save if configured; returns the exit
        code (0, or 1 when the final save failed). A second call does nothing and returns 0."""
        if self._stopped:
            return 0
        self._stopped = True
        self._stop_threads()
        code = 0
        if self.config.save_on_exit and self.config.autosave_name:
            try:
                self.persistence.save_to(self.config.autosave_name, reason="final")
            except StoreError as exc:
                log.error("final save failed: %s", exc)
                code = 1
        if self._curve is not None:
            self._curve.stop()
        self._context.term()
        with self.state.lock:
            log.info("stopped: %s", self.state.summary_line())
        return code

    def _stop_threads(self) -> None:
        self.ctx.stop.set()
        self.ctx.events.wake.set()  # wakes the events thread
        for thread in self._threads:
            thread.join(timeout=10.0)
            if thread.is_alive():
                log.error("thread %s did not stop within 10 s", thread.name)
        self._threads = [t for t in self._threads if t.is_alive()]

    def install_signal_handlers(self) -> None:
        """Make SIGINT and SIGTERM request a clean shutdown (call from the main thread)."""

        def handler(signum: int, _frame: FrameType | None) -> None:
            log.info("received %s, shutting down", signal.Signals(signum).name)
            self.ctx.stop.set()

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)

    # -- socket loops -------------------------------------------------------------------------

    def _bind(self, kind: int, endpoint: str, bound: threading.Event) -> zmq.Socket[bytes] | None:
        """A socket of ``kind`` bound on ``endpoint`` with the node's limits (``[limits]``
        high-water marks; ROUTERs: the hard size limit and ``ROUTER_MANDATORY``, so a reply to a
        full or vanished peer fails at once and is counted instead of being dropped silently) and,
        with ``curve_dir``, as a CURVE server. None (error recorded) when the bind fails."""
        sock: zmq.Socket[bytes] = self._context.socket(kind)
        sock.setsockopt(zmq.LINGER, 1000)  # flush pending replies for up to 1 s on close
        sock.setsockopt(zmq.SNDHWM, self.config.limits.sndhwm)
        sock.setsockopt(zmq.RCVHWM, self.config.limits.rcvhwm)
        if kind == zmq.ROUTER:
            sock.setsockopt(zmq.MAXMSGSIZE, HARD_LIMIT_FACTOR * self.config.max_message_bytes)
            sock.setsockopt(zmq.ROUTER_MANDATORY, 1)
        if self._curve is not None:
            self._curve.apply(sock)
        try:
            sock.bind(endpoint)
        except zmq.ZMQError as exc:
            self._bind_errors.append(f"cannot bind {endpoint}: {exc}")
            sock.close(linger=0)
            bound.set()
            return None
        bound.set()
        return sock

    def _serve_router(
        self, endpoint: str, bound: threading.Event, handle: Callable[[bytes], bytes], name: str
    ) -> None:
        sock = self._bind(zmq.ROUTER, endpoint, bound)
        if sock is None:
            return
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        timeout_ms = int(self.config.poll_interval_s * 1000)
        try:
            while not self.ctx.stop.is_set():
                if not poller.poll(timeout_ms):
                    continue
                for parts in self._drain_router(sock, name):
                    reply = handle(parts[-1])
                    self._send_reply(sock, [*parts[:-1], reply], name)
        finally:
            sock.close()

    def _drain_router(self, sock: zmq.Socket[bytes], name: str) -> Iterator[list[bytes]]:
        """The messages waiting on ROUTER ``sock`` (identity frames first), until none is left or
        the node stops; a message without an envelope is logged and dropped."""
        while not self.ctx.stop.is_set():
            try:
                parts = sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            if len(parts) < 2:  # a ROUTER always prepends the identity; be defensive
                log.warning("%s: dropped a message without envelope (%d parts)", name, len(parts))
                continue
            yield parts

    def _send_reply(self, sock: zmq.Socket[bytes], parts: list[bytes], name: str) -> bool:
        """Send ``parts`` on ROUTER ``sock`` without ever blocking; a reply the peer cannot take
        (its queue at ``limits.sndhwm``: it does not read) or that has no peer any more is dropped
        and counted in ``ctx.replies_dropped``. Returns True when sent."""
        try:
            sock.send_multipart(parts, zmq.NOBLOCK)
            return True
        except zmq.Again:
            why = "full"
        except zmq.ZMQError as exc:
            why = "gone" if exc.errno == zmq.EHOSTUNREACH else f"error {exc.errno}"
        key = f"{name}:{why}"
        with self.state.lock:
            self.ctx.replies_dropped[key] += 1
            count = self.ctx.replies_dropped[key]
        self.ctx.warn_limited(f"{name}:reply-{why}", "%s: dropped a reply (%s; %d so far)", name, why, count)
        return False

    def _ingest_loop(self, bound: threading.Event) -> None:
        self._serve_router(self.config.ingest_endpoint, bound, self.handle_ingest, "ingest")

    def _query_loop(self, bound: threading.Event) -> None:
        """The query ROUTER. Light requests are answered here, heavy ones
        (:attr:`heavy_request_types`) go to the worker pool, whose replies come back through an
        inproc PULL socket this thread owns (each worker has its own PUSH) and leave on the ROUTER,
        so the ROUTER is only ever used by this thread."""
        if self.config.queries.workers == 0:
            self._serve_router(self.config.query_endpoint, bound, self.handle_query, "query")
            return
        replies: zmq.Socket[bytes] = self._context.socket(zmq.PULL)
        replies.setsockopt(zmq.LINGER, 0)
        replies.bind(self.pool.reply_endpoint)
        sock = self._bind(zmq.ROUTER, self.config.query_endpoint, bound)
        if sock is None:
            replies.close()
            return
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(replies, zmq.POLLIN)
        timeout_ms = int(self.config.poll_interval_s * 1000)
        try:
            while not self.ctx.stop.is_set():
                ready = dict(poller.poll(timeout_ms))
                if replies in ready:
                    while True:
                        try:
                            self._send_reply(sock, replies.recv_multipart(zmq.NOBLOCK), "query")
                        except zmq.Again:
                            break
                if sock not in ready:
                    continue
                for parts in self._drain_router(sock, "query"):
                    started = time.monotonic()
                    reply = self._route_query(parts[:-1], parts[-1])
                    if reply is not None:
                        self._send_reply(sock, [*parts[:-1], reply], "query")
                    self.ctx.pace(started)
        finally:
            sock.close()
            replies.close()

    def _route_query(self, envelope: list[bytes], data: bytes) -> bytes | None:
        """Answer a light request now (its reply), or queue a heavy one for the pool (None: a
        worker replies), or ``busy`` when the pool's queue is full."""
        decoded = self._decode_query(data)
        if isinstance(decoded, bytes):
            return decoded
        waits = bool(getattr(decoded, "settle_timeout_s", None))  # a settled answer may wait: the pool
        light = type(decoded) not in self.heavy_request_types and not waits
        if light and not self.query_points.prompts_are_heavy(decoded):
            return self._answer_query(decoded, data)
        return self.pool.submit(envelope, decoded, data)

    def _events_loop(self, bound: threading.Event) -> None:
        assert self.config.events_endpoint
        sock = self._bind(zmq.PUB, self.config.events_endpoint, bound)
        if sock is None:
            return
        events = self.ctx.events
        try:
            while not self.ctx.stop.is_set():
                events.wake.wait(timeout=self.config.poll_interval_s)
                events.wake.clear()
                while not self.ctx.stop.is_set():
                    event = events.pop()
                    if event is None:
                        break
                    try:  # PUB never blocks: a subscriber at its high-water mark misses the notice
                        sock.send(encode(event), zmq.NOBLOCK)
                    except zmq.ZMQError as exc:
                        log.debug("events: dropped a notice: %s", exc)
        finally:
            sock.close(linger=0)

    # -- message handling (pure bytes -> bytes, never raises) ----------------------------------

    def handle_ingest(self, data: bytes) -> bytes:
        """Handle one message of the ingest endpoint; returns the encoded ``ack`` or ``error``."""
        ctx = self.ctx
        with ctx.state.lock:
            ctx.state.frames_received += 1
        ctx.ingest_last = time.monotonic()
        try:
            msg = decode(data, max_bytes=self.config.max_message_bytes, direction="request")
            if not isinstance(msg, Frame):
                raise ProtocolError(
                    "bad_request",
                    f"the ingest endpoint accepts only 'frame' messages, got {msg.TYPE!r}; "
                    "send queries to the query endpoint",
                )
            reply: Message = ingest_frame(ctx, msg)
        except ProtocolError as exc:
            reply = ctx.error(exc, data, "ingest")
        except Exception as exc:  # a bug: answer, log, keep serving
            reply = ctx.internal(exc, data, "ingest")
        if isinstance(reply, Error) or (isinstance(reply, Ack) and reply.status == "rejected"):
            with ctx.state.lock:
                ctx.state.frames_rejected += 1
        return encode(reply)

    def handle_query(self, data: bytes) -> bytes:
        """Handle one message of the query endpoint via :attr:`query_handlers` (on the calling
        thread; the socket loop sends heavy requests to the worker pool instead)."""
        decoded = self._decode_query(data)
        if isinstance(decoded, bytes):
            return decoded
        return self._answer_query(decoded, data)

    def _decode_query(self, data: bytes) -> Message | bytes:
        """The decoded request (counted by type), or the encoded error reply."""
        try:
            msg = decode(data, max_bytes=self.config.max_message_bytes, direction="request")
        except ProtocolError as exc:
            return encode(self.ctx.error(exc, data, "query"))
        except Exception as exc:
            return encode(self.ctx.internal(exc, data, "query"))
        with self.state.lock:
            self.state.requests_by_type[msg.TYPE] += 1
        return msg

    def _answer_query(self, msg: Message, data: bytes) -> bytes:
        """The encoded reply to a decoded request (never raises)."""
        try:
            handler = self.query_handlers.get(type(msg))
            if handler is None:
                if isinstance(msg, Frame):
                    raise ProtocolError(
                        "bad_request", "'frame' messages go to the ingest endpoint, not the query endpoint"
                    )
                raise ProtocolError("bad_request", f"the query endpoint does not serve {msg.TYPE!r} requests")
            reply = handler(msg)
            msg_id = getattr(msg, "id", None)
            if hasattr(reply, "id") and getattr(reply, "id", None) is None and msg_id is not None:
                reply.id = msg_id
        except ProtocolError as exc:
            reply = self.ctx.error(exc, data, "query")
        except Exception as exc:
            reply = self.ctx.internal(exc, data, "query")
        try:
            return encode(reply)
        except Exception as exc:  # a handler returned something unencodable: still answer
            return encode(self.ctx.internal(exc, data, "query"))

    def _transport_status(self) -> dict[str, Any]:
        """``status`` keys only the transport knows (called with the state lock held)."""
        return {
            "serving": sorted(t.TYPE for t, h in self.query_handlers.items() if not is_not_ready(h)),
            "segment_methods": self.segment.ready_methods(),
            "query_pool": self.pool.stats(),
            "answers": self.query_points.stats(),
            "security": self._security_status(),
        }

    # -- security -----------------------------------------------------------------------------

    def _endpoints(self) -> list[str]:
        """The endpoints the node binds (ingest, query and, when set, events)."""
        cfg = self.config
        return [e for e in (cfg.ingest_endpoint, cfg.query_endpoint, cfg.events_endpoint) if e]

    def _security_mode(self) -> str:
        return security_mode(self._endpoints(), self.config.curve_dir if self._curve is not None else None)

    def _security_status(self) -> dict[str, Any]:
        """``status`` key ``security``: ``mode`` (curve / loopback / insecure), ``curve_dir`` and
        the number of ``allowed_keys`` (CURVE only)."""
        out: dict[str, Any] = {"mode": self._security_mode()}
        if self._curve is not None:
            out["curve_dir"] = os.path.abspath(self._curve.curve_dir)
            out["allowed_keys"] = self._curve.allowed_keys
        return out

    def _maybe_reload_curve(self) -> None:
        """Pick up client keys added to or removed from ``allowed/`` (main thread)."""
        if self._curve is None:
            return
        now = time.monotonic()
        if now - self._last_curve_check < self.config.limits.curve_reload_interval_s:
            return
        self._last_curve_check = now
        try:
            self._curve.reload_if_changed()
        except Exception:  # an unreadable key file: keep the previous list, say why
            log.exception("CurveZMQ: could not reload %s; keeping the previous allowed keys",
                          self._curve.allowed_dir)
