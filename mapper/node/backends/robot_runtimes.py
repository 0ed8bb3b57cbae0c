"""The learned model over every robot's window: :class:`RobotRuntimes`.

Each robot's keyframe window (:class:`mapper.map.robot_windows.RobotWindows`) gets a
:class:`~mapper.runtime.model_runtime.ModelRuntime` of its own (its own views and incremental cost
volume, whose bounds follow that robot's keyframes only), all on one loaded network
(:meth:`ModelRuntime.sibling`). The first robot takes the runtime the node was given, so a node
fed by one robot serves exactly as that runtime alone.

:class:`RobotRuntimes` answers like one runtime (what the learned backend and the node's workers
call), by these rules:

* **points** (``segment``, ``segment_cosines``, ``point_features``): a point is asked of the
  runtimes of the robots whose windows observed it (a keyframe's input depth, or its frustum up to
  ``global_map.max_depth_m``, holds it: :func:`mapper.map.robot_windows.robot_groups`; of every
  robot where none does); where several of them answer, the point takes the mean of their
  cosines (of their blended features for ``point_features``), each window once; a point no window
  sees has no answer (the global map answers it). With one robot, that runtime's answer as it is.
* **renders**: the runtime of the robot whose window holds the keyframe nearest the rendered
  camera (camera centres).
* **per-keyframe settings** (``set_view_extent``, ``set_view_depth_prior``): the runtime of the
  keyframe's robot (none once the keyframe left its window).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from mapper.errors import RuntimeNotReady
from mapper.map.robot_windows import RobotWindows, robot_groups
from mapper.map.window import Keyframe, KeyframeWindow
from mapper.runtime.entries import keyframe_key
from mapper.runtime.model_runtime import ModelRuntime, RenderFrame

__all__ = ["RobotRuntimes"]

Key = tuple[str, int, int]


def _merge_timing(timings: list[dict[str, float]]) -> dict[str, float]:
    out: dict[str, float] = {}
    for timing in timings:
        for key, value in timing.items():
            out[key] = out.get(key, 0.0) + float(value)
    return out


class RobotRuntimes:
    """One :class:`ModelRuntime` per robot window (module docstring). Thread-safe: the robots'
    runtimes are made under the node's state lock and read as one tuple swapped whole."""

    def __init__(self, primary: ModelRuntime, max_range_m: float = 8.0) -> None:
        self.primary = primary
        self.max_range_m = max_range_m
        """How far a keyframe without depth observes (``global_map.max_depth_m``): which windows a
        point is asked of."""
        self._runtimes: tuple[tuple[str, ModelRuntime, KeyframeWindow], ...] = ()
        self._robot_of: dict[Key, str] = {}
        """Keyframe key -> its robot, for the keyframes in a window (the per-keyframe settings)."""
        self._lock = threading.Lock()

    # -- following the windows (state lock held) ----------------------------------------------

    def attach(self, windows: RobotWindows) -> None:
        """Give each robot's window (those there now and those made later) its runtime. Call with
        the node's state lock held."""
        windows.on_robot.append(self._new_robot)
        windows.on_add.append(self._added)
        windows.on_evict.append(self._evicted)
        for robot, window in windows.windows():
            self._new_robot(robot, window)
            for keyframe in window.keyframes:
                self._added(keyframe)

    def _new_robot(self, robot: str, window: KeyframeWindow) -> None:
        runtime = self.primary if not self._runtimes else self.primary.sibling()
        runtime.attach(window)
        self._runtimes = (*self._runtimes, (robot, runtime, window))

    def _added(self, keyframe: Keyframe) -> None:
        with self._lock:
            self._robot_of[keyframe_key(keyframe)] = keyframe.robot

    def _evicted(self, keyframe: Keyframe) -> None:
        with self._lock:
            self._robot_of.pop(keyframe_key(keyframe), None)

    def runtimes(self) -> dict[str, ModelRuntime]:
        """Robot -> its runtime (robots in the order they first sent a frame)."""
        return {robot: runtime for robot, runtime, _ in self._runtimes}

    def _of(self, key: Key) -> ModelRuntime | None:
        with self._lock:
            robot = self._robot_of.get(key)
        if robot is None:
            return None if len(self._runtimes) > 1 else self.primary
        return next((rt for r, rt, _ in self._runtimes if r == robot), None)

    # -- what one runtime offers --------------------------------------------------------------

    @property
    def config(self) -> Any:
        return self.primary.config

    @property
    def load_error(self) -> str | None:
        return self.primary.load_error

    @property
    def ready(self) -> bool:
        return self.primary.ready

    @property
    def device(self) -> Any:
        return self.primary.device

    def __len__(self) -> int:
        return sum(len(rt) for _, rt, _ in self._runtimes) if self._runtimes else len(self.primary)

    def sync(self) -> int:
        """Apply every robot's recorded window changes; returns how many were applied."""
        if not self._runtimes:
            return self.primary.sync()
        return sum(rt.sync() for _, rt, _ in self._runtimes)

    def memory_bytes(self) -> int:
        return sum(rt.memory_bytes() for _, rt, _ in self._runtimes) if self._runtimes \
            else self.primary.memory_bytes()

    def stats(self) -> dict[str, Any]:
        """The first robot's runtime's ``status`` counters; with several robots ``views``,
        ``pending`` and ``memory_bytes`` summed over them and ``robots`` (robot -> its runtime's
        ``views``, ``rebuilds``, ``memory_bytes`` and ``bounds``)."""
        out = self.primary.stats()
        if len(self._runtimes) > 1:
            per = {robot: rt.stats() for robot, rt, _ in self._runtimes}
            for key in ("views", "pending", "memory_bytes"):
                out[key] = sum(int(s[key]) for s in per.values())
            out["robots"] = {robot: {k: s[k] for k in ("views", "rebuilds", "memory_bytes", "bounds")}
                             for robot, s in per.items()}
        return out

    def set_view_extent(self, key: Key, points_m: np.ndarray | None) -> None:
        runtime = self._of(key)
        if runtime is not None:
            runtime.set_view_extent(key, points_m)

    def set_view_depth_prior(self, key: Key, depth_m: np.ndarray | None) -> None:
        runtime = self._of(key)
        if runtime is not None:
            runtime.set_view_depth_prior(key, depth_m)

    # -- answers ------------------------------------------------------------------------------

    def _answering(self) -> list[ModelRuntime]:
        """The runtimes whose windows hold keyframes (the primary alone before any robot)."""
        live = [rt for _, rt, window in self._runtimes if len(window)]
        return live or [self.primary]

    def _groups(self, points: np.ndarray) -> list[tuple[list[ModelRuntime], np.ndarray]] | None:
        """Which runtimes each point is asked of (module docstring), None: every runtime holding
        keyframes, every point."""
        held = [(robot, window.keyframes) for robot, _, window in self._runtimes]
        groups = robot_groups(held, points, self.max_range_m)
        if groups is None:
            return None
        by_robot = self.runtimes()
        return [([by_robot[r] for r in robots], idx) for robots, idx in groups]

    def segment(
        self, points: np.ndarray, texts: Sequence[str], *, use_depth: bool = False
    ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
        runtimes = self._answering()
        if len(runtimes) == 1:
            return runtimes[0].segment(points, texts, use_depth=use_depth)
        label, score, _, timing = self.segment_cosines(points, texts, use_depth=use_depth)
        return label, score, timing

    def segment_cosines(
        self, points: np.ndarray, texts: Sequence[str], *, use_depth: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
        """The cosines of the windows that observed each point, averaged where several answer
        (module docstring)."""
        runtimes = self._answering()
        if len(runtimes) == 1:
            return runtimes[0].segment_cosines(points, texts, use_depth=use_depth)
        xyz = np.asarray(points, np.float32)
        n = xyz.shape[0]
        groups = self._groups(xyz) or [(runtimes, np.arange(n))]
        total = np.zeros((n, len(texts)), np.float32)
        count = np.zeros(n, np.float32)
        timings: list[dict[str, float]] = []
        refusal: RuntimeNotReady | None = None
        for members, idx in groups:
            for runtime in members:
                try:
                    label, _, cos, timing = runtime.segment_cosines(xyz[idx], texts, use_depth=use_depth)
                except RuntimeNotReady as exc:  # e.g. a window without OV views: the others answer
                    refusal = refusal or exc
                    continue
                seen = label >= 0
                total[idx[seen]] += cos[seen]
                count[idx[seen]] += 1.0
                timings.append(timing)
        if not timings:
            assert refusal is not None
            raise refusal
        seen = count > 0
        cos = np.where(seen[:, None], total / np.maximum(count, 1.0)[:, None], 0.0).astype(np.float32)
        label = np.where(seen, np.argmax(cos, axis=1), -1).astype(np.int32)
        score = np.where(seen, cos[np.arange(n), np.maximum(label, 0)], 0.0).astype(np.float32)
        timing = _merge_timing(timings)
        timing["robot_groups"] = float(len(groups))
        return label, score, cos, timing

    def point_features(self, points: np.ndarray, *, use_depth: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The blended features of the windows that observed each point, averaged where several
        answer."""
        runtimes = self._answering()
        if len(runtimes) == 1:
            return runtimes[0].point_features(points, use_depth=use_depth)
        xyz = np.asarray(points, np.float32)
        n = xyz.shape[0]
        groups = self._groups(xyz) or [(runtimes, np.arange(n))]
        total: np.ndarray | None = None
        count = np.zeros(n, np.float32)
        refusal: RuntimeNotReady | None = None
        for members, idx in groups:
            for runtime in members:
                try:
                    feats, valid = runtime.point_features(xyz[idx], use_depth=use_depth)
                except RuntimeNotReady as exc:
                    refusal = refusal or exc
                    continue
                if total is None:
                    total = np.zeros((n, feats.shape[1]), np.float32)
                total[idx[valid]] += feats[valid]
                count[idx[valid]] += 1.0
        if total is None:
            assert refusal is not None
            raise refusal
        valid = count > 0
        return (total / np.maximum(count, 1.0)[:, None]).astype(np.float32), valid

    def render_runtime(self, world_from_cam: np.ndarray) -> ModelRuntime:
        """The runtime of the robot whose window holds the keyframe nearest the camera at
        ``world_from_cam`` (camera centres); the primary before any keyframe."""
        centre = np.asarray(world_from_cam, np.float64)[:3, 3]
        best, best_d = self.primary, np.inf
        for _, runtime, window in self._runtimes:
            keyframes = window.keyframes
            if not keyframes:
                continue
            centres = np.stack([np.asarray(k.world_from_cam)[:3, 3] for k in keyframes])
            d = float(np.min(np.linalg.norm(centres - centre, axis=1)))
            if d < best_d:
                best, best_d = runtime, d
        return best

    def render(
        self, K: np.ndarray | Sequence[float], world_from_cam: np.ndarray, width: int, height: int,
        outputs: Sequence[str], texts: Sequence[str] | None = None, **kwargs: Any,
    ) -> RenderFrame:
        """:meth:`ModelRuntime.render` by :meth:`render_runtime`'s runtime."""
        return self.render_runtime(world_from_cam).render(K, world_from_cam, width, height, outputs, texts,
                                                          **kwargs)
