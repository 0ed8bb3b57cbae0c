"""Global-map points for keyframes without input depth, from the learned model's rendered depth.

A robot with a plain RGB camera sends frames without ``depth_m``. The global semantic point map
(:mod:`mapper.node.global_map`) back-projects input depth, so such keyframes would add no points. With
the learned model served, :class:`RenderedDepthPoints` fills the gap: for each such keyframe it
renders the model's depth at the keyframe's own pose (density only, no appearance pass: the cost
of a depth render is the 3D U-Net once per runtime version plus a density MLP per sample), at
``1 / rendered_depth_stride`` of the keyframe's size, keeps the pixels whose accumulated opacity
reaches ``rendered_min_opacity`` (the ray met a clear surface), and fuses them into the global map
exactly as input depth (same voxels, same OV sampling of the keyframe's own ``ov`` map, same
quality weights) with the weights scaled by ``rendered_weight * opacity``, so input depth outranks
rendered depth where both exist.

Scheduling: the node calls :meth:`RenderedDepthPoints.on_keyframe` on the ingest thread after a
keyframe entered the window (O(1): a deque append). A background worker (``mapper-depth-points``)
renders the pending keyframes in batches: one runtime sync and one 3D U-Net pass serve every
keyframe pending at that moment. Until the model's window holds ``rendered_min_views`` keyframes
the pending ones wait (a density field from one or two views is not a surface). Beyond
``rendered_max_pending`` waiting keyframes the oldest is dropped and counted. A map load replaces
the global map; keyframes queued for the old map are dropped (counted as ``stale``).

Errors never reach the ingest thread: a keyframe whose render fails is logged (rate limited) and
counted in ``failed``; the worker keeps running.

Example (in-process; ``node`` a :class:`mapper.node.service.MapperNode`, ``runtime`` a
:class:`mapper.runtime.model_runtime.ModelRuntime` already attached to it)::

    points = RenderedDepthPoints(node, runtime)
    points.install()          # listener + worker; node.start() starts the worker thread
    ...                       # frames without depth arrive
    points.process_pending()  # or let the worker do it; returns keyframes integrated
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.node.config import GlobalMapConfig
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker
from mapper.runtime.model_runtime import ModelRuntime, RuntimeNotReady

if TYPE_CHECKING:
    from mapper.node.global_map import GlobalSemanticMap
    from mapper.node.service import MapperNode

__all__ = ["RenderedDepthPoints", "RenderedKeyframe"]

log = logging.getLogger("mapper.node.plugins.depth_points")

@dataclass(frozen=True)
class RenderedKeyframe:
    """A keyframe's rendered depth at the render size, shaped like :class:`KeyframeLike`."""

    stamp_ns: int
    K: np.ndarray  # (4,) [fx, fy, cx, cy] for the render size
    world_from_cam: np.ndarray  # (4, 4)
    rgb: np.ndarray  # (h, w, 3) uint8 placeholder (the map uses only its shape)
    depth_m: np.ndarray  # (h, w) float32 z-depth, 0 where the render found no surface
    ov: np.ndarray | None  # (h_ov, w_ov, D) the keyframe's own OV map (covers the whole image)
    confidence: np.ndarray  # (h, w) float32 in [0, 1]: rendered_weight * opacity


def render_keyframe_depth(
    runtime: ModelRuntime, keyframe: Any, config: GlobalMapConfig
) -> RenderedKeyframe:
    """Render the model's depth at ``keyframe``'s pose at ``1 / rendered_depth_stride`` of its size.

    Raises :class:`RuntimeNotReady` (no model, no keyframes) like the runtime's render.
    """
    height, width = keyframe.rgb.shape[:2]
    stride = config.rendered_depth_stride
    w, h = max(1, width // stride), max(1, height // stride)
    sx, sy = w / width, h / height
    fx, fy, cx, cy = (float(v) for v in keyframe.K)
    K = np.array([fx * sx, fy * sy, cx * sx, cy * sy], np.float64)
    pose = np.asarray(keyframe.world_from_cam, np.float64)
    frame = runtime.render(K, pose, w, h, outputs=("depth",))
    assert frame.depth_m is not None and frame.opacity is not None
    opacity = np.nan_to_num(frame.opacity.astype(np.float32), nan=0.0)
    depth = np.where(opacity >= config.rendered_min_opacity, frame.depth_m, 0.0).astype(np.float32)
    return RenderedKeyframe(
        stamp_ns=int(keyframe.stamp_ns),
        K=K,
        world_from_cam=pose,
        rgb=np.zeros((h, w, 3), np.uint8),
        depth_m=depth,
        ov=keyframe.ov,
        confidence=(config.rendered_weight * np.clip(opacity, 0.0, 1.0)).astype(np.float32),
    )


class RenderedDepthPoints:
    """Adds rendered-depth points to ``node``'s global map for keyframes without input depth.

    Args:
        node: the mapper node (its ``state.global_map`` is read at integrate time, so a map load
            is followed).
        runtime: the learned-model runtime serving ``node``'s window.
        config: defaults to ``node.config.global_map``.
    """

    def __init__(
        self, node: MapperNode, runtime: ModelRuntime, config: GlobalMapConfig | None = None
    ) -> None:
        self.node = node
        self.runtime = runtime
        self.config = config or node.config.global_map
        self._lock = threading.Lock()
        self._queue: KeyframeQueue[tuple[Any, GlobalSemanticMap]] = KeyframeQueue(
            self.config.rendered_max_pending
        )
        self._busy = False
        self.integrated = 0
        self.points = 0
        self.stale = 0
        self.failed = 0
        self.seconds_total = 0.0
        self._log = LimitedLog(log)

    # -- wiring -------------------------------------------------------------------------------

    def install(self) -> None:
        """Listen to the node's new keyframes, report in its status (``"rendered_depth"``) and run
        the worker thread with the node (started by ``node.start()``)."""
        self.node.keyframe_listeners.append(self.on_keyframe)
        self.node.workers.append(("depth-points", self.run))
        self.node.status_providers["rendered_depth"] = self.stats

    def on_keyframe(self, keyframe: Any, map_version: int) -> None:
        """Queue ``keyframe`` if it has no input depth (ingest thread; O(1), never raises)."""
        if keyframe.depth_m is not None or not self.config.rendered_depth:
            return
        self._queue.put((keyframe, self.node.state.global_map))

    # -- work -----------------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        return len(self._queue)

    @property
    def queued(self) -> int:
        return self._queue.queued

    @property
    def dropped(self) -> int:
        return self._queue.dropped

    def process_pending(self) -> int:
        """Render and integrate every keyframe pending now (if the model's window is large enough).
        Returns the number of keyframes integrated. Safe to call from any thread."""
        if not self.runtime.ready:
            return 0
        with self._lock:
            if not len(self._queue) or self._busy:
                return 0
            self._busy = True
        try:
            try:
                self.runtime.sync()
            except RuntimeNotReady:
                return 0
            if len(self.runtime) < self.config.rendered_min_views:
                return 0  # wait for more keyframes; the pending ones stay queued
            return sum(self._integrate_one(keyframe, target) for keyframe, target in self._queue.drain())
        finally:
            with self._lock:
                self._busy = False

    def _integrate_one(self, keyframe: Any, target: GlobalSemanticMap) -> int:
        if target is not self.node.state.global_map:
            self.stale += 1  # a map load replaced the map this keyframe belonged to
            return 0
        started = time.perf_counter()
        if keyframe.ov is None:
            keyframe = self._with_current_features(keyframe)
        try:
            rendered = render_keyframe_depth(self.runtime, keyframe, self.config)
            stats = target.integrate(
                rendered,
                map_version=None,  # the map already carries a version >= this keyframe's
                pixel_stride=1,
                confidence=rendered.confidence,
                count_keyframe=False,
            )
        except (RuntimeNotReady, ValueError, RuntimeError) as exc:
            self.failed += 1
            self._log.warning("failed", "rendered depth for keyframe at stamp %d failed: %s",
                              keyframe.stamp_ns, exc)
            return 0
        seconds = time.perf_counter() - started
        self.integrated += 1
        self.points += stats.points
        self.seconds_total += seconds
        log.debug("rendered depth: %d points for keyframe at stamp %d in %.0f ms (%s)",
                  stats.points, keyframe.stamp_ns, 1e3 * seconds, stats.skipped or "ok")
        return 1

    def _with_current_features(self, keyframe: Any) -> Any:
        """The window's current copy of ``keyframe`` when it has gained OV features since it was
        queued (the in-process OV backend, :mod:`mapper.node.plugins.ov_features`, swaps in a
        featured copy)."""
        with self.node.state.lock:
            for current in self.node.state.window.keyframes:
                if (current.camera, current.seq, current.stamp_ns) == (
                    keyframe.camera, keyframe.seq, keyframe.stamp_ns
                ) and current.ov is not None:
                    return current
        return keyframe

    def run(self, stop: threading.Event) -> None:
        """Worker loop: process the pending keyframes whenever new ones arrive, until ``stop``."""
        run_worker(stop, self._queue.wake, self.process_pending, self._unexpected)

    def _unexpected(self, exc: BaseException) -> None:
        self.failed += 1
        log.error("rendered-depth worker: unexpected error (continuing)", exc_info=exc)

    def stats(self) -> dict[str, Any]:
        """Counters for the node's status reply."""
        return {
            "enabled": self.config.rendered_depth,
            "pending": self.pending,
            "queued": self.queued,
            "integrated": self.integrated,
            "points": self.points,
            "dropped": self.dropped,
            "stale": self.stale,
            "failed": self.failed,
            "mean_ms": round(1e3 * self.seconds_total / max(self.integrated, 1), 1),
        }
