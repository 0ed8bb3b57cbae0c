"""The long-running mapper node: sockets, threads, shared map state, and the request dispatch.

Threads and sockets (a ZeroMQ socket is only ever used by the thread that created it):

- **ingest thread**: ROUTER bound on ``ingest_endpoint``; decodes each ``frame``, updates the
  keyframe window and replies with exactly one ``ack`` or ``error``.
- **integrator thread** (``global_map.integrate_queue`` > 0, the default): fuses each acked
  keyframe into the global map, in ack order, shortly after its ack, then calls the keyframe
  listeners. Its queue is bounded: when it is full the ingest thread waits for room before the
  next ack (backpressure, counted), so nothing acked is dropped. ``save`` (and the final save)
  first drains it; ``status`` reports it (``integration``). With 0 the ingest thread integrates
  before the ack.
- **query thread**: ROUTER bound on ``query_endpoint``; dispatches each request through
  :attr:`MapperNode.query_handlers` (message class -> handler) and replies exactly once. Heavy
  requests (:attr:`MapperNode.heavy_request_types`: ``render``, ``segment_points``) go to the
  **query workers** (``queries.workers`` threads, a queue of ``queries.queue_length``; ``busy``
  beyond it), which hand their replies back through inproc PUSH -> PULL sockets to the query
  thread, the only user of the ROUTER; so ``status`` / ``query_points`` / ``save`` / ``load``
  never wait behind a render. A ``query_points`` whose prompts hold more than
  ``queries.light_text_chars`` characters not embedded yet goes to the pool too (embedding many
  long prompts takes seconds).
- **events thread** (optional): PUB bound on ``events_endpoint``; publishes ``map_updated``
  notices handed to it through a queue by whichever thread changed the map.
- **main thread**: :meth:`MapperNode.run` waits for SIGINT/SIGTERM, does periodic autosaves and,
  on shutdown, stops the threads, does the final save and returns exit code 0.

Ingest and queries never wait on each other's sockets; they share :class:`MapState` behind one
lock, held only for the short state updates (decoding, file I/O and replies happen outside it).

Replies on a ROUTER reuse the request's envelope: every frame but the last is routing
(identities, and the empty delimiter REQ peers add), the last frame is the message. So DEALER
peers (with or without an empty delimiter) and REQ peers all get their reply. Replies to one
connection leave in the order its requests arrived (each socket is served by one thread), except
that a heavy request's reply may leave after those of light requests sent after it (replies
carry the request ``id``; docs/PROTOCOL.md, Transport).

Robustness: every message is handled inside a catch-all; a ``ProtocolError`` becomes its wire
error, anything else an ``internal`` error (logged with traceback), and the node keeps serving.
A rejected message changes nothing but the counters.

The global semantic point map (:mod:`mapper.node.global_map`) is fed by the integrator thread: after
a frame became a keyframe and was acked, it is integrated under the map's own lock. Queries
(:mod:`mapper.node.queries`) read the map's immutable per-version snapshot, so a query never waits on an
integrate (beyond the one copy per map version) and an integrate never waits on a query.

Extension points: ``register_query_handler(MsgClass, handler)`` replaces a request type's
handler (``render`` still answers ``not_ready``); ``register_segment_method(name, handler)``
serves a ``segment_points`` method (``"govnesf"`` answers ``not_ready`` until the learned model
registers it); ``GlobalSemanticMap.fusion`` is the feature fusion rule the learned model may
replace; the cost volume and OV cache hook :attr:`MapState.window`'s ``on_add`` / ``on_evict``
callbacks (called under the state lock); saving more state goes through ``MapState.snapshot`` /
``restore`` and the ``global.*`` arrays of the map file.
"""

from __future__ import annotations

import copy
import importlib
import logging
import math
import os
import queue
import signal
import threading
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from types import FrameType
from typing import TYPE_CHECKING, Any

import numpy as np
import zmq

from mapper.node.config import NodeConfig, to_dict
from mapper.node.evicted_views import EvictedViews, EvictedViewStore
from mapper.node.global_map import GlobalMapSnapshot, GlobalSemanticMap
from mapper.node.keyframe_queue import KeyframeQueue
from mapper.node.security import CurveServer, exposure_problem, security_mode
from mapper.node.store import MapStore, StoreError, StoreWriteError
from mapper.node.window import (
    Keyframe,
    KeyframeWindow,
    fit_image,
    fit_intrinsics,
    keyframes_from_arrays,
    keyframes_to_arrays,
)
from protocol.errors import ProtocolError
from protocol.messages import (
    Ack,
    AckStatus,
    Error,
    Frame,
    Load,
    MapUpdated,
    Message,
    Ok,
    Points,
    QueryPoints,
    Render,
    Save,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    encode,
    error_reply,
    peek_id,
)

if TYPE_CHECKING:
    from mapper.node.queries import AnswerCache, AnswerKey, BlockLabelCache

log = logging.getLogger("mapper.node.service")

QueryHandler = Callable[[Message], Message]
"""Takes a decoded request, returns the reply (its ``id`` is filled in by the node); raises
``ProtocolError`` for an error reply."""

SegmentHandler = Callable[[SegmentPoints], Segmentation]
"""Serves one ``segment_points`` method: takes the request, returns the reply (``id`` filled in by
the node); raises ``ProtocolError`` (e.g. ``not_ready``) for an error reply."""

WARN_INTERVAL_S = 5.0
"""Rejections and errors are logged as warnings at most this often per kind (DEBUG otherwise)."""

HARD_LIMIT_FACTOR = 4
"""ZeroMQ drops messages above ``HARD_LIMIT_FACTOR * max_message_bytes`` at the transport (the
peer is disconnected, no reply) so a hostile sender cannot make the node allocate without bound;
between ``max_message_bytes`` and that, the node answers ``too_large``."""


@dataclass(frozen=True)
class _IntegrateJob:
    """One acked keyframe waiting for the integrator: the map it goes into (the one current when it
    was acked: a ``load`` in between leaves the new map alone), its map version and ov space."""

    target: GlobalSemanticMap
    keyframe: Keyframe
    map_version: int
    ov_space: str | None
    submitted: float  # time.monotonic() at the ack


@dataclass(frozen=True)
class MapSnapshot:
    """An immutable view of the map for saving (taken under the lock, written outside it)."""

    map_version: int
    keyframes: tuple[Keyframe, ...]
    ov_space: str | None
    ov_dim: int | None


class MapState:
    """Everything the node knows, behind :attr:`lock`. Counters are part of the state."""

    def __init__(self, config: NodeConfig) -> None:
        self.lock = threading.Lock()
        self.config = config
        self.window = KeyframeWindow(config.window)
        self.global_map = GlobalSemanticMap(config.global_map)
        """Global semantic point map (own lock; kept when keyframes leave the window)."""
        self.map_version = 0
        self.ov_space: str | None = config.ov_space
        """Embedding space of the map (pinned by config, else set by the first keyframe with ov)."""
        self.ov_dim: int | None = None
        """Feature dimension of that space, learned from the first keyframe with ov."""
        self.frames_received = 0
        self.frames_rejected = 0
        self.ack_counts: Counter[str] = Counter()
        self.error_counts: Counter[str] = Counter()
        self.requests_by_type: Counter[str] = Counter()
        self.keyframes_evicted = 0
        self.last_save: dict[str, Any] | None = None
        self.started_monotonic = time.monotonic()

    # -- called with the lock held ------------------------------------------------------------

    def memory_bytes(self) -> int:
        """Bytes of map data held: keyframe arrays plus the global map's arrays (later stages add
        their volumes and caches)."""
        return self.window.nbytes + self.global_map.nbytes

    def snapshot(self) -> MapSnapshot:
        return MapSnapshot(self.map_version, self.window.keyframes, self.ov_space, self.ov_dim)


def _rss_bytes() -> int | None:
    """Resident set size of this process (Linux), for operators; None where unavailable."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def _warm_kernels(module: str) -> None:
    """Compile (or load from numba's cache) the compiled kernels of ``module`` (its ``warm_up``), so
    the first query that needs them does not pay for it; a failure is logged (that query compiles
    them instead and reports it)."""
    try:
        importlib.import_module(module).warm_up()
    except Exception:
        log.exception("warm-up of the kernels of %s failed", module)


def _warm_all_kernels(modules: list[str]) -> None:
    """:func:`_warm_kernels` of each module, in order (one background thread)."""
    for module in modules:
        _warm_kernels(module)


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
    """The node. ``start()`` binds the sockets (raising if one cannot be bound), ``run()`` serves
    until a signal or :meth:`request_stop`, ``stop()`` shuts down. Also usable in-process."""

    def __init__(self, config: NodeConfig) -> None:
        self.config = config
        limit_blas_threads(config.limits.blas_threads)
        self.state = MapState(config)
        self.store = MapStore(config.map_dir)
        self.query_handlers: dict[type[Message], QueryHandler] = {
            StatusRequest: self._handle_status,
            Save: self._handle_save,
            Load: self._handle_load,
            QueryPoints: self._handle_query_points,
            SegmentPoints: self._handle_segment_points,
            Render: self._not_ready("render", "rendering"),
        }
        """Dispatch table of the query endpoint: request class -> handler."""
        self.segment_methods: dict[str, SegmentHandler] = {
            "govnesf": _govnesf_not_loaded,
            "average": lambda msg: self._segment_average(msg, use_depth=False),
            "average_depth": lambda msg: self._segment_average(msg, use_depth=True),
        }
        """``segment_points`` methods: name -> handler (the learned model registers "govnesf")."""
        self.heavy_request_types: set[type[Message]] = {Render, SegmentPoints}
        """Requests answered by the query worker pool (``queries.workers`` threads, bounded queue:
        ``busy`` beyond it), so that light requests never wait behind them."""
        self._heavy_jobs: queue.Queue[tuple[list[bytes], Message, bytes]] = queue.Queue(
            maxsize=config.queries.queue_length
        )
        self._heavy_lock = threading.Lock()
        self._heavy_running = 0
        self._heavy_done = 0
        self._heavy_busy = 0
        self._reply_endpoint = f"inproc://mapper-query-replies-{id(self):x}"
        """Workers PUSH ``[*envelope, reply]`` here; the query thread PULLs and sends on its ROUTER."""
        self._warmed_spaces: set[str] = set()
        self._stop = threading.Event()
        self._context = zmq.Context()
        self._threads: list[threading.Thread] = []
        self._events: KeyframeQueue[MapUpdated] = KeyframeQueue(config.limits.events_queue_max)
        """``map_updated`` notices for the events thread (bounded: the oldest is dropped, counted)."""
        self._curve: CurveServer | None = None
        """CURVE keys and ZAP authenticator when ``curve_dir`` is set (made by :meth:`start`)."""
        self._last_curve_check = time.monotonic()
        self._ingest_last = -math.inf
        """When the ingest endpoint last handled a message (monotonic s; :meth:`_pace_queries`)."""
        self.frames_duplicate = 0
        """Frames received again (same seq, stamp, camera, pose and K) while already a keyframe in the
        window: acked ``accepted`` with a ``duplicate`` reason, not added twice (state lock)."""
        self.frames_downscaled = 0
        """Keyframes kept shrunk to ``window.max_image_side`` (ingest thread)."""
        self.replies_dropped: Counter[str] = Counter()
        """Replies not sent, by ``"<endpoint>:<why>"``: ``full`` (the peer's queue is at ``sndhwm``:
        it does not read its replies) or ``gone`` (the peer disconnected)."""
        self._bind_errors: list[str] = []
        self._saved_version: int | None = None
        self._last_warning: dict[str, float] = {}
        self._stopped = False
        self._last_autosave = time.monotonic()
        self.memory_providers: list[Callable[[], int]] = []
        """Extra holders of map memory (e.g. the learned-model runtime); summed into ``memory_bytes``."""
        self.status_providers: dict[str, Callable[[], Any]] = {}
        """Extra ``status`` keys computed on request (e.g. ``"model"``: the runtime's stats)."""
        self.keyframe_listeners: list[Callable[[Keyframe, int], None]] = []
        """Called on the integrator thread (the ingest thread when integration is inline), outside
        the state lock, after a new keyframe went into the window and the global map, with the
        keyframe and its map version, in ack order. Must be quick (queue the work) and must not
        raise."""
        self.feature_listeners: list[Callable[[Keyframe], None]] = []
        """Called on the in-process OV backend's worker, outside the state lock, right after a
        keyframe WITHOUT input depth got its features swapped into the window, with the featured
        keyframe: plugins that put points of that keyframe into the global map before its features
        existed (triangulation, plane-sweep stereo) fuse the features into them now. Must not
        raise."""
        self.surface_points: list[Callable[[], np.ndarray]] = []
        """Providers of measured surface points (world, (N, 3)) other than input depth, e.g. the
        triangulated points and the kept plane-sweep depths of RGB-only keyframes: ``render``
        (``model.surface_from_map = "auto"``) renders at their surfaces when the window's
        keyframes mostly lack input depth. Called on the query thread; must not raise."""
        self.load_listeners: list[Callable[[GlobalSemanticMap, int], None]] = []
        """Called on the thread that loaded a map (``load`` or the autosave at start), outside the
        state lock, right after the loaded map replaced the window and the global map, with the new
        global map and its map version: whatever belongs to the replaced map can go now (keyframes
        acked before the load carry a map version up to the replaced map's, below this one). Must be
        quick and must not raise."""
        self._integrate_jobs: queue.Queue[_IntegrateJob] = queue.Queue(
            maxsize=max(config.global_map.integrate_queue, 1)
        )
        """Keyframes acked but not yet integrated into the global map (``global_map.integrate_queue``)."""
        self._integrate_cond = threading.Condition()
        """Guards the integration counters below (never held while taking the state lock)."""
        self._integrate_submitted = 0
        """Keyframes handed to integration so far (written under the *state* lock, with the window add)."""
        self._integrate_done = 0
        self._integrate_errors = 0
        self._integrate_waits = 0
        self._integrate_wait_s = 0.0
        self._integrate_inline = 0
        self._label_cache: BlockLabelCache | None = None
        """``query_points``' per-block scoring, reused across map versions (``queries.label_cache_blocks``;
        made by the first query: :mod:`mapper.node.queries` imports SciPy)."""
        self._answer_cache: AnswerCache | None = None
        """``query_points``' recent answers (``queries.answer_max_age_s``); made with the label cache."""
        self._answers_lock = threading.Lock()
        """Guards making the two caches and the refresh bookkeeping."""
        self._refresh_jobs: queue.Queue[tuple[AnswerKey, QueryPoints]] = queue.Queue(
            maxsize=max(1, config.queries.answer_cache_entries)
        )
        """Stale ``query_points`` answers to recompute (the answer-refresh thread)."""
        self._refresh_pending: set[AnswerKey] = set()
        self.answer_refreshes = 0
        self._integrate_lag_s: deque[float] = deque(maxlen=1000)
        """Ack-to-integrated seconds of recent keyframes (status ``integration.lag_ms_*``)."""
        self._integrator: threading.Thread | None = None
        self._inline_lock = threading.RLock()
        """Serialises integrations done outside the integrator thread (they keep ack order)."""
        self.workers: list[tuple[str, Callable[[threading.Event], None]]] = []
        """Background threads ``(name, target)`` started by :meth:`start` after the sockets are
        bound; ``target(stop_event)`` runs until the event is set and must not raise."""
        self.evicted_views: EvictedViews | None = None
        """The worker that keeps evicted keyframes' views for the averaging methods
        (``queries.evicted_views``; :mod:`mapper.node.evicted_views`)."""
        if config.queries.evicted_views != "off":
            self.evicted_views = EvictedViews(self)
            self.evicted_views.install()
        self.kernel_modules: list[str] = ["mapper.node.query_kernels"]
        """Modules whose compiled kernels :meth:`start` warms in the background (each module's
        ``warm_up``: compiled, or loaded from numba's cache), so that no first query pays for it;
        plugins add theirs (the learned model: its point kernels)."""
        if self.evicted_views is not None:
            self.kernel_modules.append("mapper.node.evicted_views")  # its running-mean kernel

    # -- extension points ---------------------------------------------------------------------

    def register_query_handler(self, message_type: type[Message], handler: QueryHandler) -> None:
        """Serve ``message_type`` requests on the query endpoint with ``handler`` (replacing any)."""
        self.query_handlers[message_type] = handler

    def register_segment_method(self, method: str, handler: SegmentHandler) -> None:
        """Serve ``segment_points`` requests with ``method`` (e.g. "govnesf") by ``handler``."""
        self.segment_methods[method] = handler

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        """Start the socket threads; return once every socket is bound. Raises ``RuntimeError``
        naming the endpoint when a bind fails (e.g. address in use). With ``load_autosave_on_start``
        the autosaved map is loaded first (see :meth:`load_autosave`).

        Refuses (``RuntimeError``) a non-loopback bind without ``curve_dir`` unless ``insecure``
        (:func:`mapper.node.security.exposure_problem`); with ``curve_dir`` the key files must load."""
        cfg = self.config
        limit_blas_threads(cfg.limits.blas_threads)  # again: plugins may have loaded another BLAS (OpenCV's)
        endpoints = self._endpoints()
        problem = exposure_problem(endpoints, cfg.curve_dir, cfg.insecure)
        if problem:
            self._context.term()
            self._stopped = True
            raise RuntimeError(problem)
        if cfg.curve_dir:
            try:
                self._curve = CurveServer(self._context, cfg.curve_dir)
                self._curve.start()
            except Exception as exc:  # a key file problem (ConfigError) or the authenticator
                if self._curve is not None:
                    self._curve.stop()
                self._context.term()
                self._stopped = True
                raise RuntimeError(f"CurveZMQ (curve_dir {cfg.curve_dir!r}): {exc}") from None
        elif security_mode(endpoints, None) == "insecure":
            log.warning(
                "INSECURE: serving %s without CurveZMQ authentication (insecure = true): anyone who can "
                "reach these addresses can stream frames, query, save and load maps (docs/SECURITY.md)",
                ", ".join(e for e in endpoints if security_mode([e], None) == "insecure"),
            )
        self.load_autosave()
        if self.config.global_map.integrate_queue > 0:
            # before the socket threads, so the first keyframe already goes to it; on stop it
            # finishes its queue (what the ingest thread submits after that is integrated inline)
            self._integrator = threading.Thread(
                target=self._integrator_loop, args=(self._stop,), name="mapper-integrator", daemon=True
            )
            self._integrator.start()
            self._threads.append(self._integrator)
        workers: list[tuple[str, Callable[[threading.Event], None]]] = [
            ("ingest", self._ingest_loop),
            ("query", self._query_loop),
        ]
        if self.config.events_endpoint:
            workers.append(("events", self._events_loop))
        ready: list[threading.Event] = []
        for name, target in workers:
            bound = threading.Event()
            thread = threading.Thread(target=target, args=(bound,), name=f"mapper-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
            ready.append(bound)
        for bound in ready:
            bound.wait(timeout=10.0)
        if self._bind_errors or not all(b.is_set() for b in ready):
            self._stop_threads()
            if self._curve is not None:
                self._curve.stop()
            self._context.term()
            self._stopped = True
            raise RuntimeError("; ".join(self._bind_errors) or "socket threads did not start in 10 s")
        for index in range(self.config.queries.workers):
            thread = threading.Thread(
                target=self._heavy_worker, name=f"mapper-query-worker-{index}", daemon=True
            )
            thread.start()
            self._threads.append(thread)
        thread = threading.Thread(
            target=self._refresh_loop, args=(self._stop,), name="mapper-answer-refresh", daemon=True
        )
        thread.start()
        self._threads.append(thread)
        # query_points' kernels (about 0.2 s from numba's cache) and the plugins'
        threading.Thread(target=_warm_all_kernels, args=(list(self.kernel_modules),),
                         name="mapper-kernel-warmup", daemon=True).start()
        for name, work in self.workers:
            thread = threading.Thread(target=work, args=(self._stop,), name=f"mapper-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        log.info(
            "serving: ingest %s, query %s, events %s, map_dir %s, security %s",
            self.config.ingest_endpoint,
            self.config.query_endpoint,
            self.config.events_endpoint or "(off)",
            os.path.abspath(self.config.map_dir),
            self._security_mode(),
        )

    def load_autosave(self) -> bool:
        """Load ``autosave_name`` from the map directory if configured and present. A file that
        cannot be loaded is renamed to ``NAME.govmap.unreadable`` (kept for inspection, not
        overwritten by the next autosave) and the node starts empty. Returns True if loaded."""
        cfg = self.config
        if not (cfg.load_autosave_on_start and cfg.autosave_name):
            return False
        try:
            path = self.store.path_for(cfg.autosave_name)
        except StoreError as exc:
            log.error("autosave %r: %s", cfg.autosave_name, exc)
            return False
        if not path.is_file():
            log.info("no autosave at %s: starting with an empty map", path)
            return False
        try:
            message = self._load_map(cfg.autosave_name)
        except ProtocolError as exc:
            aside = path.with_name(path.name + ".unreadable")
            log.error("cannot load the autosave %s (%s); moved it to %s and starting empty", path,
                      exc.message, aside)
            try:
                os.replace(path, aside)
            except OSError as move_exc:
                log.error("could not move %s aside: %s", path, move_exc)
            return False
        log.info("start-up: %s", message)
        with self.state.lock:
            self._saved_version = self.state.map_version
        return True

    def request_stop(self) -> None:
        """Ask :meth:`run` to shut down (thread-safe, signal-safe)."""
        self._stop.set()

    def run(self) -> int:
        """Serve until :meth:`request_stop` (or a signal, see :meth:`install_signal_handlers`);
        then shut down. Returns the exit code."""
        last_report = time.monotonic()
        reported = (-1, -1)
        while not self._stop.wait(timeout=0.5):
            dead = [t.name for t in self._threads if not t.is_alive()]
            if dead:
                log.error("socket thread(s) %s stopped unexpectedly; shutting down", ", ".join(dead))
                self.stop()
                return 1
            self._maybe_autosave()
            self._maybe_reload_curve()
            now = time.monotonic()
            if now - last_report >= 30.0:
                last_report = now
                with self.state.lock:
                    current = (self.state.frames_received, self.state.map_version)
                    line = self._summary_line()
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
                self._save_to(self.config.autosave_name, reason="final")
            except StoreError as exc:
                log.error("final save failed: %s", exc)
                code = 1
        if self._curve is not None:
            self._curve.stop()
        self._context.term()
        with self.state.lock:
            log.info("stopped: %s", self._summary_line())
        return code

    def _stop_threads(self) -> None:
        self._stop.set()
        self._events.wake.set()  # wakes the events thread
        for thread in self._threads:
            thread.join(timeout=10.0)
            if thread.is_alive():
                log.error("thread %s did not stop within 10 s", thread.name)
        self._threads = [t for t in self._threads if t.is_alive()]

    def install_signal_handlers(self) -> None:
        """Make SIGINT and SIGTERM request a clean shutdown (call from the main thread)."""

        def handler(signum: int, _frame: FrameType | None) -> None:
            log.info("received %s, shutting down", signal.Signals(signum).name)
            self._stop.set()

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
            while not self._stop.is_set():
                if not poller.poll(timeout_ms):
                    continue
                for parts in self._drain_router(sock, name):
                    reply = handle(parts[-1])
                    self._send_reply(sock, [*parts[:-1], reply], name)
        finally:
            sock.close()

    def _pace_queries(self, started: float, now: float | None = None) -> None:
        """Ingest first. While frames are arriving (one handled within the last
        ``limits.ingest_active_s``), a query-serving thread (the query socket's, a heavy worker)
        that has just spent ``elapsed`` seconds on a request pauses ``elapsed * (1 - share) /
        share`` (``share`` = ``limits.query_share``; at most ``limits.query_pause_max_s``), so
        each uses at most that share of the CPU and a query storm cannot starve the ingest thread.
        Requests wait in ZeroMQ meanwhile (bounded by ``rcvhwm``). Called by the socket loops
        only, never by :meth:`handle_query`."""
        limits = self.config.limits
        if limits.query_share >= 1.0:
            return
        now = time.monotonic() if now is None else now
        if now - self._ingest_last > limits.ingest_active_s:
            return
        share = limits.query_share
        pause = min((now - started) * (1.0 - share) / share, limits.query_pause_max_s)
        if pause > 0:
            self._stop.wait(pause)

    def _drain_router(self, sock: zmq.Socket[bytes], name: str) -> Iterator[list[bytes]]:
        """The messages waiting on ROUTER ``sock`` (identity frames first), until none is left or
        the node stops; a message without an envelope is logged and dropped."""
        while not self._stop.is_set():
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
        and counted in :attr:`replies_dropped`. Returns True when sent."""
        try:
            sock.send_multipart(parts, zmq.NOBLOCK)
            return True
        except zmq.Again:
            why = "full"
        except zmq.ZMQError as exc:
            why = "gone" if exc.errno == zmq.EHOSTUNREACH else f"error {exc.errno}"
        key = f"{name}:{why}"
        with self.state.lock:
            self.replies_dropped[key] += 1
            count = self.replies_dropped[key]
        self._warn_limited(f"{name}:reply-{why}", "%s: dropped a reply (%s; %d so far)", name, why, count)
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
        replies.bind(self._reply_endpoint)
        sock = self._bind(zmq.ROUTER, self.config.query_endpoint, bound)
        if sock is None:
            replies.close()
            return
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(replies, zmq.POLLIN)
        timeout_ms = int(self.config.poll_interval_s * 1000)

        try:
            while not self._stop.is_set():
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
                    self._pace_queries(started)
        finally:
            sock.close()
            replies.close()

    def _route_query(self, envelope: list[bytes], data: bytes) -> bytes | None:
        """Answer a light request now (its reply), or queue a heavy one for the pool (None: a
        worker replies), or ``busy`` when the pool's queue is full."""
        decoded = self._decode_query(data)
        if isinstance(decoded, bytes):
            return decoded
        if type(decoded) not in self.heavy_request_types and not self._new_prompts_are_heavy(decoded):
            return self._answer_query(decoded, data)
        try:
            self._heavy_jobs.put_nowait((envelope, decoded, data))
        except queue.Full:
            with self._heavy_lock:
                self._heavy_busy += 1
                running = self._heavy_running
            cfg = self.config.queries
            exc = ProtocolError(
                "busy",
                f"{decoded.TYPE}: {running} heavy request(s) running and {cfg.queue_length} waiting "
                f"(queries.workers = {cfg.workers}, queries.queue_length = {cfg.queue_length}); "
                "retry later",
            )
            return encode(self._error(exc, data, "query"))
        return None

    def _new_prompts_are_heavy(self, msg: Message) -> bool:
        """A ``query_points`` whose prompts hold more than ``queries.light_text_chars`` characters
        the text encoder has not embedded yet (embedding them is the slow part: seconds for many
        long prompts), so that it does not hold up the light requests behind it."""
        if not isinstance(msg, QueryPoints):
            return False
        from mapper.node.queries import DEFAULT_NEGATIVES, normalise_query

        negatives = DEFAULT_NEGATIVES if msg.negatives is None else msg.negatives
        try:
            encoder = self._text_encoder("query_points")
            prompts = [normalise_query(t) for t in (*msg.texts, *negatives)]
            measure = getattr(encoder, "uncached_chars", None)
            new_chars = measure(prompts) if callable(measure) else sum(len(t) for t in prompts)
        except Exception:  # not_ready or an encoder's fault: the handler answers it, at once
            return False
        return bool(new_chars > self.config.queries.light_text_chars)

    def _heavy_worker(self) -> None:
        """One thread of the heavy-request pool: answer queued requests until stopped; every reply
        goes back to the query thread through this worker's own PUSH socket."""
        push: zmq.Socket[bytes] = self._context.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.connect(self._reply_endpoint)
        try:
            while not self._stop.is_set():
                try:
                    envelope, msg, data = self._heavy_jobs.get(timeout=self.config.poll_interval_s)
                except queue.Empty:
                    continue
                with self._heavy_lock:
                    self._heavy_running += 1
                started = time.monotonic()
                try:
                    reply = self._answer_query(msg, data)  # never raises
                finally:
                    with self._heavy_lock:
                        self._heavy_running -= 1
                        self._heavy_done += 1
                try:
                    push.send_multipart([*envelope, reply])
                except zmq.ZMQError as exc:  # the context is closing
                    log.warning("query worker: could not hand back a reply: %s", exc)
                self._pace_queries(started)
        finally:
            push.close()

    def answer_stats(self) -> dict[str, int]:
        """``query_points`` answers: computed, reused (same version / stale), background refreshes,
        cached questions, label-cache blocks scored and reused."""
        answers, labels = self._answer_cache, self._label_cache
        out = answers.stats() if answers is not None else {
            "computed": 0, "reused_same_version": 0, "reused_stale": 0, "entries": 0, "bytes": 0
        }  # fmt: skip
        out["refreshes"] = self.answer_refreshes
        out["label_blocks_scored"] = labels.misses if labels is not None else 0
        out["label_blocks_reused"] = labels.hits if labels is not None else 0
        return out

    def query_pool_stats(self) -> dict[str, int]:
        """The heavy-request pool, for ``status``: ``workers``, ``queue_length``, ``running``,
        ``queued``, ``done`` (answered by a worker) and ``busy`` (refused: queue full)."""
        with self._heavy_lock:
            return {
                "workers": self.config.queries.workers,
                "queue_length": self.config.queries.queue_length,
                "running": self._heavy_running,
                "queued": self._heavy_jobs.qsize(),
                "done": self._heavy_done,
                "busy": self._heavy_busy,
            }

    def _events_loop(self, bound: threading.Event) -> None:
        assert self.config.events_endpoint
        sock = self._bind(zmq.PUB, self.config.events_endpoint, bound)
        if sock is None:
            return
        try:
            while not self._stop.is_set():
                self._events.wake.wait(timeout=self.config.poll_interval_s)
                self._events.wake.clear()
                while not self._stop.is_set():
                    event = self._events.pop()
                    if event is None:
                        break
                    try:  # PUB never blocks: a subscriber at its high-water mark misses the notice
                        sock.send(encode(event), zmq.NOBLOCK)
                    except zmq.ZMQError as exc:
                        log.debug("events: dropped a notice: %s", exc)
        finally:
            sock.close(linger=0)

    def _publish(self, map_version: int, keyframes: int) -> None:
        """Queue a ``map_updated`` notice (O(1), never blocks; the oldest beyond
        ``limits.events_queue_max`` is dropped and counted)."""
        if self.config.events_endpoint:
            self._events.put(MapUpdated(map_version=map_version, keyframes=keyframes))

    # -- message handling (pure bytes -> bytes, never raises) ----------------------------------

    def handle_ingest(self, data: bytes) -> bytes:
        """Handle one message of the ingest endpoint; returns the encoded ``ack`` or ``error``."""
        with self.state.lock:
            self.state.frames_received += 1
        self._ingest_last = time.monotonic()
        try:
            msg = decode(data, max_bytes=self.config.max_message_bytes, direction="request")
            if not isinstance(msg, Frame):
                raise ProtocolError(
                    "bad_request",
                    f"the ingest endpoint accepts only 'frame' messages, got {msg.TYPE!r}; "
                    "send queries to the query endpoint",
                )
            reply: Message = self._ingest_frame(msg)
        except ProtocolError as exc:
            reply = self._error(exc, data, "ingest")
        except Exception as exc:  # a bug: answer, log, keep serving
            reply = self._internal(exc, data, "ingest")
        if isinstance(reply, Error) or (isinstance(reply, Ack) and reply.status == "rejected"):
            with self.state.lock:
                self.state.frames_rejected += 1
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
            return encode(self._error(exc, data, "query"))
        except Exception as exc:
            return encode(self._internal(exc, data, "query"))
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
            reply = self._error(exc, data, "query")
        except Exception as exc:
            reply = self._internal(exc, data, "query")
        try:
            return encode(reply)
        except Exception as exc:  # a handler returned something unencodable: still answer
            return encode(self._internal(exc, data, "query"))

    def _error(self, exc: ProtocolError, data: bytes, where: str) -> Error:
        with self.state.lock:
            self.state.error_counts[exc.code] += 1
            count = self.state.error_counts[exc.code]
        self._warn_limited(
            f"{where}:{exc.code}", "%s: %s error (%d so far): %s", where, exc.code, count, exc.message
        )
        return error_reply(exc, peek_id(data))

    def _warn_limited(self, key: str, fmt: str, *args: object) -> None:
        """Log a warning at most once per ``WARN_INTERVAL_S`` per key (DEBUG otherwise), so a
        misbehaving client cannot flood the log."""
        now = time.monotonic()
        if now - self._last_warning.get(key, -math.inf) >= WARN_INTERVAL_S:
            self._last_warning[key] = now
            log.warning(fmt, *args)
        else:
            log.debug(fmt, *args)

    def _internal(self, exc: Exception, data: bytes, where: str) -> Error:
        log.error("%s: internal error while handling a message:\n%s", where, traceback.format_exc())
        with self.state.lock:
            self.state.error_counts["internal"] += 1
        message = f"internal error ({type(exc).__name__}) while handling the request; see the node log"
        return error_reply(ProtocolError("internal", message), peek_id(data))

    # -- ingest -------------------------------------------------------------------------------

    def _ingest_frame(self, frame: Frame) -> Ack:
        keyframe = Keyframe(
            seq=frame.seq,
            stamp_ns=frame.stamp_ns,
            camera=frame.camera,
            K=frame.K,
            world_from_cam=frame.world_from_cam,
            rgb=frame.rgb,
            depth_m=frame.depth_m,
            ov=frame.ov,
            ov_space=frame.ov_space,
        )
        state = self.state
        max_side = self.config.window.max_image_side
        kept_K = fit_intrinsics(frame.K, frame.width, frame.height, max_side)  # K as a keyframe keeps it
        if 0 < max_side < max(frame.width, frame.height):
            with state.lock:  # shrink only what will be a keyframe (the ingest thread alone adds)
                will_keep = state.window.is_keyframe(frame.camera, frame.world_from_cam)[0]
            if will_keep:
                fitted = fit_image(keyframe, max_side)  # outside the lock (tens of ms at 4096 px)
                if fitted is not keyframe:
                    keyframe = fitted
                    self.frames_downscaled += 1
        with state.lock:
            for kept in state.window.keyframes:
                same_id = (kept.seq, kept.stamp_ns, kept.camera) == (frame.seq, frame.stamp_ns, frame.camera)
                if same_id and np.array_equal(kept.world_from_cam, frame.world_from_cam) and np.array_equal(
                    kept.K, kept_K
                ):
                    # a resent frame (the client's retry after a timeout or a node restart) that is
                    # already a keyframe (same seq, stamp, camera and pose): acked again, not added twice
                    state.ack_counts["accepted"] += 1
                    self.frames_duplicate += 1
                    return Ack(seq=frame.seq, status="accepted", map_version=state.map_version, id=frame.id,
                               reason=f"duplicate: frame seq {frame.seq} is already a keyframe of the map")
            if frame.ov is not None:
                if state.ov_space is not None and frame.ov_space != state.ov_space:
                    raise ProtocolError(
                        "ov_space_mismatch",
                        f"frame seq {frame.seq}: ov_space {frame.ov_space!r} differs from the map's "
                        f"{state.ov_space!r}; send features of that space, or load/start a map for yours",
                    )
                dim = int(frame.ov.shape[2])
                if state.ov_dim is not None and dim != state.ov_dim:
                    return self._reject(
                        frame,
                        f"ov feature dimension {dim} differs from the map's {state.ov_dim} "
                        f"for space {state.ov_space!r}",
                    )
            update = state.window.consider(keyframe)
            status: AckStatus
            if update.added:
                if frame.ov is not None:
                    state.ov_space = frame.ov_space
                    state.ov_dim = int(frame.ov.shape[2])
                state.map_version += 1
                state.keyframes_evicted += len(update.evicted)
                if self.evicted_views is not None:
                    for old in update.evicted:
                        self.evicted_views.put(old, state.global_map)
                status = "keyframe"
                self._publish(state.map_version, len(state.window))
            else:
                status = "accepted"
            state.ack_counts[status] += 1
            version = state.map_version
            job = None
            if update.added:
                self._integrate_submitted += 1  # with the window add: save's drain target
                job = _IntegrateJob(state.global_map, keyframe, version, state.ov_space, time.monotonic())
        if job is not None:
            # outside the state lock: the integrator thread fuses it into the global map shortly
            # after this ack (queries keep working on their snapshot meanwhile); inline when
            # ``global_map.integrate_queue`` is 0 or the integrator is not running
            self._submit_integration(job)
        log.debug(
            "frame seq %d (%s): %s, moved %.3f m, turned %.1f deg",
            frame.seq,
            frame.camera,
            status,
            update.translation_m,
            update.rotation_deg,
        )
        return Ack(seq=frame.seq, status=status, map_version=version, id=frame.id)

    def integration_backlog(self) -> int:
        """Keyframes acked and not yet integrated into the global map (no lock needed: a read of
        two counters, exact or one keyframe off)."""
        with self._integrate_cond:
            done = self._integrate_done
        return max(self._integrate_submitted - done, 0)

    def _integrator_alive(self) -> bool:
        return self._integrator is not None and self._integrator.is_alive()

    def _submit_integration(self, job: _IntegrateJob) -> None:
        """Queue an acked keyframe for the integrator. When ``global_map.integrate_queue``
        keyframes are already waiting, wait for room (backpressure: the ack waits; counted), so
        nothing acked is dropped. Inline when the queue is off or the integrator is not running."""
        if self.config.global_map.integrate_queue == 0 or not self._integrator_alive():
            self._integrate_now(job)
            return
        try:
            self._integrate_jobs.put_nowait(job)
            return
        except queue.Full:
            pass
        started = time.monotonic()
        while True:
            try:
                self._integrate_jobs.put(job, timeout=self.config.poll_interval_s)
                break
            except queue.Full:
                if not self._integrator_alive():  # stopped meanwhile: do its work here, in order
                    self._integrate_now(job)
                    break
        with self._integrate_cond:
            self._integrate_waits += 1
            self._integrate_wait_s += time.monotonic() - started

    def _integrate_keyframe(self, job: _IntegrateJob) -> None:
        """Fuse one acked keyframe into its global map, then tell the keyframe listeners (not when a
        ``load`` replaced that map meanwhile). Never raises: a failure is logged and counted in
        status ``integration.errors``."""
        keyframe = job.keyframe
        try:
            stats = job.target.integrate(keyframe, map_version=job.map_version)
            log.debug("frame seq %d: %d points into the global map (%d new voxels) in %.1f ms%s",
                      keyframe.seq, stats.points, stats.voxels_new, 1e3 * stats.seconds,
                      f" ({stats.skipped})" if stats.skipped else "")
            if keyframe.ov is not None and job.ov_space is not None:
                self._warm_text_encoder(job.ov_space)
            if job.target is not self.state.global_map:
                return  # a ``load`` replaced the map (and the window) since this keyframe's ack
            for listener in self.keyframe_listeners:
                listener(keyframe, job.map_version)
        except Exception:
            log.error("integrating keyframe seq %d failed:\n%s", keyframe.seq, traceback.format_exc())
            with self._integrate_cond:
                self._integrate_errors += 1
        finally:
            with self._integrate_cond:
                self._integrate_done += 1
                self._integrate_lag_s.append(time.monotonic() - job.submitted)
                self._integrate_cond.notify_all()

    def _integrate_now(self, job: _IntegrateJob) -> None:
        """Integrate on the calling thread (counted as ``inline``), after anything a stopped
        integrator left in the queue."""
        with self._inline_lock:
            self._integrate_pending_inline()
            with self._integrate_cond:
                self._integrate_inline += 1
            self._integrate_keyframe(job)

    def _integrate_pending_inline(self) -> None:
        """Integrate whatever waits in the queue on the calling thread (only when the integrator is
        not running: it and this must not both take jobs)."""
        with self._inline_lock:
            while not self._integrator_alive():
                try:
                    job = self._integrate_jobs.get_nowait()
                except queue.Empty:
                    return
                self._integrate_keyframe(job)

    def _integrator_loop(self, stop: threading.Event) -> None:
        """The integrator thread: fuse queued keyframes in ack order until stopped and the queue is
        empty (so the final save holds everything acked)."""
        while True:
            try:
                job = self._integrate_jobs.get(timeout=self.config.poll_interval_s)
            except queue.Empty:
                if stop.is_set():
                    return
                continue
            self._integrate_keyframe(job)

    def drain_integrations(self) -> None:
        """Return once every keyframe acked so far is integrated into the global map (``save`` does
        this first). Waits for the integrator, or does its work here when it is not running."""
        with self.state.lock:
            target = self._integrate_submitted
        self._wait_integrated(target)

    def _wait_integrated(self, target: int) -> None:
        """Until ``target`` keyframes are integrated (the rest may be in the queue, or being
        integrated inline by the ingest thread right now)."""
        while True:
            if not self._integrator_alive():
                self._integrate_pending_inline()
            with self._integrate_cond:
                if self._integrate_done >= target:
                    return
                self._integrate_cond.wait(self.config.poll_interval_s)

    def integration_stats(self) -> dict[str, Any]:
        """The keyframe integrator, for ``status`` (``integration``): ``background`` (False:
        inline, before the ack), ``queue_length`` (``global_map.integrate_queue``), ``backlog``
        (acked keyframes not yet in the global map), ``integrated``, ``errors``,
        ``backpressure_waits`` / ``backpressure_s`` (acks that waited for room in the queue),
        ``inline`` (integrated on the ingest thread) and ``lag_ms_p50`` / ``lag_ms_p95`` (ack to
        integrated, recent keyframes). Called with the state lock held."""
        submitted = self._integrate_submitted
        with self._integrate_cond:
            lags = sorted(self._integrate_lag_s)
            done = self._integrate_done

            def pct(q: float) -> float | None:
                return round(1e3 * lags[min(len(lags) - 1, int(q * len(lags)))], 3) if lags else None

            return {
                "background": self._integrator_alive(),
                "queue_length": self.config.global_map.integrate_queue,
                "backlog": max(submitted - done, 0),
                "integrated": done,
                "errors": self._integrate_errors,
                "backpressure_waits": self._integrate_waits,
                "backpressure_s": round(self._integrate_wait_s, 3),
                "inline": self._integrate_inline,
                "lag_ms_p50": pct(0.5),
                "lag_ms_p95": pct(0.95),
            }

    def _reject(self, frame: Frame, reason: str) -> Ack:
        """A rejected ack (called with the lock held)."""
        self.state.ack_counts["rejected"] += 1
        self._warn_limited("ingest:rejected", "frame seq %d rejected: %s", frame.seq, reason)
        return Ack(
            seq=frame.seq, status="rejected", map_version=self.state.map_version, reason=reason, id=frame.id
        )

    # -- queries ------------------------------------------------------------------------------

    def _handle_status(self, msg: Message) -> Status:
        state = self.state
        with state.lock:
            extra: dict[str, Any] = {
                "max_keyframes": self.config.window.max_keyframes,
                "frames_keyframe": state.ack_counts["keyframe"],
                "frames_accepted": state.ack_counts["accepted"],
                "frames_rejected_ack": state.ack_counts["rejected"],
                "keyframes_evicted": state.keyframes_evicted,
                "errors": dict(state.error_counts),
                "requests": dict(state.requests_by_type),
                "ov_dim": state.ov_dim,
                "last_save": state.last_save,
                "endpoints": {
                    "ingest": self.config.ingest_endpoint,
                    "query": self.config.query_endpoint,
                    "events": self.config.events_endpoint,
                },
                "map_dir": os.path.abspath(self.config.map_dir),
                "pid": os.getpid(),
                "rss_bytes": _rss_bytes(),
                "serving": sorted(t.TYPE for t, h in self.query_handlers.items() if not _is_not_ready(h)),
                "segment_methods": sorted(m for m, h in self.segment_methods.items() if not _is_not_ready(h)),
                "query_pool": self.query_pool_stats(),
                "answers": self.answer_stats(),
                "security": self._security_status(),
                "limits": {
                    "sndhwm": self.config.limits.sndhwm,
                    "rcvhwm": self.config.limits.rcvhwm,
                    "events_queue_max": self.config.limits.events_queue_max,
                },
                "events_dropped": self._events.dropped,
                "frames_duplicate": self.frames_duplicate,
                "frames_downscaled": self.frames_downscaled,
                "replies_dropped": dict(self.replies_dropped),
                "integration": self.integration_stats(),
                **state.global_map.stats(),
            }
            for key, provider in self.status_providers.items():
                extra[key] = provider()
            return Status(
                map_version=state.map_version,
                keyframes=len(state.window),
                frames_received=state.frames_received,
                frames_rejected=state.frames_rejected,
                ov_space=state.ov_space,
                memory_bytes=state.memory_bytes() + sum(f() for f in self.memory_providers),
                uptime_s=time.monotonic() - state.started_monotonic,
                extra=extra,
                id=getattr(msg, "id", None),
            )

    def _handle_save(self, msg: Message) -> Ok:
        assert isinstance(msg, Save)
        try:
            path, version, count = self._save_to(msg.name, reason="request")
        except StoreWriteError as exc:
            log.error("save of map %r failed: %s", msg.name, exc)
            raise ProtocolError("internal", f"save failed on the node: {exc}") from None
        except StoreError as exc:
            raise ProtocolError("bad_request", f"save failed: {exc}") from None
        return Ok(id=msg.id, message=f"saved map version {version} ({count} keyframes) to {path}")

    def _save_to(self, name: str, reason: str) -> tuple[str, int, int]:
        """Snapshot under the lock, write outside it. Returns (path, map_version, keyframes).
        Every keyframe acked before the save (at least those in the saved window) is integrated
        into the saved global map first (the integrator's backlog is drained)."""
        with self.state.lock:
            snap = self.state.snapshot()
            target = self._integrate_submitted
            global_map = self.state.global_map
        self._wait_integrated(target)
        if self.evicted_views is not None:
            self.evicted_views.process_pending()  # the views of keyframes that left, in the saved map
        # the map as of now: every keyframe of ``snap`` and perhaps a few acked since (its own lock)
        global_arrays, global_manifest = global_map.to_arrays()
        arrays, entries = keyframes_to_arrays(snap.keyframes)
        arrays.update(global_arrays)
        manifest = {
            "map_version": snap.map_version,
            "ov_space": snap.ov_space,
            "ov_dim": snap.ov_dim,
            "keyframes": entries,
            "global_map": global_manifest,
            "saved_unix_s": time.time(),
            "config": to_dict(self.config),
        }
        started = time.monotonic()
        path = self.store.save(name, arrays, manifest)
        elapsed = time.monotonic() - started
        with self.state.lock:
            self.state.last_save = {"name": name, "map_version": snap.map_version, "unix_s": time.time()}
        self._saved_version = snap.map_version
        log.info(
            "%s save: map version %d (%d keyframes) -> %s in %.2f s",
            reason,
            snap.map_version,
            len(snap.keyframes),
            path,
            elapsed,
        )
        return str(path), snap.map_version, len(snap.keyframes)

    def _handle_load(self, msg: Message) -> Ok:
        assert isinstance(msg, Load)
        return Ok(id=msg.id, message=self._load_map(msg.name))

    def _load_map(self, name: str) -> str:
        """Replace the window and the global map with the saved map ``name``; returns a note.
        Raises ``ProtocolError`` (nothing changed) when the file is missing or damaged. Maps
        saved without a global map section get one rebuilt from their keyframes."""
        try:
            arrays, manifest = self.store.load(name)
            keyframes = keyframes_from_arrays(arrays, manifest.get("keyframes"))
        except (StoreError, ValueError) as exc:
            raise ProtocolError("bad_request", f"load failed: {exc}") from None
        ov_space = manifest.get("ov_space")
        ov_dim = manifest.get("ov_dim")
        saved_version = manifest.get("map_version")
        valid_space = ov_space is None or isinstance(ov_space, str)
        if not valid_space or not (ov_dim is None or isinstance(ov_dim, int)):
            raise ProtocolError("bad_request", f"load failed: map {name!r} has a corrupt manifest (ov)")
        if self.config.ov_space is not None and ov_space is not None and ov_space != self.config.ov_space:
            raise ProtocolError(
                "ov_space_mismatch",
                f"map {name!r} holds ov_space {ov_space!r}; this node is pinned to {self.config.ov_space!r}",
            )
        # build the new global map aside, so a damaged section changes nothing
        fresh = GlobalSemanticMap(self.config.global_map, fusion=self.state.global_map.fusion)
        section = manifest.get("global_map")
        try:
            if section is not None:
                fresh.restore(arrays, section, map_version=0)
            else:
                for keyframe in keyframes:
                    fresh.integrate(keyframe)
        except ValueError as exc:
            raise ProtocolError("bad_request", f"load failed: map {name!r}: {exc}") from None
        state = self.state
        with state.lock:
            state.window.replace(keyframes)
            state.ov_space = ov_space if ov_space is not None else self.config.ov_space
            state.ov_dim = ov_dim
            # keep the saved version when it is ahead, so versions seen by clients stay comparable
            if isinstance(saved_version, int) and saved_version > state.map_version:
                state.map_version = saved_version
            else:
                state.map_version += 1
            version, count = state.map_version, len(state.window)
            fresh.retag(version)
            state.global_map = fresh  # a frame being integrated into the old map right now is dropped
            self._publish(version, count)
        # The loaded map is ready to query when the reply goes out: its snapshot and normalised
        # features (what the first query_points would compute) are made here, off the query path.
        fresh.snapshot().unit_feature_blocks()
        for listener in self.load_listeners:
            listener(fresh, version)
        points = len(state.global_map)
        log.info("loaded map %r: %d keyframes, %d global points, now map version %d", name, count, points,
                 version)
        return f"loaded map {name!r}: {count} keyframes, {points} map points, map version {version}"

    # -- semantic queries ---------------------------------------------------------------------

    def _text_encoder(self, what: str) -> Any:
        """The text encoder of the map's ov_space, or ``not_ready`` saying why there is none."""
        from mapper.ov.encoders import UnknownSpaceError, get_text_encoder

        with self.state.lock:
            space = self.state.ov_space
        if space is None:
            raise ProtocolError(
                "not_ready",
                f"{what}: the map has no open-vocabulary features yet (no keyframe carried ov); "
                "send frames with ov (e.g. minilm-l6-v2 features) first",
            )
        try:
            return get_text_encoder(space)
        except UnknownSpaceError as exc:
            raise ProtocolError("not_ready", f"{what}: {exc}") from None

    def _warm_text_encoder(self, space: str) -> None:
        """Load the text encoder of ``space`` in the background once, so the first query is fast;
        the first time, also the averaging kernel (``segment_points`` ``average`` /
        ``average_depth``: compiled, or loaded from numba's cache)."""
        if space in self._warmed_spaces:
            return
        first = not self._warmed_spaces
        self._warmed_spaces.add(space)

        def warm() -> None:
            from mapper.ov.encoders import UnknownSpaceError, get_text_encoder

            try:
                get_text_encoder(space).encode(["chair"])
            except UnknownSpaceError:
                log.info("no text encoder for ov_space %r: semantic queries will answer not_ready", space)
            except Exception:  # a broken encoder must not take the node down; queries report it
                log.exception("text encoder warm-up for %r failed", space)
            if first:
                _warm_kernels("mapper.model.ops.average_kernel")
                _warm_kernels("mapper.model.ops.occlusion_kernel")  # depth tests without depth

        threading.Thread(target=warm, name="mapper-encoder-warmup", daemon=True).start()

    def _handle_query_points(self, msg: Message) -> Message:
        """Answer from :class:`mapper.node.queries.AnswerCache` when it may (same map version, or,
        while frames are arriving, a stale answer within ``queries.answer_max_age_s``, then
        recomputed in the background), else compute on the current snapshot. Once the stream
        stops (no frame for ``limits.ingest_active_s``) every answer is of the current map."""
        assert isinstance(msg, QueryPoints)
        from mapper.node.queries import answer_key

        answers = self._query_caches()[1]
        key = answer_key(msg.texts, msg.negatives, msg.min_score, msg.max_points, msg.objects)
        gmap = self.state.global_map
        t0 = time.monotonic()
        streaming = t0 - self._ingest_last <= self.config.limits.ingest_active_s
        hit = answers.get(key, gmap.version, gmap.generation, t0, allow_stale=streaming)
        if hit is None:
            return self._compute_answer(key, msg)
        answer, _age, stale = hit
        if stale:
            self._schedule_refresh(key, msg)
        answer.timing_ms["total"] = 1e3 * (time.monotonic() - t0)
        return answer

    def _query_caches(self) -> tuple[BlockLabelCache, AnswerCache]:
        from mapper.node.queries import AnswerCache, BlockLabelCache

        with self._answers_lock:
            if self._label_cache is None or self._answer_cache is None:
                cfg = self.config.queries
                self._label_cache = BlockLabelCache(cfg.label_cache_blocks)
                self._answer_cache = AnswerCache(
                    cfg.answer_max_age_s, cfg.answer_cache_entries, int(cfg.answer_cache_mb * 2**20)
                )
            return self._label_cache, self._answer_cache

    def _compute_answer(self, key: AnswerKey, msg: QueryPoints) -> Points:
        """``query_points`` on the current snapshot; the answer is cached for ``key``."""
        from mapper.node.queries import query_points

        labels, answers = self._query_caches()
        encoder = self._text_encoder("query_points")
        taken = time.monotonic()
        snapshot = self.state.global_map.snapshot()
        answer = query_points(
            snapshot,
            encoder,
            msg.texts,
            negatives=msg.negatives,
            min_score=msg.min_score,
            max_points=msg.max_points,
            objects=msg.objects,
            config=self.config.queries,
            label_cache=labels,
        )
        answers.put(key, answer, snapshot.version, snapshot.generation, taken)
        return answer

    def _schedule_refresh(self, key: AnswerKey, msg: QueryPoints) -> None:
        """Queue one background recomputation of ``key`` (none when one is already queued or the
        queue is full: the next stale request queues it)."""
        with self._answers_lock:
            if key in self._refresh_pending:
                return
            try:
                self._refresh_jobs.put_nowait((key, msg))
            except queue.Full:
                return
            self._refresh_pending.add(key)

    def _refresh_loop(self, stop: threading.Event) -> None:
        """The answer-refresh thread: recompute stale ``query_points`` answers on the current map
        (paced like the query threads: ingest first), so the next request gets a fresh one."""
        while not stop.is_set():
            started = time.monotonic()
            if self.refresh_one(self.config.poll_interval_s):
                self._pace_queries(started)

    def refresh_one(self, timeout_s: float) -> bool:
        """Recompute one queued stale answer (waiting up to ``timeout_s`` for one); False when
        none was queued. Never raises (a failed refresh leaves the next request to compute)."""
        try:
            key, msg = self._refresh_jobs.get(timeout=timeout_s)
        except queue.Empty:
            return False
        try:
            gmap = self.state.global_map
            if not self._query_caches()[1].current(key, gmap.version, gmap.generation):
                self._compute_answer(key, msg)
                self.answer_refreshes += 1
        except ProtocolError as exc:  # e.g. the map was cleared: the next request says so
            log.debug("answer refresh: %s", exc.message)
        except Exception:
            log.exception("answer refresh failed (the next request computes its answer)")
        finally:
            with self._answers_lock:
                self._refresh_pending.discard(key)
        return True

    def _handle_segment_points(self, msg: Message) -> Message:
        assert isinstance(msg, SegmentPoints)
        handler = self.segment_methods.get(msg.method)
        if handler is None:
            raise ProtocolError(
                "bad_request",
                f"method: {msg.method!r} unknown; served: {', '.join(sorted(self.segment_methods))}",
            )
        return handler(msg)

    def _occluder_depths(self, xyz: np.ndarray, keyframes: Sequence[Keyframe]) -> dict[int, np.ndarray]:
        """``queries.point_occlusion``: for each of ``keyframes`` without input depth (by index), its
        (H, W) z-buffer of the request's points ``xyz`` (N, 3), the depth ``average_depth`` tests
        against there (all zeros for a request without points). Empty when the setting is off or no
        keyframe lacks depth."""
        need = [i for i, k in enumerate(keyframes) if k.depth_m is None]
        if not self.config.queries.point_occlusion or not need:
            return {}
        from mapper.geometry.splat import request_occluder_depths

        out = {}
        for size in {(keyframes[i].width, keyframes[i].height) for i in need}:  # one launch a size
            same = [i for i in need if (keyframes[i].width, keyframes[i].height) == size]
            z = request_occluder_depths(
                xyz, np.stack([np.asarray(keyframes[i].K, np.float64) for i in same]),
                np.stack([np.asarray(keyframes[i].world_from_cam, np.float64) for i in same]),
                size[0], size[1], self.config.model.point_occlusion_footprint, threads=0)
            out.update({i: z[j] for j, i in enumerate(same)})
        return out

    def _segment_average(self, msg: SegmentPoints, use_depth: bool) -> Segmentation:
        """``average`` / ``average_depth`` (:meth:`_segment_average_ordered`) with the points in
        Z-order of map voxels where they do not come spatially coherent (``queries.spatial_sort``,
        :func:`mapper.node.queries.spatial_order`), the answers returned in the request's order.
        (The learned model's path groups its points by view set and cell already: a shuffled
        request costs it about as much as a coherent one, docs/BENCHMARKS.md.)"""
        if not self.config.queries.spatial_sort:
            return self._segment_average_ordered(msg, use_depth)
        from mapper.node.queries import spatial_order

        started = time.perf_counter()
        xyz = np.asarray(msg.xyz, np.float32)
        order = spatial_order(xyz, self.config.global_map.voxel_size_m)
        if order is None:
            return self._segment_average_ordered(msg, use_depth)
        sorted_ms = 1e3 * (time.perf_counter() - started)
        in_order = copy.copy(msg)  # a permutation of points validated at the boundary: not checked again
        in_order.xyz = xyz[order]
        reply = self._segment_average_ordered(in_order, use_depth)
        for name in ("label", "score", "source"):  # back to the request's order
            arr = getattr(reply, name)
            if arr is not None:
                back = np.empty_like(arr)
                back[order] = arr
                setattr(reply, name, back)
        reply.timing_ms["spatial_sort"] = sorted_ms
        return reply

    def _segment_average_ordered(self, msg: SegmentPoints, use_depth: bool) -> Segmentation:
        """``average`` / ``average_depth``: OpenScene-2D averaging over the window's keyframes where
        they see a point, together with the views of keyframes that left the window at its nearest
        map voxel (``queries.evicted_views``, :meth:`_evicted_prior`), and the global map's fused
        features elsewhere (:meth:`answer_from_map`)."""
        from mapper.node.queries import SOURCE_MAP, SOURCE_WINDOW, best_text, segment_average_cosines

        started = time.perf_counter()
        method = "average_depth" if use_depth else "average"
        with self.state.lock:
            keyframes = self.state.window.keyframes
        with_ov = [k for k in keyframes if k.ov is not None]
        xyz = np.asarray(msg.xyz, np.float32)
        occluders = self._occluder_depths(xyz, with_ov) if use_depth else {}
        views = [
            (k.ov, k.K, k.world_from_cam, (k.width, k.height),
             k.depth_m if k.depth_m is not None else occluders.get(i))
            for i, k in enumerate(with_ov)
            if k.ov is not None and (not use_depth or k.depth_m is not None or i in occluders)
        ]
        gmap = self.state.global_map  # its snapshot and evicted views together (a load swaps the map)
        map_store = gmap.evicted
        map_snap = gmap.snapshot()  # one snapshot for the check and the fill
        map_has_features = map_snap.n_with_features > 0
        if not with_ov and not map_has_features:
            raise ProtocolError(
                "not_ready",
                f"segment_points method {method!r}: none of the {len(keyframes)} keyframes in the window "
                "carries ov features and the global map has none; send frames with ov",
            )
        if not views and not map_has_features:
            raise ProtocolError(
                "not_ready",
                f"segment_points method 'average_depth' needs keyframes with both depth and ov: the "
                f"window has {len(with_ov)} keyframes with ov, none with depth; send depth or use "
                "method 'average'",
            )
        encoder = self._text_encoder(f"segment_points ({method})")
        with self.state.lock:
            dim = self.state.ov_dim
        if dim is not None and dim != encoder.dim:
            raise ProtocolError(
                "not_ready",
                f"segment_points: the map's features have dimension {dim}, the text encoder of "
                f"{encoder.space!r} produces {encoder.dim}",
            )
        t_views = time.perf_counter()
        text_emb = encoder.encode(list(msg.texts))
        t_text = time.perf_counter()
        nearest = map_snap.nearest_with_feature(xyz, self.map_radius_m) if map_has_features else None
        t_near = time.perf_counter()
        prior = self._evicted_prior(map_store, map_snap, nearest, "depth" if use_depth else "all", text_emb)
        t_prior = time.perf_counter()
        if views or prior is not None:
            cos, n_views = segment_average_cosines(xyz, views, text_emb, use_depth=use_depth, prior=prior)
        else:
            cos = np.zeros((xyz.shape[0], text_emb.shape[0]), np.float32)
            n_views = np.zeros(xyz.shape[0], np.int64)
        evicted_only = (n_views == 0) & (prior[1] >= 0) if prior is not None else np.zeros(xyz.shape[0], bool)
        seen = (n_views > 0) | evicted_only
        label, score = best_text(cos, seen)
        t_avg = time.perf_counter()
        label, score, source = self.answer_from_map(xyz, text_emb, label, score, seen, map_snap,
                                                    window_cos=cos, depth_tested=use_depth, nearest=nearest)
        source[evicted_only & (source == SOURCE_WINDOW)] = SOURCE_MAP  # only keyframes that left saw it
        t_done = time.perf_counter()
        return Segmentation(
            label=label,
            score=score,
            source=source,
            timing_ms={
                "views": 1e3 * (t_views - started),
                "encode_text": 1e3 * (t_text - t_views),
                "nearest": 1e3 * (t_near - t_text),
                "evicted": 1e3 * (t_prior - t_near),
                "average": 1e3 * (t_avg - t_prior),
                "map": 1e3 * (t_done - t_avg),
                "total": 1e3 * (t_done - started),
                "n_views": float(len(views)),
                "from_evicted": float(np.count_nonzero(prior[2] > 0)) if prior is not None else 0.0,
                "from_map": float(np.count_nonzero(source == 2)),
            },
        )

    def answer_from_map(
        self,
        xyz: np.ndarray,  # (N, 3) float32 world metres
        text_emb: np.ndarray,  # (T, D) float32 unit rows
        label: np.ndarray,  # (N,) int32 the window's labels
        score: np.ndarray,  # (N,) float32 the window's scores
        window_seen: np.ndarray,  # (N,) bool: the window answered the point
        snap: GlobalMapSnapshot | None = None,  # the snapshot to use (default: the current one)
        window_cos: np.ndarray | None = None,  # (N, T) the window's cosines (for queries.map_blend)
        depth_tested: bool = False,  # the window's answer already passed a depth test
        nearest: np.ndarray | None = None,  # (N,) int64 the snapshot's nearest rows, if looked up already
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fill the points the window did not answer from the global map's snapshot (nearest point
        with a feature within ``queries.map_radius_voxels`` voxels) and, with ``window_cos``, blend
        the two where both answer (``queries.map_blend``): (label, score, source (N,) uint8), see
        :func:`mapper.node.queries.fill_from_map`. Used by every segment method."""
        from mapper.node.queries import fill_from_map

        if snap is None:
            snap = self.state.global_map.snapshot()
        return fill_from_map(snap, xyz, text_emb, label, score, window_seen, self.map_radius_m,
                             more_confident=self.config.queries.map_when_more_confident,
                             window_cos=window_cos, blend=self.map_blend(depth_tested=depth_tested),
                             nearest=nearest)

    def _evicted_prior(
        self,
        store: EvictedViewStore,
        snap: GlobalMapSnapshot,
        nearest: np.ndarray | None,  # (N,) int64 nearest map rows with a feature (-1: none)
        channel: str,
        text_emb: np.ndarray,  # (T, D)
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The views of keyframes that left the window at each point's nearest map voxel, as the
        averaging's ``prior`` (means (P, D) float32, row (N,) int64 (-1: none), views (N,) float32),
        or None when there are none (``queries.evicted_views`` off, nothing evicted yet, no map
        voxel near, another feature dimension)."""
        if self.evicted_views is None or nearest is None or snap.keys is None or len(store) == 0:
            return None
        if channel == "all" and not self.evicted_views.both:
            return None
        if store.dim != text_emb.shape[1]:
            return None
        keys = np.full(nearest.shape[0], -1, np.int64)
        hit = nearest >= 0
        keys[hit] = snap.keys[nearest[hit]]
        table, row, weight = store.prior(keys, channel)
        row[~hit] = -1
        weight[~hit] = 0.0
        if not (row >= 0).any():
            return None
        return table, row, weight

    def map_blend(self, *, depth_tested: bool = False) -> float:
        """The weight of the global map's cosines where the window answers a ``segment_points`` point
        too (see :func:`mapper.node.queries.blend_with_map`): 0 for answers that already passed a
        depth test (``average_depth``, ``govnesf`` with ``use_depth``: the more-confident rule),
        else ``queries.map_blend`` while at least half of the window's keyframes carry input
        depth, else ``queries.map_blend_without_depth``."""
        if depth_tested:
            return 0.0
        q = self.config.queries
        return q.map_blend if self.window_has_depth() else q.map_blend_without_depth

    def window_has_depth(self) -> bool:
        """Whether at least half of the window's keyframes carry input depth (an empty window has
        none): the global map's surfaces are then measured ones, not an RGB-only robot's estimates."""
        with self.state.lock:
            keyframes = self.state.window.keyframes
        with_depth = sum(k.depth_m is not None for k in keyframes)
        return bool(keyframes) and 2 * with_depth >= len(keyframes)

    @property
    def map_radius_m(self) -> float:
        """Radius (metres) of the whole-map lookup: ``queries.map_radius_voxels`` map voxels."""
        return self.config.queries.map_radius_voxels * self.config.global_map.voxel_size_m

    def text_encoder(self, what: str) -> Any:
        """The text encoder of the map's ov_space (``not_ready`` naming ``what`` without one)."""
        return self._text_encoder(what)

    @staticmethod
    def _not_ready(type_name: str, what: str) -> QueryHandler:
        def handler(msg: Message) -> Message:
            raise ProtocolError(
                "not_ready",
                f"{type_name} ({what}) is not served by this node yet: the model stage is not "
                "installed; status, save and load are served",
            )

        handler.not_ready = True  # type: ignore[attr-defined]
        return handler

    # -- housekeeping -------------------------------------------------------------------------

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

    def _maybe_autosave(self) -> None:
        cfg = self.config
        if not cfg.autosave_name or cfg.autosave_interval_s <= 0:
            return
        if time.monotonic() - self._last_autosave < cfg.autosave_interval_s:
            return
        self._last_autosave = time.monotonic()
        with self.state.lock:
            version = self.state.map_version
        if version == self._saved_version:
            return
        try:
            self._save_to(cfg.autosave_name, reason="periodic")
        except StoreError as exc:
            log.error("periodic save failed: %s", exc)

    def _summary_line(self) -> str:
        s = self.state
        return (
            f"map_version {s.map_version}, keyframes {len(s.window)}, frames received "
            f"{s.frames_received} (rejected {s.frames_rejected}), memory {s.memory_bytes() / 1e6:.1f} MB"
        )


def _is_not_ready(handler: Callable[..., Any]) -> bool:
    return bool(getattr(handler, "not_ready", False))


def _govnesf_not_loaded(msg: SegmentPoints) -> Segmentation:
    raise ProtocolError(
        "not_ready",
        "segment_points method 'govnesf' (learned blending): the learned model is not loaded on this "
        "node yet; use method 'average' or 'average_depth'",
    )


_govnesf_not_loaded.not_ready = True  # type: ignore[attr-defined]
