"""In-process open-vocabulary features for keyframes that arrive without ``ov``.

A robot that cannot run a 2D open-vocabulary model sends frames without ``ov``. They still count
for geometry (window, global-map points, colour and depth renders); semantic requests need OV
features. With ``[ov_backend] kind = "clip"`` the node computes them itself from local CLIP ViT
weights (:class:`mapper.ov.clip.ClipDenseBackend`, MaskCLIP dense features) and embeds text
queries in the same space, ``openclip:<model_name>``.

Wiring (:func:`install_ov_backend`, called once after the node is built and after
:func:`mapper.node.backends.learned.install_learned_backend`):

* the backend is loaded from ``weights_path`` / ``bpe_path`` (never downloaded). When it loads,
  its text encoder is registered for its space (:func:`mapper.ov.encoders.register_text_encoder`), so
  ``query_points``, ``segment_points`` and ``render`` texts work in that space. When it does not
  (missing file, bad checkpoint), the node serves everything else; ``status`` shows the error under
  ``ov_backend.error`` and semantic requests answer ``not_ready`` with the reason and the path;
* :meth:`OvFeatureWorker.on_keyframe` (a node keyframe listener, integrator thread) only queues a new
  keyframe that has no ``ov`` (O(1)); a keyframe whose frame carried ``ov`` is never re-encoded;
* the worker thread (``mapper-ov-backend``) computes the dense features, outside every lock (about
  2 s per frame for ViT-B/16 on a CPU), then:

  a. under the node's state lock, if the keyframe is still in the window: replaces it there by a
     copy carrying the features (``KeyframeWindow.swap``, so the window's ``on_evict`` /
     ``on_add`` callbacks record "old keyframe out, new keyframe in"; the learned runtime applies
     that incrementally on its next sync, and the averaging baselines and saved maps see the
     features too). The map's ``ov_space`` / ``ov_dim`` are set by the first keyframe with
     features, as for frames with ``ov``; ``map_version`` goes up by one;
  b. outside the state lock, fuses the features into the global map's voxels that the keyframe's
     depth points fell in (:meth:`mapper.map.global_map.GlobalSemanticMap.integrate_features`): no
     geometry weight is added a second time.

Space rules stay those of the node: the backend only fills frames without ``ov``. If the map's
space is another one (a frame with, e.g., ``minilm-l6-v2`` features came first, or a loaded map
holds it), queued keyframes are skipped (``skipped_space`` in status) rather than mixing spaces.
A pinned ``ov_space`` other than the backend's is a config error at start-up.

Bounds and failures: beyond ``max_pending`` queued keyframes the oldest is dropped (``dropped``);
keyframes queued before a map load are dropped (``stale``); a keyframe that left the window and has
no depth is skipped (nothing would use its features). A failed encode or integrate is logged (rate
limited) and counted in ``failed``; the worker never dies. Keyframes without input depth get their
features into the window; the global-map points that :mod:`mapper.node.workers.depth_points` adds for them
from rendered depth carry those features when the rendered-depth worker runs after the swap (it
looks up the window's current copy of the keyframe it queued), and the node's ``feature_listeners``
are told of the featured keyframe (the triangulation plugin then fuses the features into the
triangulated and plane-sweep points it added for that keyframe before the features existed).

Example (in-process; ``node`` a :class:`mapper.node.service.MapperNode` whose config has
``ov_backend.kind = "clip"``)::

    worker = install_ov_backend(node)   # loads the weights, registers listener + worker + status
    ...                                 # frames without ov arrive
    worker.process_pending()            # or let the worker thread do it; returns keyframes done
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from mapper.node.config import ConfigError, OvBackendConfig
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker
from protocol.errors import ProtocolError
from protocol.messages import Message, QueryPoints, Render, SegmentPoints

if TYPE_CHECKING:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.map.robot_windows import RobotWindows
    from mapper.map.window import Keyframe, KeyframeWindow
    from mapper.node.context import NodeContext, QueryHandler
    from mapper.node.service import MapperNode

__all__ = ["DenseOvBackend", "OvFeatureWorker", "install_ov_backend", "load_backend"]

log = logging.getLogger("mapper.node.workers.ov_features")

_ERROR_LOG_INTERVAL_S = 10.0
"""Failures and skips are logged as warnings at most this often per kind."""


class DenseOvBackend(Protocol):
    """What the worker needs from a dense OV backend (:class:`ClipDenseBackend` satisfies it; it is
    also a :class:`mapper.ov.encoders.TextEncoder`)."""

    space: str
    dim: int

    def dense_features(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (h, w, dim) features covering the whole image."""
        ...

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N,) strings -> (N, dim) float32 unit rows."""
        ...


def load_backend(config: OvBackendConfig) -> tuple[DenseOvBackend | None, str | None]:
    """Build the configured backend: ``(backend, None)``, or ``(None, reason)`` when it cannot be
    loaded (the reason names the weights and BPE paths). ``kind = ""`` gives ``(None, None)``."""
    if not config.kind:
        return None, None
    if config.kind != "clip":
        raise ConfigError(f"ov_backend.kind {config.kind!r} is not supported")
    from mapper.ov.clip import ClipDenseBackend

    try:
        return ClipDenseBackend(config.clip_config()), None
    except Exception as exc:  # missing file, bad checkpoint, no CUDA, ...: serve the rest, say why
        return None, (
            f"ov_backend 'clip' could not be loaded from weights_path {config.weights_path!r} "
            f"(bpe_path {config.bpe_path!r}): {type(exc).__name__}: {exc}"
        )


def _is_semantic(msg: Message) -> bool:
    """Does this request need OV features (and so possibly the backend)?"""
    if isinstance(msg, QueryPoints | SegmentPoints):
        return True
    return isinstance(msg, Render) and bool(msg.texts)


def _check_pinned(ctx: NodeContext | MapperNode, space: str) -> None:
    pinned = ctx.config.ov_space
    if pinned is not None and pinned != space:
        raise ConfigError(
            f"ov_space = {pinned!r} is pinned, but the in-process OV backend produces {space!r}"
        )


def _swap_keyframe(window: KeyframeWindow | RobotWindows, old: Keyframe, new: Keyframe) -> bool:
    """Replace ``old`` by ``new`` in ``window`` (state lock held); False if ``old`` left it.

    ``KeyframeWindow.swap``: same position, ``on_evict(old)`` then ``on_add(new)`` fire (the learned
    runtime swaps that one view), every other keyframe and each camera's latest keyframe stay."""
    return window.swap(old, new)


class OvFeatureWorker:
    """Computes OV features for keyframes without ``ov`` in the background (see the module docstring).

    Args:
        node: the mapper node (``state.global_map`` is read at processing time, so a load is followed).
        backend: the loaded backend, or None when it could not be loaded (``load_error`` says why;
            nothing is queued then).
        config: defaults to ``node.config.ov_backend``.
        load_error: why ``backend`` is None.
    """

    def __init__(
        self,
        ctx: NodeContext,
        backend: DenseOvBackend | None,
        config: OvBackendConfig | None = None,
        load_error: str | None = None,
    ) -> None:
        self.ctx = ctx
        self.backend = backend
        self.config = config or ctx.config.ov_backend
        self.space = backend.space if backend is not None else self.config.space
        self.load_error = load_error
        self._lock = threading.Lock()
        self._queue: KeyframeQueue[tuple[Keyframe, GlobalSemanticMap]] = KeyframeQueue(
            self.config.max_pending
        )
        self._busy = False
        self._in_flight = 0
        self.with_ov = 0
        """Keyframes that arrived with ov (never re-encoded)."""
        self.encoded = 0
        """Keyframes whose features were computed and attached (window and/or global map)."""
        self.window_updates = 0
        """Of those, keyframes still in the window, replaced there by a copy with features."""
        self.map_points = 0
        """Global-map observations that received features."""
        self.stale = 0
        self.skipped_space = 0
        self.skipped_evicted = 0
        self.failed = 0
        self.seconds_total = 0.0
        self._log = LimitedLog(log, _ERROR_LOG_INTERVAL_S)

    # -- wiring -------------------------------------------------------------------------------

    def install(self) -> None:
        """Register with the node: the text encoder of the backend's space (when loaded), the
        keyframe listener, the worker thread (started by ``node.start()``) and ``status["ov_backend"]``
        (:meth:`add_notes` adds the ``not_ready`` notes of semantic requests)."""
        _check_pinned(self.ctx, self.space)
        if self.backend is not None:
            from mapper.ov.encoders import register_text_encoder

            backend = self.backend
            register_text_encoder(self.space, lambda: backend)
        self.ctx.keyframe_listeners.append(self.on_keyframe)
        self.ctx.workers.append(("ov-backend", self.run))
        self.ctx.register_pending("ov_backend", lambda: self.pending)
        self.ctx.status_providers["ov_backend"] = self.stats

    def add_notes(self, node: MapperNode) -> None:
        """Append the backend's state to the ``not_ready`` answers of ``node``'s semantic requests
        (it wraps the query handlers present now: call after the learned backend is installed)."""
        for message_type in (QueryPoints, SegmentPoints, Render):
            handler = node.query_handlers.get(message_type)
            if handler is not None:
                node.register_query_handler(message_type, self._with_note(handler))

    def _with_note(self, handler: QueryHandler) -> QueryHandler:
        """``handler``, with the backend's state appended to the ``not_ready`` answers of semantic
        requests (e.g. the missing weights file)."""

        def wrapped(msg: Message) -> Message:
            try:
                return handler(msg)
            except ProtocolError as exc:
                note = self.note() if exc.code == "not_ready" and _is_semantic(msg) else None
                if note is None:
                    raise
                raise ProtocolError("not_ready", f"{exc.message}; {note}") from None

        wrapped.__wrapped__ = handler  # type: ignore[attr-defined]  # status follows it (is_not_ready)
        return wrapped

    def note(self) -> str | None:
        """Why the backend cannot help a semantic request right now, or None (no lock held)."""
        if self.load_error is not None:
            return f"the in-process OV backend ({self.space}) is not available: {self.load_error}"
        waiting = self.pending
        if waiting:
            return (
                f"the in-process OV backend ({self.space}) is computing features for {waiting} "
                "keyframe(s); retry shortly"
            )
        with self.ctx.state.lock:
            space = self.ctx.state.ov_space
        if space is not None and space != self.space:
            return (
                f"the in-process OV backend produces {self.space!r} features, but the map's ov_space "
                f"is {space!r}, so it does not fill frames without ov"
            )
        return None

    def on_keyframe(self, keyframe: Keyframe, map_version: int) -> None:
        """Queue ``keyframe`` if it has no ``ov`` (keyframe-listener thread; O(1), never raises)."""
        if keyframe.ov is not None:
            with self._lock:
                self.with_ov += 1
            return
        if self.backend is None:
            return
        self._queue.put((keyframe, self.ctx.state.global_map))

    # -- work -----------------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Keyframes queued or being encoded."""
        with self._lock:
            return len(self._queue) + self._in_flight

    @property
    def queued(self) -> int:
        """Keyframes without ov queued for features."""
        return self._queue.queued

    @property
    def dropped(self) -> int:
        """Keyframes dropped because the queue was full."""
        return self._queue.dropped

    def process_pending(self, stop: threading.Event | None = None) -> int:
        """Encode and attach every keyframe queued now, oldest first (until ``stop`` is set).
        Returns the number of keyframes whose features were attached. Safe to call from any
        thread; a call while another is running returns 0."""
        if self.backend is None:
            return 0
        with self._lock:
            if self._busy:
                return 0
            self._busy = True
        done = 0
        try:
            while stop is None or not stop.is_set():
                with self._lock:
                    item = self._queue.pop()
                    if item is None:
                        break
                    keyframe, target = item
                    self._in_flight = 1
                try:
                    done += self._process_one(keyframe, target)
                finally:
                    with self._lock:
                        self._in_flight = 0
            return done
        finally:
            with self._lock:
                self._busy = False

    def _space_conflict(self) -> str | None:
        """Why features of the backend cannot join the current map (state lock held), or None."""
        assert self.backend is not None
        state = self.ctx.state
        if state.ov_space is not None and state.ov_space != self.space:
            return f"the map's ov_space is {state.ov_space!r}, the backend produces {self.space!r}"
        if state.ov_dim is not None and state.ov_dim != self.backend.dim:
            return f"the map's features are {state.ov_dim}-d, the backend's {self.backend.dim}-d"
        return None

    def _process_one(self, keyframe: Keyframe, target: GlobalSemanticMap) -> int:
        assert self.backend is not None
        state = self.ctx.state
        with state.lock:
            if state.global_map is not target:
                self.stale += 1  # a map load replaced the map this keyframe belonged to
                return 0
            conflict = self._space_conflict()
            in_window = any(k is keyframe for k in state.window.keyframes)
        if conflict is not None:
            self.skipped_space += 1
            self._log.warning("space", "ov backend: keyframe seq %d not encoded: %s", keyframe.seq, conflict)
            return 0
        if not in_window and keyframe.depth_m is None:
            self.skipped_evicted += 1  # left the window, no depth: nothing would use its features
            return 0
        started = time.perf_counter()
        try:
            feats = np.asarray(self.backend.dense_features(np.array(keyframe.rgb)))  # writable copy for torch
            if feats.ndim != 3 or feats.shape[2] != self.backend.dim or not np.isfinite(feats).all():
                raise ValueError(
                    f"the backend returned features of shape {feats.shape} (expected (h, w, "
                    f"{self.backend.dim}), finite)"
                )
        except Exception as exc:  # a bad image or a backend failure must not stop the worker
            return self._failed(keyframe, "encode", exc)
        featured = dataclasses.replace(keyframe, ov=feats, ov_space=self.space)
        swapped = False
        with state.lock:
            if state.global_map is not target:
                self.stale += 1
                return 0
            conflict = self._space_conflict()
            if conflict is None:
                swapped = _swap_keyframe(state.window, keyframe, featured)
                if swapped or keyframe.depth_m is not None:
                    state.ov_space = self.space
                    state.ov_dim = self.backend.dim
                    state.map_version += 1
                    # "map_updated" like any map change (the node's own notice queue)
                    self.ctx.publish(state.map_version, len(state.window))
            version = state.map_version
        if conflict is not None:  # a frame of another space claimed the map while we encoded
            self.skipped_space += 1
            self._log.warning("space", "ov backend: keyframe seq %d not attached: %s", keyframe.seq, conflict)
            return 0
        if not swapped and keyframe.depth_m is None:
            self.skipped_evicted += 1  # left the window while it was encoded
            return 0
        if swapped and keyframe.depth_m is None:
            for listener in self.ctx.feature_listeners:  # points other plugins added without features
                try:
                    listener(featured)
                except Exception as exc:
                    self._failed(keyframe, "feature listener", exc)
        points = 0
        if keyframe.depth_m is not None:
            try:
                points = target.integrate_features(featured, map_version=version).points
            except Exception as exc:
                return self._failed(keyframe, "global map", exc)
        seconds = time.perf_counter() - started
        with self._lock:
            self.encoded += 1
            self.window_updates += int(swapped)
            self.map_points += points
            self.seconds_total += seconds
        log.debug("ov backend: keyframe seq %d: %s features, %s, %d map points in %.0f ms", keyframe.seq,
                  feats.shape, "in the window" if swapped else "left the window", points, 1e3 * seconds)
        return 1

    def _failed(self, keyframe: Keyframe, what: str, exc: Exception) -> int:
        with self._lock:
            self.failed += 1
        self._log.warning("failed", "ov backend: %s failed for keyframe seq %d: %s: %s", what, keyframe.seq,
                          type(exc).__name__, exc)
        return 0

    def run(self, stop: threading.Event) -> None:
        """Worker loop: process the queued keyframes whenever new ones arrive, until ``stop``."""
        run_worker(stop, self._queue.wake, lambda: self.process_pending(stop), self._unexpected)

    def _unexpected(self, exc: BaseException) -> None:
        with self._lock:
            self.failed += 1
        log.error("ov backend worker: unexpected error (continuing)", exc_info=exc)

    def stats(self) -> dict[str, Any]:
        """Counters for the node's status reply (called under the node's state lock)."""
        with self._lock:
            return {
                "kind": self.config.kind,
                "space": self.space,
                "loaded": self.backend is not None,
                "error": self.load_error,
                "weights_path": self.config.weights_path,
                "dim": self.backend.dim if self.backend is not None else None,
                "device": str(getattr(self.backend, "device", self.config.device)),
                "pending": len(self._queue) + self._in_flight,
                "queued": self.queued,
                "with_ov": self.with_ov,
                "encoded": self.encoded,
                "window_updates": self.window_updates,
                "map_points": self.map_points,
                "dropped": self.dropped,
                "stale": self.stale,
                "skipped_space": self.skipped_space,
                "skipped_evicted": self.skipped_evicted,
                "failed": self.failed,
                "mean_ms": round(1e3 * self.seconds_total / max(self.encoded, 1), 1),
            }


def install_ov_backend(node: MapperNode, config: OvBackendConfig | None = None) -> OvFeatureWorker | None:
    """Load the backend ``node.config.ov_backend`` describes and install its worker on ``node``.

    Returns the worker, or None when ``kind`` is "" (no backend). A backend that cannot be loaded
    is logged as an error and still installed (status and ``not_ready`` answers say why). Raises
    :class:`ConfigError` when the node's ``ov_space`` is pinned to another space. Call once, after
    :func:`mapper.node.backends.learned.install_learned_backend` and before ``node.start()``."""
    config = config or node.config.ov_backend
    if not config.kind:
        return None
    _check_pinned(node, config.space)  # before loading any weights
    backend, error = load_backend(config)
    if error is not None:
        log.error("%s; semantic requests will answer not_ready (everything else is served)", error)
    else:
        assert backend is not None
        log.info("ov backend: %s (%d-d) loaded from %s on %s", backend.space, backend.dim,
                 config.weights_path, getattr(backend, "device", "?"))
    worker = OvFeatureWorker(node.ctx, backend, config, load_error=error)
    worker.install()
    worker.add_notes(node)
    return worker
