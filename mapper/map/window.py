"""The bounded keyframe window: which frames the node keeps, and hooks for incremental updates.

A frame becomes a keyframe when its camera moved (translation of the camera centre) or turned
(angle of the relative rotation) enough since the most recent keyframe *of the same camera*:
comparing across the cameras of a rig would turn every frame into a keyframe. The first frame of
each camera is always a keyframe. Beyond ``max_keyframes`` the oldest keyframe (in arrival order)
is evicted.

Later stages keep derived state in step with the window without rebuilding it: the incremental
cost volume and the OV cache register ``on_add`` / ``on_evict`` callbacks (called under the
node's state lock, in order: the new keyframe's ``on_add`` first, then ``on_evict`` for each
evicted keyframe), and :meth:`KeyframeWindow.consider` also returns what changed.

Example::

    >>> import numpy as np
    >>> window = KeyframeWindow(WindowConfig(max_keyframes=2, min_translation_m=0.1, min_rotation_deg=10))
    >>> def kf(seq, x):
    ...     world_from_cam = np.eye(4); world_from_cam[0, 3] = x
    ...     return Keyframe(seq=seq, stamp_ns=seq, camera="cam0", K=np.array([100.0, 100.0, 80.0, 60.0]),
    ...                     world_from_cam=world_from_cam, rgb=np.zeros((120, 160, 3), np.uint8))
    >>> [window.consider(kf(i, x)).added for i, x in enumerate([0.0, 0.05, 0.2, 0.4])]
    [True, False, True, True]
    >>> [k.seq for k in window.keyframes]
    [2, 3]
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from mapper.checks import check_range as _check_range
from mapper.errors import ConfigError


@dataclass(frozen=True)
class WindowConfig:
    """The bounded window of keyframes (see :mod:`mapper.map.window`)."""

    max_keyframes: int = 30
    """Most keyframes kept (per robot: each robot has its own window, ``max_robots``); adding one
    more evicts the oldest. 1..10000."""

    min_translation_m: float = 0.10
    """A frame becomes a keyframe when its camera centre moved at least this far (metres) from the
    most recent keyframe of the same camera. >= 0."""

    min_rotation_deg: float = 10.0
    """... or when its viewing direction turned by at least this angle (degrees, the angle of the
    relative rotation) from that keyframe. 0..180."""

    max_image_side: int = 1280
    """A keyframe whose image is larger is kept shrunk to this many pixels on its longer side
    (colour by area, depth by nearest sample, K scaled with it; ``ov`` as sent): a window of 30
    keyframes of 4096 x 4096 frames with depth would hold 3.5 GB, and the global map integrates
    every second depth pixel. Frames up to this size are kept as sent. 0 = always as sent. 0..4096."""

    max_ov_cells: int = 4800
    """A keyframe whose OV map has more cells is kept with it area-averaged to at most this many (80 x
    60 at 4:3; the aspect and dtype kept). The learned model blends OV maps on its own grid (the
    working size / 4: 40 x 30 for ``cpu-small``), the averaging and the map sample them bilinearly:
    a 640 x 480 camera's 384-d features at 1/4 resolution (160 x 120, 14.7 MB in float16) are kept
    at 3.7 MB. 0 = always as sent. 0..10000000."""

    max_robots: int = 4
    """Most robots (the frames' ``robot`` names; "" the default robot counts once it sent a frame),
    each with a window of its own of up to ``max_keyframes`` keyframes
    (:mod:`mapper.map.robot_windows`); a frame naming one robot more is refused (``bad_request``).
    1..64."""

    def validate(self, where: str) -> None:
        _check_range(where, "window.max_keyframes", self.max_keyframes, 1, 10_000)
        _check_range(where, "window.max_robots", self.max_robots, 1, 64)
        _check_range(where, "window.max_image_side", self.max_image_side, 0, 4096)
        _check_range(where, "window.max_ov_cells", self.max_ov_cells, 0, 10_000_000)
        if 0 < self.max_image_side < 16:
            raise ConfigError(f"{where}: window.max_image_side = {self.max_image_side} must be 0 or >= 16")
        _check_range(where, "window.min_translation_m", self.min_translation_m, 0.0, 1e6)
        _check_range(where, "window.min_rotation_deg", self.min_rotation_deg, 0.0, 180.0)


@dataclass(frozen=True, eq=False)
class Keyframe:
    """One posed frame kept by the node. Its arrays are exposed as read-only views."""

    seq: int
    """Sender's sequence number."""
    stamp_ns: int
    """Capture time, nanoseconds."""
    camera: str
    """Camera name (keyframe selection is per camera)."""
    K: np.ndarray
    """(4,) float64 intrinsics [fx, fy, cx, cy] in pixels of ``rgb``."""
    world_from_cam: np.ndarray
    """(4, 4) float64 camera-to-world pose, OpenCV optical camera frame, metres."""
    rgb: np.ndarray
    """(H, W, 3) uint8 colour image."""
    depth_m: np.ndarray | None = None
    """(H, W) float32 metric depth along +z; 0 or non-finite = no depth. None if not sent."""
    ov: np.ndarray | None = None
    """(h, w, d) float16/float32 open-vocabulary feature map at its own resolution, or None."""
    ov_space: str | None = None
    """Embedding space of ``ov`` (e.g. "minilm-l6-v2"); None when ``ov`` is None."""
    robot: str = ""
    """Robot name (the frame's ``robot``; "" the default robot): each robot has its own window
    (:class:`mapper.map.robot_windows.RobotWindows`)."""

    def __post_init__(self) -> None:
        for name in ("K", "world_from_cam", "rgb", "depth_m", "ov"):
            array = getattr(self, name)
            if isinstance(array, np.ndarray) and array.flags.writeable:
                view = array.view()  # a read-only view: no copy, and no mutation through the keyframe
                view.setflags(write=False)
                object.__setattr__(self, name, view)

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def nbytes(self) -> int:
        """Bytes held by the keyframe's arrays."""
        return sum(
            a.nbytes for a in (self.K, self.world_from_cam, self.rgb, self.depth_m, self.ov) if a is not None
        )


def pose_change(
    world_from_a: np.ndarray,  # (4, 4)
    world_from_b: np.ndarray,  # (4, 4)
) -> tuple[float, float]:
    """Distance between the camera centres (metres) and angle of the relative rotation (degrees)."""
    translation_m = float(np.linalg.norm(world_from_b[:3, 3] - world_from_a[:3, 3]))
    a_from_b = world_from_a[:3, :3].T @ world_from_b[:3, :3]
    cos_angle = (float(np.trace(a_from_b)) - 1.0) / 2.0
    rotation_deg = math.degrees(math.acos(min(1.0, max(-1.0, cos_angle))))
    return translation_m, rotation_deg


@dataclass(frozen=True)
class WindowUpdate:
    """What :meth:`KeyframeWindow.consider` did with a frame."""

    added: bool
    """True when the frame became a keyframe."""
    evicted: tuple[Keyframe, ...]
    """Keyframes that left the window because of it (oldest first)."""
    translation_m: float
    """Camera-centre distance to the previous keyframe of that camera (inf for the first)."""
    rotation_deg: float
    """Relative rotation angle to that keyframe (inf for the first)."""


KeyframeCallback = Callable[[Keyframe], None]


def fit_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """(w, h) of a ``width x height`` image kept at most ``max_side`` on its longer side (itself
    when it fits or ``max_side`` is 0)."""
    if max_side <= 0 or max(width, height) <= max_side:
        return width, height
    shrink = max_side / max(width, height)
    return max(1, round(width * shrink)), max(1, round(height * shrink))


def fit_intrinsics(K: np.ndarray, width: int, height: int, max_side: int) -> np.ndarray:
    """(4,) float64 ``K`` of that image kept at :func:`fit_size` (pixel edges kept)."""
    nw, nh = fit_size(width, height, max_side)
    return np.asarray(K, np.float64) * np.array([nw / width, nh / height, nw / width, nh / height])


def fit_image(keyframe: Keyframe, max_side: int) -> Keyframe:
    """``keyframe`` with its images shrunk to at most ``max_side`` pixels on the longer side
    (``window.max_image_side``): colour by area, depth by nearest sample (no depth mixed across an
    edge), K scaled with the image (pixel edges kept: ``u -> u * W' / W``); ``ov`` and the pose as
    they are. The keyframe itself when it fits, ``max_side`` is 0, or OpenCV (an extra) is missing.

    >>> kf = Keyframe(seq=0, stamp_ns=0, camera="cam0", K=np.array([2000.0, 2000.0, 2048.0, 1536.0]),
    ...               world_from_cam=np.eye(4), rgb=np.zeros((3072, 4096, 3), np.uint8))
    >>> small = fit_image(kf, 1280)
    >>> small.width, small.height, small.K.tolist()
    (1280, 960, [625.0, 625.0, 640.0, 480.0])
    """
    h, w = keyframe.height, keyframe.width
    nw, nh = fit_size(w, h, max_side)
    if (nw, nh) == (w, h):
        return keyframe
    try:
        import cv2  # an extra (the node core imports without it); only frames larger than max_side
    except ImportError:  # a core-only install keeps large frames as sent
        return keyframe
    rgb = cv2.resize(np.asarray(keyframe.rgb), (nw, nh), interpolation=cv2.INTER_AREA)
    depth = keyframe.depth_m
    if depth is not None:
        depth = cv2.resize(np.asarray(depth), (nw, nh), interpolation=cv2.INTER_NEAREST)
    K = fit_intrinsics(keyframe.K, w, h, max_side)
    return dataclasses.replace(keyframe, K=K, rgb=rgb, depth_m=depth)


def fit_ov(keyframe: Keyframe, max_cells: int) -> Keyframe:
    """``keyframe`` with its OV map area-averaged to at most ``max_cells`` cells
    (``window.max_ov_cells``; :func:`mapper.map.evicted_frames.reduce_ov`, the aspect and the
    dtype kept); the keyframe itself when it has none, it fits, or ``max_cells`` is 0.

    >>> kf = Keyframe(seq=0, stamp_ns=0, camera="cam0", K=np.array([500.0, 500.0, 320.0, 240.0]),
    ...               world_from_cam=np.eye(4), rgb=np.zeros((480, 640, 3), np.uint8),
    ...               ov=np.ones((120, 160, 8), np.float16))
    >>> small = fit_ov(kf, 4800)
    >>> small.ov.shape, small.ov.dtype.name, float(small.ov.max())
    ((60, 80, 8), 'float16', 1.0)
    """
    ov = keyframe.ov
    if ov is None or max_cells <= 0 or ov.shape[0] * ov.shape[1] <= max_cells:
        return keyframe
    from mapper.map.evicted_frames import as_dtype, reduce_ov

    return dataclasses.replace(keyframe, ov=as_dtype(reduce_ov(np.asarray(ov), max_cells), ov.dtype))


@dataclass
class KeyframeWindow:
    """A bounded, ordered set of keyframes selected by pose change. Not thread-safe: the node
    calls it under its state lock."""

    config: WindowConfig
    on_add: list[KeyframeCallback] = field(default_factory=list)
    """Called with every keyframe that enters the window (including on :meth:`replace`)."""
    on_evict: list[KeyframeCallback] = field(default_factory=list)
    """Called with every keyframe that leaves the window (eviction, :meth:`replace`, :meth:`clear`)."""
    _keyframes: list[Keyframe] = field(default_factory=list, init=False, repr=False)
    _last_by_camera: dict[str, Keyframe] = field(default_factory=dict, init=False, repr=False)

    @property
    def keyframes(self) -> tuple[Keyframe, ...]:
        """The keyframes, oldest first."""
        return tuple(self._keyframes)

    def __len__(self) -> int:
        return len(self._keyframes)

    @property
    def nbytes(self) -> int:
        """Bytes held by all keyframes' arrays."""
        return sum(k.nbytes for k in self._keyframes)

    def is_keyframe(self, camera: str, world_from_cam: np.ndarray) -> tuple[bool, float, float]:
        """Would a frame of ``camera`` at this (4, 4) pose become a keyframe? Returns
        ``(decision, translation_m, rotation_deg)`` relative to that camera's latest keyframe."""
        last = self._last_by_camera.get(camera)
        if last is None:
            return True, math.inf, math.inf
        translation_m, rotation_deg = pose_change(last.world_from_cam, world_from_cam)
        decision = (
            translation_m >= self.config.min_translation_m or rotation_deg >= self.config.min_rotation_deg
        )
        return decision, translation_m, rotation_deg

    def consider(self, frame: Keyframe) -> WindowUpdate:
        """Add ``frame`` if it moved or turned enough; evict the oldest keyframes beyond the bound."""
        decision, translation_m, rotation_deg = self.is_keyframe(frame.camera, frame.world_from_cam)
        if not decision:
            return WindowUpdate(False, (), translation_m, rotation_deg)
        evicted = self._append(frame)
        return WindowUpdate(True, evicted, translation_m, rotation_deg)

    def replace(self, keyframes: Iterable[Keyframe]) -> tuple[tuple[Keyframe, ...], tuple[Keyframe, ...]]:
        """Swap the whole content (e.g. a loaded map). Returns ``(removed, added)``; when more than
        ``max_keyframes`` are given only the newest are kept. Callbacks fire for every change."""
        removed = self.clear()
        new = list(keyframes)[-self.config.max_keyframes :]
        for keyframe in new:
            self._append(keyframe)
        return removed, tuple(new)

    def swap(self, old: Keyframe, new: Keyframe) -> bool:
        """Put ``new`` in ``old``'s place (same position; e.g. ``old`` with features added later).
        ``on_evict(old)`` then ``on_add(new)`` fire; nothing else changes. Returns False (and does
        nothing) when ``old`` is no longer in the window."""
        for i, keyframe in enumerate(self._keyframes):
            if keyframe is old:
                self._keyframes[i] = new
                if self._last_by_camera.get(old.camera) is old:
                    self._last_by_camera[old.camera] = new
                for callback in self.on_evict:
                    callback(old)
                for callback in self.on_add:
                    callback(new)
                return True
        return False

    def clear(self) -> tuple[Keyframe, ...]:
        """Remove every keyframe (``on_evict`` fires for each); returns them."""
        removed = tuple(self._keyframes)
        self._keyframes.clear()
        self._last_by_camera.clear()
        for keyframe in removed:
            for callback in self.on_evict:
                callback(keyframe)
        return removed

    def _append(self, keyframe: Keyframe) -> tuple[Keyframe, ...]:
        self._keyframes.append(keyframe)
        self._last_by_camera[keyframe.camera] = keyframe
        for callback in self.on_add:
            callback(keyframe)
        evicted: list[Keyframe] = []
        while len(self._keyframes) > self.config.max_keyframes:
            old = self._keyframes.pop(0)
            evicted.append(old)
            for callback in self.on_evict:
                callback(old)
        # The latest keyframe of a camera is never evicted while newer ones of other cameras stay,
        # unless the window is smaller than the number of cameras; keep the reference anyway so
        # selection stays relative to the last keyframe that camera produced.
        return tuple(evicted)


# --------------------------------------------------------------------------------------------
# (de)serialisation for mapper.node.store: numeric arrays + a JSON-able manifest section, no pickle

_ARRAY_FIELDS = ("K", "world_from_cam", "rgb", "depth_m", "ov")


def keyframes_to_arrays(
    keyframes: Iterable[Keyframe], prefix: str = "kf"
) -> tuple[dict[str, np.ndarray], list[dict[str, object]]]:
    """Flatten keyframes into ``{"kf.<i>.<field>": array}`` and a manifest list of their scalars."""
    arrays: dict[str, np.ndarray] = {}
    entries: list[dict[str, object]] = []
    for i, keyframe in enumerate(keyframes):
        for name in _ARRAY_FIELDS:
            value = getattr(keyframe, name)
            if value is not None:
                arrays[f"{prefix}.{i}.{name}"] = np.ascontiguousarray(value)
        entry: dict[str, object] = {
            "seq": keyframe.seq,
            "stamp_ns": keyframe.stamp_ns,
            "camera": keyframe.camera,
            "ov_space": keyframe.ov_space,
        }
        if keyframe.robot:  # the default robot's keyframes are saved as before robots existed
            entry["robot"] = keyframe.robot
        entries.append(entry)
    return arrays, entries


def keyframes_from_arrays(
    arrays: dict[str, np.ndarray], entries: object, prefix: str = "kf"
) -> list[Keyframe]:
    """Inverse of :func:`keyframes_to_arrays`; checks shapes and dtypes, raising ``ValueError``
    with the offending keyframe index and field (a map file can be damaged or hand-made)."""
    if not isinstance(entries, list):
        raise ValueError(f"keyframe list must be a list, got {type(entries).__name__}")
    keyframes: list[Keyframe] = []
    for i, entry in enumerate(entries):
        where = f"keyframe {i}"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: manifest entry must be a mapping")
        seq, stamp_ns, camera, ov_space = (entry.get(k) for k in ("seq", "stamp_ns", "camera", "ov_space"))
        if not isinstance(seq, int) or not isinstance(stamp_ns, int) or not isinstance(camera, str):
            raise ValueError(f"{where}: seq/stamp_ns must be int and camera str, got {entry!r}")
        if ov_space is not None and not isinstance(ov_space, str):
            raise ValueError(f"{where}: ov_space must be a string or null, got {ov_space!r}")
        robot = entry.get("robot", "")
        if not isinstance(robot, str) or len(robot) > 64:
            raise ValueError(f"{where}: robot must be a string of at most 64 characters, got {robot!r}")
        got = {name: arrays.get(f"{prefix}.{i}.{name}") for name in _ARRAY_FIELDS}
        K, world_from_cam, rgb, depth_m, ov = (got[name] for name in _ARRAY_FIELDS)
        if K is None or K.shape != (4,) or not np.isfinite(K).all():
            raise ValueError(f"{where}: K must be 4 finite numbers")
        if world_from_cam is None or world_from_cam.shape != (4, 4) or not np.isfinite(world_from_cam).all():
            raise ValueError(f"{where}: world_from_cam must be a finite 4x4 matrix")
        if rgb is None or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"{where}: rgb must be uint8 (H, W, 3)")
        if depth_m is not None and (depth_m.dtype != np.float32 or depth_m.shape != rgb.shape[:2]):
            raise ValueError(
                f"{where}: depth_m must be float32 {rgb.shape[:2]}, got {depth_m.dtype} {depth_m.shape}"
            )
        if ov is not None and (ov.dtype not in (np.float16, np.float32) or ov.ndim != 3 or ov_space is None):
            raise ValueError(f"{where}: ov must be float16/float32 (h, w, d) with an ov_space")
        keyframes.append(
            Keyframe(
                seq=seq,
                stamp_ns=stamp_ns,
                camera=camera,
                K=K.astype(np.float64),
                world_from_cam=world_from_cam.astype(np.float64),
                rgb=rgb,
                depth_m=depth_m,
                ov=ov,
                ov_space=ov_space if ov is not None else None,
                robot=robot,
            )
        )
    return keyframes
