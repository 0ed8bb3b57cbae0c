"""What every request of the node shares, below the transport: :class:`NodeContext`.

The transport (:class:`mapper.node.service.MapperNode`: sockets, threads, dispatch, security) owns
one context; the answers (:mod:`mapper.node.answers`), the ingest path (:mod:`mapper.node.ingest`),
the backends and the background workers all work through it. It holds the map state behind its
lock, the map store, the keyframe integrator, the extension registries (listeners, providers,
workers), the ``map_updated`` events queue, the pacing of queries against ingest, the text encoders
and the rate-limited logging of rejections and errors.
"""

from __future__ import annotations

import importlib
import logging
import math
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from mapper.map.global_map import GlobalSemanticMap
from mapper.map.window import Keyframe
from mapper.node.config import NodeConfig
from mapper.node.integration import Integrator
from mapper.node.keyframe_queue import KeyframeQueue
from mapper.node.state import MapState
from mapper.node.store import MapStore
from mapper.node.workers.evicted_views import EvictedViews
from protocol.errors import ProtocolError
from protocol.messages import Error, MapUpdated, Message, error_reply, peek_id

__all__ = ["NodeContext", "QueryHandler", "is_not_ready", "warm_kernels"]

log = logging.getLogger("mapper.node.service")

QueryHandler = Callable[[Message], Message]
"""Takes a decoded request, returns the reply (its ``id`` is filled in by the node); raises
``ProtocolError`` for an error reply."""

WARN_INTERVAL_S = 5.0
"""Rejections and errors are logged as warnings at most this often per kind (DEBUG otherwise)."""


def warm_kernels(module: str) -> None:
    """Compile (or load from numba's cache) the compiled kernels of ``module`` (its ``warm_up``), so
    the first query that needs them does not pay for it; a failure is logged (that query compiles
    them instead and reports it)."""
    try:
        importlib.import_module(module).warm_up()
    except Exception:
        log.exception("warm-up of the kernels of %s failed", module)


def warm_all_kernels(modules: list[str]) -> None:
    """:func:`warm_kernels` of each module, in order (one background thread)."""
    for module in modules:
        warm_kernels(module)


def is_not_ready(handler: Callable[..., Any]) -> bool:
    """Whether ``handler`` only answers ``not_ready``: a method of an object whose ``not_ready`` is
    true (e.g. :class:`mapper.node.answers.render.RenderAnswers` without a backend), or a wrapper
    (``__wrapped__``) of such a handler (``status`` leaves it out of ``serving``)."""
    while handler is not None:
        if getattr(getattr(handler, "__self__", None), "not_ready", False):
            return True
        handler = getattr(handler, "__wrapped__", None)  # type: ignore[assignment]
    return False


class NodeContext:
    """The node's shared state and services (module docstring). Made by the transport; thread-safe
    where noted (the map state behind ``state.lock``, the integrator and the events queue have
    their own locks)."""

    def __init__(self, config: NodeConfig) -> None:
        self.config = config
        self.state = MapState(config)
        self.store = MapStore(config.map_dir)
        self.stop = threading.Event()
        """Set when the node shuts down: every thread and every pause ends on it."""
        self.events: KeyframeQueue[MapUpdated] = KeyframeQueue(config.limits.events_queue_max)
        """``map_updated`` notices for the events thread (bounded: the oldest is dropped, counted)."""
        self.ingest_last = -math.inf
        """When the ingest endpoint last handled a message (monotonic s; :meth:`pace`)."""
        self.frames_duplicate = 0
        """Frames received again (same seq, stamp, camera, pose and K) while already a keyframe in the
        window: acked ``accepted`` with a ``duplicate`` reason, not added twice (state lock)."""
        self.frames_downscaled = 0
        """Keyframes kept shrunk to ``window.max_image_side`` (ingest thread)."""
        self.replies_dropped: Counter[str] = Counter()
        """Replies not sent, by ``"<endpoint>:<why>"``: ``full`` (the peer's queue is at ``sndhwm``:
        it does not read its replies) or ``gone`` (the peer disconnected)."""
        self.saved_version: int | None = None
        """The map version last saved (the periodic autosave skips an unchanged map)."""
        self._last_warning: dict[str, float] = {}
        self._warmed_spaces: set[str] = set()
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
        keyframe: workers that put points of that keyframe into the global map before its features
        existed (triangulation, plane-sweep stereo) fuse the features into them now. Must not
        raise."""
        self.surface_points: list[Callable[[], np.ndarray]] = []
        """Providers of measured surface points (world, (N, 3)) other than input depth, e.g. the
        triangulated points and the kept plane-sweep depths of RGB-only keyframes: ``render``
        (``model.surface_from_map = "auto"``) renders at their surfaces when the window's
        keyframes mostly lack input depth. Called on the query thread; must not raise."""
        self.load_listeners: list[Callable[[GlobalSemanticMap, int, tuple[Keyframe, ...]], None]] = []
        """Called on the thread that loaded a map (``load`` or the autosave at start), outside the
        state lock, right after the loaded map replaced the window and the global map, with the new
        global map, its map version and the loaded window's keyframes (oldest first): whatever
        belongs to the replaced map can go now (keyframes acked before the load carry a map version
        up to the replaced map's, below this one), and what a worker derives from the window can be
        made again from the loaded keyframes (queue the work). Must be quick and must not raise."""
        self.workers: list[tuple[str, Callable[[threading.Event], None]]] = []
        """Background threads ``(name, target)`` started by the transport after the sockets are
        bound; ``target(stop_event)`` runs until the event is set and must not raise."""
        self.kernel_modules: list[str] = ["mapper.map.query_kernels"]
        """Modules whose compiled kernels the transport warms in the background at start (each
        module's ``warm_up``: compiled, or loaded from numba's cache), so that no first query pays
        for it; backends add theirs (the learned model: its point kernels)."""
        self.pending_sources: dict[str, tuple[Callable[[], int], bool]] = {}
        """Background work by name: ``(pending, geometry)``; ``pending()`` counts the keyframes queued
        or being worked on (must be quick, no state lock); ``geometry`` marks the work an RGB-only
        window's learned answers wait for (:meth:`geometry_pending`). Workers register here."""
        self.integration = Integrator(config, self.state, self.keyframe_listeners, self.warm_text_encoder)
        """The keyframe integrator (:mod:`mapper.node.integration`)."""
        self.evicted_views: EvictedViews | None = None
        """The worker that keeps evicted keyframes' views for the averaging methods
        (``queries.evicted_views``; :mod:`mapper.map.evicted_views`)."""
        if config.global_map.carve:
            self.kernel_modules.append("mapper.map.carving")  # the see-through test of integrates
        if config.queries.evicted_views != "off":
            self.evicted_views = EvictedViews(self)
            self.evicted_views.install()
            self.kernel_modules.append("mapper.map.evicted_views")  # its running-mean kernel

    # -- the integrator -----------------------------------------------------------------------

    def drain_integrations(self) -> None:
        """Return once every keyframe acked so far is integrated into the global map."""
        self.integration.drain()

    def register_pending(self, name: str, pending: Callable[[], int], *, geometry: bool = False) -> None:
        """Count ``pending()`` (keyframes a worker has queued or is working on) as background work
        in ``status`` (``pending``, ``settled``) and in the settled wait."""
        self.pending_sources[name] = (pending, geometry)

    def pending_work(self) -> dict[str, int]:
        """Background work on acked keyframes, by source: ``integration`` (acked, not yet in the
        global map) and each registered worker's queued or running keyframes."""
        out = {"integration": self.integration.backlog()}
        for name, (pending, _geometry) in self.pending_sources.items():
            out[name] = int(pending())
        return out

    def settled(self) -> bool:
        """Whether no background work is pending for what was acked (every source at 0)."""
        return not any(self.pending_work().values())

    def geometry_pending(self) -> int:
        """Keyframes whose geometry is still being made: not yet integrated, or queued for the
        workers registered with ``geometry=True`` (triangulation and stereo, rendered depth)."""
        return self.integration.backlog() + sum(
            int(pending()) for pending, geometry in self.pending_sources.values() if geometry
        )

    def wait_settled(self, timeout_s: float | None) -> bool:
        """Wait up to ``timeout_s`` (capped at ``queries.max_settle_wait_s``) for :meth:`settled`;
        returns whether the node settled. None or 0: no wait."""
        if not timeout_s:
            return self.settled()
        deadline = time.monotonic() + min(float(timeout_s), self.config.queries.max_settle_wait_s)
        while not self.settled():
            left = deadline - time.monotonic()
            if left <= 0 or self.stop.wait(min(0.05, left)):
                return self.settled()
        return True

    # -- events -------------------------------------------------------------------------------

    def publish(self, map_version: int, keyframes: int,
                region: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Queue a ``map_updated`` notice (O(1), never blocks; the oldest beyond
        ``limits.events_queue_max`` is dropped and counted); ``region`` (min (3,), max (3,)) the box
        the change can touch (None: the whole map may have)."""
        if self.config.events_endpoint:
            lo, hi = (None, None) if region is None else (np.asarray(region[0], np.float64),
                                                            np.asarray(region[1], np.float64))
            self.events.put(MapUpdated(map_version=map_version, keyframes=keyframes, region_min=lo,
                                       region_max=hi))

    # -- pacing -------------------------------------------------------------------------------

    def streaming(self, now: float | None = None) -> bool:
        """Whether frames are arriving: one was handled within the last ``limits.ingest_active_s``."""
        now = time.monotonic() if now is None else now
        return now - self.ingest_last <= self.config.limits.ingest_active_s

    def pace(self, started: float, now: float | None = None) -> None:
        """Ingest first. While frames are arriving (:meth:`streaming`), a query-serving thread (the
        query socket's, a heavy worker, the answer refresh) that has just spent ``elapsed`` seconds
        on a request pauses ``elapsed * (1 - share) / share`` (``share`` = ``limits.query_share``;
        at most ``limits.query_pause_max_s``), so each uses at most that share of the CPU and a
        query storm cannot starve the ingest thread. Requests wait in ZeroMQ meanwhile (bounded by
        ``rcvhwm``)."""
        limits = self.config.limits
        if limits.query_share >= 1.0:
            return
        now = time.monotonic() if now is None else now
        if not self.streaming(now):
            return
        share = limits.query_share
        pause = min((now - started) * (1.0 - share) / share, limits.query_pause_max_s)
        if pause > 0:
            self.stop.wait(pause)

    # -- logging and error replies ------------------------------------------------------------

    def warn_limited(self, key: str, fmt: str, *args: object) -> None:
        """Log a warning at most once per ``WARN_INTERVAL_S`` per key (DEBUG otherwise), so a
        misbehaving client cannot flood the log."""
        now = time.monotonic()
        if now - self._last_warning.get(key, -math.inf) >= WARN_INTERVAL_S:
            self._last_warning[key] = now
            log.warning(fmt, *args)
        else:
            log.debug(fmt, *args)

    def error(self, exc: ProtocolError, data: bytes, where: str) -> Error:
        """The wire error for ``exc`` (counted by code, logged at most every few seconds)."""
        with self.state.lock:
            self.state.error_counts[exc.code] += 1
            count = self.state.error_counts[exc.code]
        self.warn_limited(
            f"{where}:{exc.code}", "%s: %s error (%d so far): %s", where, exc.code, count, exc.message
        )
        return error_reply(exc, peek_id(data))

    def internal(self, exc: Exception, data: bytes, where: str) -> Error:
        """An ``internal`` error reply for a bug (logged with its traceback; the node keeps serving)."""
        log.error("%s: internal error while handling a message:\n%s", where, traceback.format_exc())
        with self.state.lock:
            self.state.error_counts["internal"] += 1
        message = f"internal error ({type(exc).__name__}) while handling the request; see the node log"
        return error_reply(ProtocolError("internal", message), peek_id(data))

    # -- text encoders ------------------------------------------------------------------------

    def text_encoder(self, what: str) -> Any:
        """The text encoder of the map's ov_space, or ``not_ready`` naming ``what`` and saying why
        there is none."""
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

    def warm_text_encoder(self, space: str) -> None:
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
                warm_kernels("mapper.kernels.average_kernel")
                warm_kernels("mapper.model.ops.occlusion_kernel")  # depth tests without depth

        threading.Thread(target=warm, name="mapper-encoder-warmup", daemon=True).start()

    # -- the global map's part in answers -----------------------------------------------------

    @property
    def map_radius_m(self) -> float:
        """Radius (metres) of the whole-map lookup: ``queries.map_radius_voxels`` map voxels."""
        return self.config.queries.map_radius_voxels * self.config.global_map.voxel_size_m

    def window_has_depth(self) -> bool:
        """Whether at least half of the window's keyframes carry input depth (an empty window has
        none): the global map's surfaces are then measured ones, not an RGB-only robot's estimates."""
        with self.state.lock:
            keyframes = self.state.window.keyframes
        with_depth = sum(k.depth_m is not None for k in keyframes)
        return bool(keyframes) and 2 * with_depth >= len(keyframes)

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

    def memory_bytes(self) -> int:
        """Map memory: the state's arrays plus the registered providers' (call with the state lock held)."""
        return self.state.memory_bytes() + sum(f() for f in self.memory_providers)
