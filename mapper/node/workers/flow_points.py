"""Dense points for RGB-only keyframes by optical flow against partner keyframes, off the ack path.

:class:`DenseFlowPoints` (``[dense_flow]``, off by default) matches each keyframe that arrives
without depth into its best ``max_partners`` earlier keyframes (by frustum overlap and baseline,
not recency) with OpenCV's DIS flow and triangulates the pixels with the known poses
(:mod:`mapper.geometry.dense_flow`). The points:

* join the **global map** the way the triangulated and swept depths do: a depth map of the
  keyframe (each working-size pixel at the full-size pixel under its centre) integrated with the
  keyframe's OV features at ``global_map_weight`` times a certainty that falls with the
  uncertainty, without carving; a keyframe whose features the in-process OV backend brings later
  gets them fused into its points then (``node.feature_listeners``);
* are kept (``max_points``, oldest keyframes first out) with their sigma: the rendered-depth
  points' consistency check (:mod:`mapper.node.workers.depth_points`) and ``render``'s measured
  surfaces (``ctx.surface_points``) use them beside the triangulated and swept points.

Scheduling: :meth:`DenseFlowPoints.on_keyframe` (keyframe-listener thread) only queues (O(1));
the worker ``dense-flow`` takes every queued keyframe oldest first (a keyframe costs tens of
milliseconds at 160 x 120, so a live stream does not outrun it); beyond ``max_pending`` waiting
keyframes the oldest is dropped and counted. Keyframes with depth only become partner candidates
(their small grayscale image). A map load clears the candidates and points. ``status`` reports
``dense_flow`` (``pending``, ``keyframes``, ``points_per_keyframe``, ``partners_per_keyframe``,
``global_map_points``, ``points``, ``mean_ms``, ``p90_ms``, ``no_partner``, ``dropped``, ``failed``).

Example (in-process; ``node`` a :class:`mapper.node.service.MapperNode`)::

    flow = DenseFlowPoints(node.ctx)
    flow.install()              # listener + worker + status "dense_flow"
    ...                         # frames without depth arrive
    flow.process_pending()      # or let the worker do it
    xyz, sigma = flow.geometry_points()
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.geometry.config import DenseFlowConfig
from mapper.geometry.dense_flow import FlowDepth, FlowView, flow_depth, flow_view, select_flow_partners
from mapper.geometry.triangulation import backproject
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker, with_current_features
from mapper.node.workers.triangulation import TriangulatedKeyframe, _KeyframeBudget, keyframe_key

if TYPE_CHECKING:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.context import NodeContext
    from mapper.node.service import MapperNode

__all__ = ["DenseFlowPoints", "flow_keyframe", "install_dense_flow"]

log = logging.getLogger("mapper.node.workers.flow_points")

KeyframeKey = tuple[str, int, int]


def flow_keyframe(
    keyframe: Any, view: FlowView, dense: FlowDepth, config: DenseFlowConfig
) -> TriangulatedKeyframe:
    """``dense`` (at ``view``'s working size) as a depth map of ``keyframe`` (full size): each point at
    the full-size pixel under its working-size pixel's centre, confidence ``global_map_weight`` times
    ``1 - sigma / (max_sigma_rel * depth)`` (at least 0.1)."""
    height, width = keyframe.rgb.shape[:2]
    h, w = view.gray.shape
    rows, cols = np.nonzero(dense.depth_m > 0)
    z = dense.depth_m[rows, cols]
    certainty = np.clip(1.0 - dense.sigma_m[rows, cols] / (config.max_sigma_rel * z), 0.1, 1.0)
    full_r = np.minimum(((rows + 0.5) * height / h).astype(np.int64), height - 1)
    full_c = np.minimum(((cols + 0.5) * width / w).astype(np.int64), width - 1)
    depth = np.zeros((height, width), np.float32)
    conf = np.zeros((height, width), np.float32)
    depth[full_r, full_c] = z
    conf[full_r, full_c] = config.global_map_weight * certainty
    return TriangulatedKeyframe(
        stamp_ns=int(keyframe.stamp_ns), K=np.asarray(keyframe.K, np.float64),
        world_from_cam=np.asarray(keyframe.world_from_cam, np.float64), rgb=keyframe.rgb,
        depth_m=depth, ov=keyframe.ov, confidence=conf,
    )


@dataclass(frozen=True)
class _Candidate:
    key: KeyframeKey
    view: FlowView
    robot: str = ""  # a keyframe's partners are its own robot's


class DenseFlowPoints:
    """Dense flow points of a node's RGB-only keyframes, in a background worker (module docstring)."""

    def __init__(self, ctx: NodeContext, config: DenseFlowConfig | None = None) -> None:
        self.ctx = ctx
        self.config = config or ctx.config.dense_flow
        self._lock = threading.Lock()  # the candidates, the kept points, the map they belong to
        self._work_lock = threading.Lock()
        self._queue: KeyframeQueue[tuple[Any, int, GlobalSemanticMap]] = KeyframeQueue(
            self.config.max_pending)
        self._candidates: deque[_Candidate] = deque(maxlen=self.config.candidate_keyframes)
        self._points: _KeyframeBudget[tuple[np.ndarray, np.ndarray]] = _KeyframeBudget(
            self.config.max_points, lambda xyz_sigma: len(xyz_sigma[1]))
        self._featureless: OrderedDict[KeyframeKey, tuple[GlobalSemanticMap, TriangulatedKeyframe]] = (
            OrderedDict())
        self._map: GlobalSemanticMap | None = None
        self._loaded_version = -1
        self._generation = 0
        self._in_batch = 0
        self._stop = threading.Event()
        self.processed = 0
        self.points_total = 0
        self.partners_total = 0
        self.matched_total = 0
        self.no_partner = 0
        self.map_points = 0
        self.late_feature_points = 0
        self.stale = 0
        self.failed = 0
        self.seconds: deque[float] = deque(maxlen=1000)
        self.seconds_total = 0.0
        self._log = LimitedLog(log)

    def install(self) -> None:
        """Listen to new keyframes, map loads and late features; report in ``status``
        (``"dense_flow"``); count ``pending`` as geometry work; run the worker with the node."""
        self.ctx.keyframe_listeners.append(self.on_keyframe)
        self.ctx.load_listeners.append(self.on_map_loaded)
        self.ctx.feature_listeners.append(self.on_features)
        self.ctx.surface_points.append(lambda: self.geometry_points()[0])
        self.ctx.workers.append(("dense-flow", self.run))
        self.ctx.register_pending("dense_flow", lambda: self.pending, geometry=True)
        self.ctx.status_providers["dense_flow"] = self.stats

    def on_keyframe(self, keyframe: Any, map_version: int) -> None:
        """Queue ``keyframe`` (O(1), never raises)."""
        if self.config.enabled:
            self._queue.put((keyframe, int(map_version), self.ctx.state.global_map))

    def on_map_loaded(self, global_map: GlobalSemanticMap, map_version: int,
                      keyframes: tuple[Any, ...] = ()) -> None:
        """A load replaced the map: forget the old map's candidates and points; the loaded window's
        keyframes become the partner candidates of the keyframes that follow (their points are in
        the loaded map already)."""
        views = [(keyframe_key(k), flow_view(k.rgb, k.K, k.world_from_cam, self.config.max_width),
                  getattr(k, "robot", "")) for k in keyframes[-self.config.candidate_keyframes:]] \
            if self.config.enabled else []
        with self._lock:
            self._loaded_version = max(self._loaded_version, int(map_version))
            self._reset_locked()
            self._map = global_map
            for key, view, robot in views:
                self._candidates.append(_Candidate(key, view, robot))

    def _reset_locked(self) -> None:
        self._generation += 1
        self._candidates.clear()
        self._points.clear()
        self._featureless.clear()

    @property
    def pending(self) -> int:
        """Keyframes waiting, including the batch being worked on."""
        return len(self._queue) + self._in_batch

    def process_pending(self) -> int:
        """Work on every keyframe pending now (oldest first); returns the RGB-only keyframes done."""
        if not self._work_lock.acquire(blocking=False):
            return 0
        try:
            batch = self._queue.drain()
            self._in_batch = len(batch)
            done = 0
            for n, (keyframe, version, target) in enumerate(batch):
                if self._stop.is_set():
                    break
                try:
                    done += self._process_one(keyframe, version, target)
                except Exception as exc:  # bad input, OpenCV errors: count, never kill the worker
                    self.failed += 1
                    self._log.warning("failed", "dense flow of keyframe at stamp %d failed: %s",
                                      keyframe.stamp_ns, exc)
                finally:
                    self._in_batch = len(batch) - n - 1
            return done
        finally:
            self._in_batch = 0
            self._work_lock.release()

    def _process_one(self, keyframe: Any, map_version: int, target: GlobalSemanticMap) -> int:
        started = time.perf_counter()
        with self._lock:
            if map_version <= self._loaded_version:
                self.stale += 1
                return 0
            if target is not self._map:
                if self._map is not None:
                    self._reset_locked()
                self._map = target
            generation = self._generation
            robot = getattr(keyframe, "robot", "")
            candidates = [c for c in self._candidates if c.robot == robot]
        view = flow_view(keyframe.rgb, keyframe.K, keyframe.world_from_cam, self.config.max_width)
        key = keyframe_key(keyframe)
        with self._lock:
            if generation == self._generation:
                self._candidates.append(_Candidate(key, view, robot))
        if keyframe.depth_m is not None:
            return 0
        chosen = select_flow_partners(view.posed, [c.view.posed for c in candidates], self.config)
        if not chosen:
            self.no_partner += 1
            self._done(started, None, 0)
            return 1
        dense = flow_depth(view, [candidates[i].view for i in chosen], self.config)
        rows, cols, xyz = backproject(dense.depth_m, view.K, view.world_from_cam)
        sigma = dense.sigma_m[rows, cols].astype(np.float64)
        with self._lock:
            if generation != self._generation:
                self.stale += 1
                return 0
            if len(sigma) and self.config.max_points > 0:
                self._points.put(key, (xyz, sigma))
        if len(sigma) and self.config.global_map_weight > 0.0:
            current = with_current_features(self.ctx, keyframe)
            self._fuse(current, flow_keyframe(current, view, dense, self.config), target)
        self._done(started, dense, len(chosen))
        return 1

    def _done(self, started: float, dense: FlowDepth | None, partners: int) -> None:
        seconds = time.perf_counter() - started
        self.processed += 1
        self.partners_total += partners
        if dense is not None:
            self.points_total += len(dense)
            self.matched_total += dense.matched
        with self._lock:
            self.seconds.append(seconds)
        self.seconds_total += seconds

    def _fuse(self, keyframe: Any, depth: TriangulatedKeyframe, target: GlobalSemanticMap) -> None:
        if target is not self.ctx.state.global_map:
            self.stale += 1
            return
        stats = target.integrate(depth, map_version=None, pixel_stride=1, confidence=depth.confidence,
                                 count_keyframe=False, carve=False)  # not input depth: no carving
        self.map_points += stats.points
        if depth.ov is None and self.ctx.config.ov_backend.kind:  # features come later from the backend
            with self._lock:
                self._featureless[keyframe_key(keyframe)] = (target, depth)
                while len(self._featureless) > max(1, self.ctx.config.ov_backend.max_pending):
                    self._featureless.popitem(last=False)
            current = with_current_features(self.ctx, keyframe)
            if current.ov is not None:  # swapped in meanwhile
                self.on_features(current)

    def on_features(self, keyframe: Any) -> None:
        """``node.feature_listeners``: fuse ``keyframe``'s new OV features into the points added for it
        without features. Never raises."""
        with self._lock:
            entry = self._featureless.pop(keyframe_key(keyframe), None)
        if entry is None or keyframe.ov is None:
            return
        target, depth = entry
        if target is not self.ctx.state.global_map:
            return
        try:
            stats = target.integrate_features(replace(depth, ov=keyframe.ov), pixel_stride=1,
                                              confidence=depth.confidence)
        except (ValueError, RuntimeError) as exc:
            self.failed += 1
            self._log.warning("features", "dense flow: late features of stamp %d failed: %s",
                              keyframe.stamp_ns, exc)
            return
        self.late_feature_points += stats.points

    def geometry_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The kept points: ``(xyz (N, 3) float64 world, sigma_m (N,) float64 along the ray)``."""
        with self._lock:
            kept = list(self._points.items.values())
        if not kept:
            return np.zeros((0, 3)), np.zeros(0)
        return np.concatenate([p for p, _ in kept]), np.concatenate([s for _, s in kept])

    def run(self, stop: threading.Event) -> None:
        """Worker loop until ``stop``."""
        self._stop = stop
        run_worker(stop, self._queue.wake, self.process_pending, self._unexpected)

    def _unexpected(self, exc: BaseException) -> None:
        self.failed += 1
        log.error("dense flow worker: unexpected error (continuing)", exc_info=exc)

    def stats(self) -> dict[str, Any]:
        """Counters for the node's ``status`` reply."""
        with self._lock:
            recent = sorted(self.seconds)
        done = max(self.processed, 1)
        return {
            "enabled": self.config.enabled,
            "pending": self.pending,
            "queued": self._queue.queued,
            "dropped": self._queue.dropped,
            "keyframes": self.processed,
            "no_partner": self.no_partner,
            "matched_per_keyframe": round(self.matched_total / done, 1),
            "points_per_keyframe": round(self.points_total / done, 1),
            "partners_per_keyframe": round(self.partners_total / done, 2),
            "global_map_points": self.map_points,
            "late_feature_points": self.late_feature_points,
            "points": self._points.total,
            "mean_ms": round(1e3 * self.seconds_total / done, 1),
            "p90_ms": round(1e3 * recent[int(0.9 * (len(recent) - 1))], 1) if recent else 0.0,
            "stale": self.stale,
            "failed": self.failed,
        }


def install_dense_flow(node: MapperNode) -> DenseFlowPoints | None:
    """Install :class:`DenseFlowPoints` on ``node`` when ``dense_flow.enabled`` (returned; else None)."""
    if not node.config.dense_flow.enabled:
        return None
    flow = DenseFlowPoints(node.ctx)
    flow.install()
    return flow
