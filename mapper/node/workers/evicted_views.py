"""The node's worker that keeps the views of keyframes that left the window for the averaging
methods (``queries.evicted_views``): for each keyframe the window evicts (queued by the ingest
path; the ack never waits), it samples the keyframe's OV map at every global-map voxel with the
averaging's own selection (:func:`mapper.model.baselines.view_samples`) and adds the samples to the
global map's :class:`mapper.map.evicted_views.EvictedViewStore` (what they are and how
``average`` / ``average_depth`` use them: :mod:`mapper.map.evicted_views`)."""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.map.evicted_views import behind_surface, in_image
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker

if TYPE_CHECKING:
    from mapper.map.window import Keyframe

__all__ = ["EvictedViews"]

# The worker takes the node's context and its global maps (``mapper.map.global_map.GlobalSemanticMap``)
# as ``Any``: the global map holds the store, so naming those types would make an import cycle.

log = logging.getLogger("mapper.node.workers.evicted_views")

OCCLUSION_REL_TOL = 0.25
"""``queries.evicted_views_occlusion``: a voxel more than this share of the measured depth behind
it is hidden from the keyframe (the averaging's depth-test tolerance)."""


def frame_key(keyframe: Keyframe) -> tuple[Any, ...]:
    """A keyframe's identity across the workers (robot, camera, seq, stamp)."""
    return (keyframe.robot, keyframe.camera, int(keyframe.seq), int(keyframe.stamp_ns))


def keyframe_bytes(keyframe: Keyframe) -> int:
    """What a queued keyframe holds: its colour, depth and OV arrays."""
    return sum(int(a.nbytes) for a in (keyframe.rgb, keyframe.depth_m, keyframe.ov) if a is not None)


class EvictedViews:
    """The node's worker that adds evicted keyframes' views to their global map's store (module
    docstring). ``install()`` hooks it into the node (before ``node.start()``)."""

    def __init__(self, ctx: Any) -> None:  # NodeContext
        self.ctx = ctx
        cfg = ctx.config
        self.queue: KeyframeQueue[tuple[Keyframe, Any]] = KeyframeQueue(  # (keyframe, its GlobalSemanticMap)
            cfg.queries.evicted_views_max_pending,
            max_bytes=int(cfg.queries.evicted_views_max_pending_mb * 2**20),
            size_of=lambda item: keyframe_bytes(item[0]),
        )
        self.both = cfg.queries.evicted_views == "both"
        """Also the ``all`` channel (``average``); else ``depth`` only (``average_depth``)."""
        self.frames_budget = int(cfg.queries.evicted_frames_mb * 2**20) if self.both else 0
        """``queries.evicted_frames_mb`` in bytes: keyframes without depth kept as reduced views
        (:mod:`mapper.map.evicted_frames`) instead of their samples at the voxels; 0 = off."""
        self.frame_cells = cfg.queries.evicted_frames_cells
        self.all_occlusion = cfg.queries.evicted_views_occlusion
        """``queries.evicted_views_occlusion``: the ``all`` channel of a keyframe with depth leaves
        out the voxels behind what it measured (:func:`mapper.map.evicted_views.behind_surface`)."""
        self.border_px = 10.0
        """The averaging's border (``segment_average``'s default; the node's methods use it)."""
        self.chunk = 32_768
        """Voxels sampled at a time (the samples are (chunk, D) float32 per channel)."""
        self._busy = threading.Lock()
        self._in_batch = 0
        self._limited = LimitedLog(log)
        self.done = 0
        self.stale = 0
        self.deferred = 0
        """Times the worker left queued keyframes for later because the integrator had work."""
        self.seconds_total = 0.0
        self._learned_lock = threading.Lock()
        self._learned_waiting: dict[tuple[Any, ...], tuple[np.ndarray, np.ndarray]] = {}
        """Learned maps (:meth:`offer_learned`) of keyframes not kept yet, by :func:`frame_key`."""
        self.learned_late = 0
        """Learned maps whose keyframe was not kept (dropped, a depth keyframe, a map loaded since)."""

    def install(self) -> None:
        self.ctx.workers.append(("evicted-views", self.run))
        self.ctx.register_pending("evicted_views", lambda: self.pending)
        self.ctx.status_providers["evicted_views"] = self.stats

    def put(self, keyframe: Keyframe, gmap: Any) -> None:  # gmap: GlobalSemanticMap
        """Queue a keyframe the window evicted (cheap; any thread)."""
        if keyframe.ov is not None and (self.both or keyframe.depth_m is not None):
            self.queue.put((keyframe, gmap))

    def run(self, stop: threading.Event) -> None:
        """Worker thread body (``node.workers``): absorbs queued keyframes one at a time while the
        integrator has nothing waiting or this queue is half full (a keyframe's integration comes
        first: the cores go to the stream; what waits here is picked up when the next keyframe
        leaves or within a poll)."""
        def on_error(exc: BaseException) -> None:
            self._limited.warning("error", "evicted views failed: %r", exc)

        def work() -> None:
            while len(self.queue) and not stop.is_set():
                # the integrator first, unless this queue is half full (then nothing is dropped)
                q = self.queue
                half_full = 2 * len(q) >= q.max_len or (q.max_bytes > 0 and 2 * q.bytes >= q.max_bytes)
                if self.ctx.integration.backlog() > 0 and not half_full:
                    self.deferred += 1
                    return
                self._process_one()

        run_worker(stop, self.queue.wake, work, on_error)

    def process_pending(self) -> int:
        """Absorb every queued keyframe now (also callable directly: ``save``, benchmarks).
        Returns how many."""
        n = 0
        while self._process_one():
            n += 1
        return n

    def _process_one(self) -> bool:
        with self._busy:
            self._in_batch = 1  # before the pop: ``pending`` never reads 0 while one is in hand
            item = self.queue.pop()
            if item is None:
                self._in_batch = 0
                return False
            try:
                self._absorb(*item)
            finally:
                self._in_batch = 0
            return True

    @property
    def pending(self) -> int:
        return len(self.queue) + self._in_batch

    def offer_learned(self, keyframe: Keyframe, gmap: Any, learned: tuple[np.ndarray, np.ndarray]) -> None:
        """The learned model's features at ``keyframe``'s kept view's cells (``(h', w', D)``, ``(h',
        w')`` valid; :meth:`EvictedFrameStore.add`), from the pre-eviction worker: given to its kept
        view now, or when the keyframe is kept (any thread). At most ``4 x window.max_keyframes`` wait;
        beyond that the oldest is dropped (counted in ``learned_late``)."""
        with self.ctx.state.lock:
            current = self.ctx.state.global_map
        if gmap is not current or self.frames_budget <= 0:
            return
        key = frame_key(keyframe)
        with self._learned_lock:  # held across the store's update: _absorb reads the waiting ones under it
            try:
                if gmap.evicted.frames.set_learned(key, learned):
                    return
            except ValueError:  # another grid than its kept view's (cells changed by a load)
                self.learned_late += 1
                return
            self._learned_waiting[key] = learned
            while len(self._learned_waiting) > 4 * self.ctx.config.window.max_keyframes:
                self._learned_waiting.pop(next(iter(self._learned_waiting)))
                self.learned_late += 1

    def _absorb(self, keyframe: Keyframe, gmap: Any) -> None:  # gmap: GlobalSemanticMap
        """One evicted keyframe: kept as a reduced view when it has no depth and
        ``queries.evicted_frames_mb`` is on (the views that budget drops: sampled at the voxels
        instead), else its samples at the map's voxels."""
        started = time.perf_counter()
        with self.ctx.state.lock:
            current = self.ctx.state.global_map
        if gmap is not current:  # a map loaded since: the keyframe belongs to the old one
            self.stale += 1
            return
        if self.frames_budget > 0 and keyframe.depth_m is None and keyframe.ov is not None:
            key = frame_key(keyframe)
            with self._learned_lock:
                learned = self._learned_waiting.pop(key, None)
                try:
                    dropped = gmap.evicted.frames.add(
                        keyframe.ov, keyframe.K, keyframe.world_from_cam, (keyframe.width, keyframe.height),
                        max_cells=self.frame_cells, budget_bytes=self.frames_budget, learned=learned, key=key)
                except ValueError:  # a learned map of another grid: the view is kept without it
                    if learned is None:
                        raise
                    self.learned_late += 1
                    dropped = gmap.evicted.frames.add(
                        keyframe.ov, keyframe.K, keyframe.world_from_cam, (keyframe.width, keyframe.height),
                        max_cells=self.frame_cells, budget_bytes=self.frames_budget, key=key)
            gmap.evicted.absorb(np.zeros(0, np.int64), {})  # counts the keyframe
            for frame in dropped:
                self._absorb_voxels(frame, gmap, count=False)
        else:
            self._absorb_voxels(keyframe, gmap)
        self.done += 1
        self.seconds_total += time.perf_counter() - started

    def _absorb_voxels(self, keyframe: Any, gmap: Any, count: bool = True) -> None:
        """A keyframe's (or a dropped kept view's: ``count`` False, counted already) samples at
        every map voxel it counts for, into the per-voxel means."""
        from mapper.model.baselines import OVView, view_samples  # torch-heavy; imported when first used

        map_xyz, map_keys = gmap.geometry()  # points and keys only: no copy of the map's features
        if gmap.paged_points and keyframe.ov is not None:  # paged voxels too (read, not paged in)
            paged_xyz, paged_keys = gmap.paged_geometry()
            map_xyz = np.concatenate([map_xyz, paged_xyz])
            map_keys = np.concatenate([map_keys, paged_keys])
        if map_xyz.shape[0] == 0 or keyframe.ov is None:
            return
        view = OVView(keyframe.ov, keyframe.K, keyframe.world_from_cam, (keyframe.width, keyframe.height),
                      keyframe.depth_m)
        rows = in_image(map_xyz, keyframe.K, keyframe.world_from_cam, (keyframe.width, keyframe.height),
                        self.border_px)
        store = gmap.evicted
        first = count
        for lo in range(0, rows.shape[0], self.chunk):  # bounded memory: (chunk, D) samples at a time
            part = rows[lo: lo + self.chunk]
            xyz = map_xyz[part]
            samples = {}
            if self.both:
                feat, counted = view_samples(xyz, view, use_depth=False, border_px=self.border_px)
                if keyframe.depth_m is not None and self.all_occlusion:  # not through what it measured
                    hidden = behind_surface(xyz, keyframe.K, keyframe.world_from_cam, keyframe.depth_m,
                                            OCCLUSION_REL_TOL)
                    counted = counted & ~hidden
                    feat[hidden] = 0.0
                samples["all"] = (feat, counted)
            if keyframe.depth_m is not None:
                samples["depth"] = view_samples(xyz, view, use_depth=True, border_px=self.border_px)
            store.absorb(map_keys[part], samples, new_keyframe=first)
            first = False
        if first:
            store.absorb(np.zeros(0, np.int64), {})  # counts the keyframe (no voxel in its image)
        if len(store) > max(2 * gmap.total_points, 4096):  # voxels the map pruned since (paged ones stay)
            store.compact(gmap.all_keys())

    def stats(self) -> dict[str, Any]:
        """``status`` key ``evicted_views`` (called under the state lock: takes no node lock)."""
        store = self.ctx.state.global_map.evicted
        return {
            "pending": self.pending,
            "dropped": self.queue.dropped,
            "done": self.done,
            "stale": self.stale,
            "deferred": self.deferred,
            "ms_per_keyframe": round(1e3 * self.seconds_total / max(self.done, 1), 3),
            "learned_late": self.learned_late,
            "bytes": store.nbytes,
            **store.stats(),
            **store.frames.stats(),
        }
