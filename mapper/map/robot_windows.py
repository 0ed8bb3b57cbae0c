"""One keyframe window per robot: :class:`RobotWindows`.

Frames carry an optional robot name (``Frame.robot``; "" is the default robot). Each robot gets
its own :class:`~mapper.map.window.KeyframeWindow` (keyframe selection relative to that robot's own
last keyframe of the camera, ``window.max_keyframes`` keyframes of its own, its own eviction), up to
``window.max_robots`` robots; every robot's keyframes fuse into the one global map. A robot's window
is made by its first frame and kept (empty after a ``load`` that holds none of its keyframes) while
the node runs.

:class:`RobotWindows` offers the single window's interface (``keyframes``, ``consider``,
``replace``, ``swap``, ``clear``, ``on_add`` / ``on_evict``): ``keyframes`` are every robot's
(robot by robot, in the order the robots first sent a frame; with one robot, exactly its window's),
and the callbacks fire for a change in any robot's window. What is per window (the learned model's
cost volume) follows one robot's window through :attr:`RobotWindows.on_robot`.

Example::

    >>> import numpy as np
    >>> from mapper.map.window import Keyframe, WindowConfig
    >>> windows = RobotWindows(WindowConfig(max_keyframes=2, min_translation_m=0.1, max_robots=2))
    >>> def kf(seq, x, robot):
    ...     world_from_cam = np.eye(4); world_from_cam[0, 3] = x
    ...     return Keyframe(seq=seq, stamp_ns=seq, camera="cam0", K=np.array([100.0, 100.0, 80.0, 60.0]),
    ...                     world_from_cam=world_from_cam,
    ...                     rgb=np.zeros((120, 160, 3), np.uint8),
    ...                     robot=robot)
    >>> frames = [(0.0, "a"), (12.0, "b"), (0.05, "a")]
    >>> [windows.consider(kf(i, x, r)).added for i, (x, r) in enumerate(frames)]
    [True, True, False]
    >>> windows.counts()
    {'a': 1, 'b': 1}
    >>> windows.check_robot("c")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    mapper.map.robot_windows.TooManyRobots: robot 'c' would be robot 3 of at most 2 (window.max_robots); ...
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np

from mapper.map.window import Keyframe, KeyframeCallback, KeyframeWindow, WindowConfig, WindowUpdate

__all__ = ["RobotCallback", "RobotWindows", "TooManyRobots", "observed_box", "robot_groups"]

RobotCallback = Callable[[str, KeyframeWindow], None]


def observed_box(keyframe: Keyframe, max_range_m: float, stride: int = 8, pad_m: float = 0.1
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box (min (3,), max (3,), world metres) of what ``keyframe`` observed: its
    input depth back-projected (every ``stride``-th pixel, up to ``max_range_m``), or, without
    depth, its frustum up to ``max_range_m``; padded by ``pad_m``."""
    fx, fy, cx, cy = (float(v) for v in keyframe.K)
    pose = np.asarray(keyframe.world_from_cam, np.float64)
    h, w = keyframe.height, keyframe.width
    cam: np.ndarray | None = None
    if keyframe.depth_m is not None:
        depth = np.asarray(keyframe.depth_m)[::stride, ::stride]
        rows, cols = np.nonzero(np.isfinite(depth) & (depth > 0) & (depth <= max_range_m))
        if rows.size:
            z = depth[rows, cols].astype(np.float64)
            u, v = cols * stride + 0.5, rows * stride + 0.5
            cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    if cam is None:  # the frustum: the camera centre and the image corners at max_range_m
        u, v = np.array([0.0, w, 0.0, w]), np.array([0.0, 0.0, h, h])
        cam = np.concatenate([np.zeros((1, 3)), np.stack([(u - cx) / fx * max_range_m,
                                                          (v - cy) / fy * max_range_m,
                                                          np.full(4, max_range_m)], axis=1)])
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    return world.min(axis=0) - pad_m, world.max(axis=0) + pad_m


def robot_groups(
    windows: Iterable[tuple[str, Iterable[Keyframe]]],
    xyz: np.ndarray,  # (N, 3) world points
    max_range_m: float,
) -> list[tuple[tuple[str, ...], np.ndarray]] | None:
    """Which robots' windows answer each point: those with a keyframe whose :func:`observed_box`
    holds it (all robots with keyframes where none does). Returns ``(robots, point indices)``
    groups, or None when one group would take every point with every robot (fewer than two robots
    with keyframes, or every point inside every robot's boxes): then all windows answer all points,
    as one window does."""
    held = [(robot, list(keyframes)) for robot, keyframes in windows]
    held = [(robot, keyframes) for robot, keyframes in held if keyframes]
    if len(held) < 2:
        return None
    points = np.asarray(xyz, np.float64)
    inside = np.zeros((len(held), points.shape[0]), bool)
    for r, (_, keyframes) in enumerate(held):
        for keyframe in keyframes:
            lo, hi = observed_box(keyframe, max_range_m)
            inside[r] |= np.all((points >= lo) & (points <= hi), axis=1)
    inside[:, ~inside.any(axis=0)] = True  # seen by no window's box: every window may answer
    codes = np.packbits(inside, axis=0, bitorder="little")  # (ceil(R / 8), N)
    keys, group = np.unique(codes.T, axis=0, return_inverse=True)
    if keys.shape[0] == 1 and inside[:, 0].all():
        return None
    out = []
    for g in range(keys.shape[0]):
        idx = np.flatnonzero(group.reshape(-1) == g)
        robots = tuple(robot for r, (robot, _) in enumerate(held) if inside[r, idx[0]])
        out.append((robots, idx))
    return out


class TooManyRobots(ValueError):
    """A frame names a robot beyond ``window.max_robots`` (nothing changed)."""


class RobotWindows:
    """The robots' keyframe windows (module docstring). Not thread-safe: the node calls it under its
    state lock, as it does the single window."""

    def __init__(self, config: WindowConfig) -> None:
        self.config = config
        self.on_add: list[KeyframeCallback] = []
        """Called with every keyframe that enters any robot's window."""
        self.on_evict: list[KeyframeCallback] = []
        """Called with every keyframe that leaves any robot's window."""
        self.on_robot: list[RobotCallback] = []
        """Called with ``(robot, window)`` when a robot's window is made (before its first keyframe
        enters it): what is per window (the learned model's cost volume) attaches to it there."""
        self._windows: dict[str, KeyframeWindow] = {}

    # -- the robots ---------------------------------------------------------------------------

    @property
    def robots(self) -> tuple[str, ...]:
        """The robots with a window, in the order they first sent a frame."""
        return tuple(self._windows)

    def window(self, robot: str) -> KeyframeWindow | None:
        """The robot's window (None before its first frame)."""
        return self._windows.get(robot)

    def windows(self) -> tuple[tuple[str, KeyframeWindow], ...]:
        """``(robot, window)`` for every robot, in :attr:`robots` order."""
        return tuple(self._windows.items())

    def counts(self) -> dict[str, int]:
        """Keyframes in each robot's window."""
        return {robot: len(window) for robot, window in self._windows.items()}

    def check_robot(self, robot: str) -> None:
        """Raise :class:`TooManyRobots` when ``robot`` has no window and ``window.max_robots`` robots
        have one already."""
        if robot in self._windows or len(self._windows) < self.config.max_robots:
            return
        names = ", ".join(repr(r) for r in self._windows)
        raise TooManyRobots(
            f"robot {robot!r} would be robot {len(self._windows) + 1} of at most {self.config.max_robots} "
            f"(window.max_robots); robots: {names}"
        )

    def _window_for(self, robot: str) -> KeyframeWindow:
        window = self._windows.get(robot)
        if window is None:
            self.check_robot(robot)
            window = KeyframeWindow(self.config)
            window.on_add.append(self._added)
            window.on_evict.append(self._evicted)
            self._windows[robot] = window
            for callback in self.on_robot:
                callback(robot, window)
        return window

    def _added(self, keyframe: Keyframe) -> None:
        for callback in self.on_add:
            callback(keyframe)

    def _evicted(self, keyframe: Keyframe) -> None:
        for callback in self.on_evict:
            callback(keyframe)

    # -- the single window's interface --------------------------------------------------------

    @property
    def keyframes(self) -> tuple[Keyframe, ...]:
        """Every robot's keyframes: robot by robot (:attr:`robots` order), oldest first in each."""
        if len(self._windows) == 1:
            return next(iter(self._windows.values())).keyframes
        return tuple(k for window in self._windows.values() for k in window.keyframes)

    def robot_keyframes(self, robot: str) -> tuple[Keyframe, ...]:
        """The keyframes of ``robot``'s window, oldest first (none before its first frame)."""
        window = self._windows.get(robot)
        return () if window is None else window.keyframes

    def keyframes_of(self, robots: Iterable[str]) -> tuple[Keyframe, ...]:
        """The keyframes of these robots' windows (in :attr:`robots` order)."""
        wanted = set(robots)
        return tuple(k for robot, window in self._windows.items() if robot in wanted
                     for k in window.keyframes)

    def __len__(self) -> int:
        return sum(len(window) for window in self._windows.values())

    @property
    def nbytes(self) -> int:
        """Bytes held by every robot's keyframes."""
        return sum(window.nbytes for window in self._windows.values())

    def is_keyframe(
        self, camera: str, world_from_cam: np.ndarray, robot: str = ""
    ) -> tuple[bool, float, float]:
        """Would a frame of ``robot``'s ``camera`` at this pose become a keyframe of its window?"""
        window = self._windows.get(robot)
        if window is None:
            return True, math.inf, math.inf
        return window.is_keyframe(camera, world_from_cam)

    def consider(self, frame: Keyframe) -> WindowUpdate:
        """:meth:`KeyframeWindow.consider` in ``frame.robot``'s window (made on its first frame;
        raises :class:`TooManyRobots`, nothing changed, beyond ``window.max_robots``)."""
        return self._window_for(frame.robot).consider(frame)

    def replace(self, keyframes: Iterable[Keyframe]) -> tuple[tuple[Keyframe, ...], tuple[Keyframe, ...]]:
        """Swap the whole content (a loaded map): each robot's window takes its robot's keyframes
        (its newest ``max_keyframes``). Returns ``(removed, added)``. Raises :class:`TooManyRobots`
        (nothing changed) when they name more robots than ``window.max_robots`` allows."""
        by_robot: dict[str, list[Keyframe]] = {}
        for keyframe in keyframes:
            by_robot.setdefault(keyframe.robot, []).append(keyframe)
        new = [r for r in by_robot if r not in self._windows]
        if len(self._windows) + len(new) > self.config.max_robots:
            raise TooManyRobots(
                f"the keyframes name {len(by_robot)} robots ({', '.join(repr(r) for r in by_robot)}); "
                f"with the node's robots {list(self._windows)} more than window.max_robots = "
                f"{self.config.max_robots}"
            )
        removed = self.clear()
        added: list[Keyframe] = []
        for robot, group in by_robot.items():
            added += self._window_for(robot).replace(group)[1]
        return removed, tuple(added)

    def swap(self, old: Keyframe, new: Keyframe) -> bool:
        """:meth:`KeyframeWindow.swap` in ``old``'s robot's window."""
        window = self._windows.get(old.robot)
        return window is not None and window.swap(old, new)

    def clear(self) -> tuple[Keyframe, ...]:
        """Remove every robot's keyframes (the robots keep their empty windows); returns them."""
        return tuple(k for window in self._windows.values() for k in window.clear())
