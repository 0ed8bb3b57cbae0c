"""Learned features into the global map, just before a keyframe leaves the window.

The global map fuses every keyframe's 2D OV features by a weighted mean (``mapper.map.global_map``).
When the node serves the learned model, the model's blended feature of a point (cross-view
attention over the window's views) is better than that average, but it is only available while
the views that see the point are in the window. :class:`PreEvictionFeatures` writes it into the
map before it is lost:

* when the window is full, the oldest keyframe is the next to leave; after each new keyframe
  (``node.keyframe_listeners``, integrator thread, O(1)), if it is not queued yet, it and the next
  oldest up to ``global_map.learned_features_batch`` keyframes are queued
  (:class:`KeyframeQueue`: bounded, the oldest dropped beyond ``learned_features_max_pending``);
* the worker thread (``mapper-map-features``) takes every queued keyframe, the map voxels their
  observations fall in (:meth:`GlobalSemanticMap.seen_voxels`, merged), asks the plugin's
  ``features`` callback ONCE for the blended features at their fused positions (the model's
  cached volume is recomputed once per window change, so batching is what keeps this cheap), and
  sets them (:meth:`GlobalSemanticMap.set_features`: new direction, the fused norm and weight kept);
  with ``global_map.learned_features_once`` (default) only for voxels that have no learned
  feature yet, so a voxel takes the blend of the window its first observers were in.

The core stays torch-free: the callback is supplied by the learned plugin
(``mapper.node.backends.learned``: ``ModelRuntime.point_features``). A keyframe whose turn came
after it had already left the window (the worker lagged) is still processed, with the views left,
and counted as ``late``. The node's ``map_version`` does not change (no geometry changes); query
snapshots see the new features (the map's internal version changes).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.map.window import Keyframe
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker

if TYPE_CHECKING:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.context import NodeContext

__all__ = ["FeatureFn", "PreEvictionFeatures", "ViewFeatureFn"]

log = logging.getLogger("mapper.node.workers.map_features")

FeatureFn = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray] | None"]
"""``features(xyz (M, 3) float32) -> (features (M, D) float32, valid (M,) bool)``, or None when
the model cannot answer now (not ready: nothing is written)."""

ViewFeatureFn = Callable[[Keyframe, "tuple[int, int]"], "tuple[np.ndarray, np.ndarray] | None"]
"""``view_features(keyframe, (h', w')) -> (features (h', w', D) float32, valid (h', w') bool)``: the
model's blended features at a keyframe's cells (its rendered surface through each), or None."""


class PreEvictionFeatures:
    """See the module docstring. ``install()`` hooks it into the node (before ``node.start()``)."""

    def __init__(
        self, ctx: NodeContext, features: FeatureFn, view_features: ViewFeatureFn | None = None
    ) -> None:
        self.ctx = ctx
        self.features = features
        self.view_features = view_features
        """With ``queries.evicted_frames_learned``: the learned map of each keyframe without depth,
        handed to the kept view the evicted-views worker makes of it
        (:meth:`mapper.node.workers.evicted_views.EvictedViews.offer_learned`)."""
        self.views_learned = 0
        self.queue: KeyframeQueue[tuple[Keyframe, GlobalSemanticMap]] = KeyframeQueue(
            ctx.config.global_map.learned_features_max_pending
        )
        self._queued: set[int] = set()
        """``id()`` of the keyframes queued and still in the window (each is queued once)."""
        self._busy = threading.Lock()
        self._in_batch = 0
        """Keyframes the worker took from the queue and has not finished (``pending`` counts them)."""
        self._limited = LimitedLog(log)
        self.keyframes_done = 0
        self.keyframes_late = 0
        self.keyframes_not_ready = 0
        self.voxels_set = 0
        self.calls = 0
        """Model evaluations (one per batch of keyframes)."""
        self.seconds_total = 0.0

    def install(self) -> None:
        """Register the keyframe listener, the eviction bookkeeping, the worker and ``status``."""
        node = self.ctx
        node.keyframe_listeners.append(self.on_keyframe)
        with node.state.lock:
            node.state.window.on_evict.append(self._on_evict)
        node.workers.append(("map-features", self.run))
        node.register_pending("map_features", lambda: self.pending)
        node.status_providers["map_features"] = self.stats

    # -- keyframe-listener thread ----------------------------------------------------------

    def on_keyframe(self, keyframe: Keyframe, map_version: int) -> None:
        """After a new keyframe: queue its robot's window's oldest when that window is full (it leaves
        next)."""
        state = self.ctx.state
        with state.lock:
            keyframes = state.window.robot_keyframes(keyframe.robot)
            if len(keyframes) < self.ctx.config.window.max_keyframes or id(keyframes[0]) in self._queued:
                return
            due = [k for k in keyframes[: self.ctx.config.global_map.learned_features_batch]
                   if id(k) not in self._queued]  # fmt: skip
            self._queued.update(id(k) for k in due)
            gmap = state.global_map
        for k in due:
            self.queue.put((k, gmap))

    def _on_evict(self, keyframe: Keyframe) -> None:
        """Window callback (state lock held): forget the keyframe's queued mark."""
        self._queued.discard(id(keyframe))

    # -- worker ------------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        """Worker thread body (``node.workers``)."""
        def on_error(exc: BaseException) -> None:
            self._limited.warning("error", "learned map features failed: %r", exc)

        run_worker(stop, self.queue.wake, self.process_pending, on_error)

    def process_pending(self) -> int:
        """Handle every queued keyframe now (also callable directly, e.g. by a benchmark).
        Returns the number of keyframes handled."""
        with self._busy:
            items = self.queue.drain()
            if items:
                self._in_batch = len(items)
                try:
                    self._process(items)
                finally:
                    self._in_batch = 0
        return len(items)

    @property
    def pending(self) -> int:
        """Keyframes waiting, including those of the batch the worker took and has not finished."""
        return len(self.queue) + self._in_batch

    def idle(self) -> bool:
        """Nothing queued and nothing being processed."""
        if len(self.queue):
            return False
        if self._busy.acquire(blocking=False):
            self._busy.release()
            return len(self.queue) == 0
        return False

    def _process(self, items: list[tuple[Keyframe, GlobalSemanticMap]]) -> None:
        started = time.perf_counter()
        state = self.ctx.state
        with state.lock:
            gmap = state.global_map
            in_window = {id(k) for k in state.window.keyframes}
        # a map loaded since: those keyframes belong to the old one
        keyframes = [k for k, m in items if m is gmap]
        if not keyframes:
            return
        once = gmap.config.learned_features_once  # voxels that have their learned feature are not asked again
        parts = [gmap.seen_voxels(k, unlearned=once) for k in keyframes]
        keys = np.concatenate([p[0] for p in parts])
        xyz = np.concatenate([p[1] for p in parts])
        keys, first = np.unique(keys, return_index=True)  # a voxel seen by several keyframes once
        xyz = xyz[first]
        if keys.shape[0]:
            answer = self.features(xyz)
            if answer is None:
                self.keyframes_not_ready += len(keyframes)
                return
            feats, valid = answer
            self.voxels_set += gmap.set_features(keys[valid], feats[valid])
        self._learned_views([k for k in keyframes if id(k) in in_window], gmap)
        self.keyframes_done += len(keyframes)
        self.keyframes_late += sum(1 for k in keyframes if id(k) not in in_window)
        self.calls += 1
        self.seconds_total += time.perf_counter() - started

    def _learned_views(self, keyframes: list[Keyframe], gmap: GlobalSemanticMap) -> None:
        """The learned maps of the keyframes without depth still in the window, for their kept views
        (``view_features``; a keyframe that left already is skipped: the window's volume and views no
        longer hold it)."""
        evicted = self.ctx.evicted_views
        if self.view_features is None or evicted is None or evicted.frames_budget <= 0:
            return
        from mapper.map.evicted_frames import reduced_shape

        cells = self.ctx.config.queries.evicted_frames_cells
        for k in keyframes:
            if k.depth_m is not None or k.ov is None:
                continue
            learned = self.view_features(k, reduced_shape(k.ov.shape[0], k.ov.shape[1], cells))
            if learned is not None:
                evicted.offer_learned(k, gmap, learned)
                self.views_learned += 1

    def stats(self) -> dict[str, Any]:
        """``status`` key ``map_features`` (called under the state lock: takes no node lock)."""
        return {
            "pending": self.pending,
            "queued": self.queue.queued,
            "dropped": self.queue.dropped,
            "done": self.keyframes_done,
            "late": self.keyframes_late,
            "not_ready": self.keyframes_not_ready,
            "voxels_set": self.voxels_set,
            "views_learned": self.views_learned,
            "calls": self.calls,
            "ms_per_call": round(1e3 * self.seconds_total / max(self.calls, 1), 3),
        }
