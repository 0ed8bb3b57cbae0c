"""Sparse geometry for RGB-only keyframes: points triangulated from posed RGB, off the ack path.

A robot without a depth camera sends frames without ``depth_m``. :class:`SparseTriangulation`
triangulates each such keyframe against a few earlier keyframes with the pure geometry of
:mod:`mapper.geometry.triangulation` (features, partners by frustum overlap and baseline, epipolar
filtering from the known poses, ``cv2.triangulatePoints``, cheirality / reprojection / parallax /
multi-view checks, an uncertainty per point) and uses the points three ways:

* **sparse map**: kept per keyframe, bounded by ``triangulation.max_points`` (the oldest
  keyframes' points go first); :meth:`SparseTriangulation.points` returns them all;
* **volume bounds**: with a learned-model runtime, a keyframe's extent for the cost volume's
  bounds becomes its points (``ModelRuntime.set_view_extent``, with at least
  ``bounds_min_points``; fewer: its frustum up to the depth recent keyframes' points reach)
  instead of its frustum up to the fixed ``model.max_range_m``: the volume grows (or shrinks)
  with the room, within the voxel budget;
* **sparse depth prior**: with a runtime, each keyframe's points splatted into a sparse depth map
  (``depth_prior_radius_px``; ``ModelRuntime.set_view_depth_prior``) for Depth-Guided-Masking-like
  view masking in ``segment_points`` with ``use_depth`` where the points exist;
* **global map**: the points are fused into the global semantic map with the keyframe's OV
  features (a sparse depth map through the map's public ``integrate``), at
  ``global_map_weight`` times a confidence that falls with the uncertainty.

With ``triangulation.refine_poses`` the keyframe's pose is first refined against the points its
partners triangulated (:mod:`mapper.node.workers.pose_refinement`); its triangulation, sweep, map
points and priors then use the refined pose, and later keyframes take it as a partner at that pose
(the window, the ack and a saved map keep the pose as sent; ``status``: ``triangulation.poses``).

Then **plane-sweep stereo** (``[stereo]``, :mod:`mapper.geometry.plane_sweep`): the keyframe is swept
against the best ``stereo.max_sources`` of the same partners (at most ``stereo.max_width`` wide,
depth range from its triangulated points); depths that a partner's own depth confirms join the
global map (``stereo.global_map_weight``), are kept as points with a relative sigma for the
rendered-depth points' consistency check (:meth:`SparseTriangulation.geometry_points`), and, filled
along the image, become the runtime's depth prior. With more than ``stereo.max_backlog`` keyframes
waiting the sweep is put off (the worker keeps up with the sparse geometry) and done later, oldest
first, whenever no keyframe waits (``stereo.max_deferred`` remembered; ``pending`` counts them, so
the node is not settled before they are swept). Points added before
the in-process OV backend encoded their keyframe get its features later
(``node.feature_listeners`` -> :meth:`SparseTriangulation.on_features`).

Scheduling: :meth:`SparseTriangulation.on_keyframe` runs on the keyframe-listener thread
(integrator; ingest when integration is inline) after the keyframe entered the window and only
queues it (O(1)); the worker (``mapper-triangulation``) detects, matches and triangulates. The
features of the last ``candidate_keyframes`` keyframes (with or without depth) stay in memory as
partner candidates; a map load clears them and the sparse map at once (``node.load_listeners``:
nothing of the replaced map is held or reported after the load returns), and keyframes acked before
the load that the worker meets later are skipped (counted in ``stale``). The loaded window's
keyframes are then queued again (``restored``): the worker makes their candidates, sparse points,
volume extents, swept depths and depth priors as it did before the save, without fusing their
points into the global map a second time (the loaded map holds them), so a map loaded after a
restart continues with the geometry the live node had. Beyond ``max_pending``
waiting keyframes the oldest is dropped and counted. Errors never reach the listener thread: they
are logged (rate limited) and counted in ``failed``.

Example (in-process; ``node`` a :class:`mapper.node.service.MapperNode`)::

    tri = SparseTriangulation(node)
    tri.install()            # listener + worker + status "triangulation"
    ...                      # frames without depth arrive
    tri.process_pending()    # or let the worker do it; returns keyframes triangulated
    xyz, sigma = tri.points()
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import cv2
import numpy as np

from mapper.geometry.config import StereoConfig, TriangulationConfig
from mapper.geometry.plane_sweep import (
    DenseDepth,
    StereoView,
    agreeing_views,
    depth_range,
    fill_depth,
    gray_image,
    sweep_depth,
)
from mapper.geometry.triangulation import (
    FeatureExtractor,
    Features,
    PosedView,
    SparsePoints,
    backproject,
    frustum_points,
    select_partners,
    triangulate_keyframe,
)
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker, with_current_features
from mapper.node.workers.pose_refinement import KeyframePoses

if TYPE_CHECKING:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.context import NodeContext
    from mapper.node.service import MapperNode

__all__ = ["SparseTriangulation", "TriangulatedKeyframe", "install_triangulation", "keyframe_key"]

log = logging.getLogger("mapper.node.workers.triangulation")

KeyframeKey = tuple[str, int, int]
T = TypeVar("T")


class ExtentSink(Protocol):
    """What the plugin needs of the learned-model runtime (``ModelRuntime.set_view_extent``)."""

    def set_view_extent(self, key: KeyframeKey, points_m: np.ndarray | None) -> None: ...

    def set_view_depth_prior(self, key: KeyframeKey, depth_m: np.ndarray | None) -> None: ...


def keyframe_key(keyframe: Any) -> KeyframeKey:
    """``(camera, seq, stamp_ns)``: a keyframe's identity that survives a swap in the window; a
    named robot's camera is ``"<robot>/<camera>"`` (two robots' frames may share seq and stamp)."""
    camera, robot = str(getattr(keyframe, "camera", "")), str(getattr(keyframe, "robot", ""))
    return (f"{robot}/{camera}" if robot else camera, int(keyframe.seq), int(keyframe.stamp_ns))


@dataclass(frozen=True)
class TriangulatedKeyframe:
    """A keyframe's triangulated points as a sparse depth map, shaped like ``KeyframeLike``."""

    stamp_ns: int
    K: np.ndarray  # (4,) [fx, fy, cx, cy] of the keyframe
    world_from_cam: np.ndarray  # (4, 4)
    rgb: np.ndarray  # (H, W, 3) uint8 the keyframe's image (the map uses its shape)
    depth_m: np.ndarray  # (H, W) float32 z-depth at the points' pixels, 0 elsewhere
    ov: np.ndarray | None  # (h_ov, w_ov, D) the keyframe's OV map
    confidence: np.ndarray  # (H, W) float32 in [0, 1]


def sparse_depth_keyframe(
    keyframe: Any, points: SparsePoints, config: TriangulationConfig
) -> TriangulatedKeyframe:
    """The points as a sparse depth map of ``keyframe`` (the most certain point per pixel)."""
    height, width = keyframe.rgb.shape[:2]
    depth = np.zeros((height, width), np.float32)
    conf = np.zeros((height, width), np.float32)
    cols = np.clip(np.floor(points.uv[:, 0]).astype(np.int64), 0, width - 1)
    rows = np.clip(np.floor(points.uv[:, 1]).astype(np.int64), 0, height - 1)
    order = np.argsort(-points.sigma_m)  # least certain first: the most certain is written last
    certainty = np.clip(1.0 - points.sigma_m / config.max_sigma_m, 0.1, 1.0)
    depth[rows[order], cols[order]] = points.depth_m[order]
    conf[rows[order], cols[order]] = config.global_map_weight * certainty[order]
    return TriangulatedKeyframe(
        stamp_ns=int(keyframe.stamp_ns), K=np.asarray(keyframe.K, np.float64),
        world_from_cam=np.asarray(keyframe.world_from_cam, np.float64), rgb=keyframe.rgb,
        depth_m=depth, ov=keyframe.ov, confidence=conf,
    )


def depth_prior(sparse: TriangulatedKeyframe, radius_px: int) -> np.ndarray:
    """(H, W) float32: the sparse depth splatted over discs of ``radius_px`` (max where they meet)."""
    if radius_px <= 0:
        return sparse.depth_m
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
    return np.asarray(cv2.dilate(sparse.depth_m, kernel), np.float32)


@dataclass
class _Candidate:
    """A recent keyframe as a partner candidate; its features are detected on first use (keyframes
    with depth are never triangulated, so their features are only computed when chosen)."""

    key: KeyframeKey
    view: PosedView
    rgb: np.ndarray | None  # (H, W, 3) uint8 until the features are detected
    features: Features | None = None
    stereo: _StereoImage | None = None  # its image (and depth) at the sweep's working size
    points: tuple[np.ndarray, np.ndarray] | None = None  # its triangulated keypoints: (feature index, xyz)
    robot: str = ""  # partners are the same robot's recent keyframes

    def detected(self, extractor: FeatureExtractor) -> Features:
        if self.features is None:
            assert self.rgb is not None
            self.features = extractor.detect(np.asarray(self.rgb))
            self.rgb = None
        return self.features


class _RobotCandidates:
    """Partner candidates by robot: each robot's ``maxlen`` most recent keyframes (a keyframe's
    partners are its own robot's); ``len`` and iteration cover every robot's."""

    def __init__(self, maxlen: int) -> None:
        self.maxlen = maxlen
        self._by_robot: dict[str, deque[_Candidate]] = {}

    def append(self, candidate: _Candidate) -> None:
        self._by_robot.setdefault(candidate.robot, deque(maxlen=self.maxlen)).append(candidate)

    def of(self, robot: str) -> list[_Candidate]:
        return list(self._by_robot.get(robot, ()))

    def clear(self) -> None:
        self._by_robot.clear()

    def __len__(self) -> int:
        return sum(len(d) for d in self._by_robot.values())

    def __iter__(self) -> Iterator[_Candidate]:
        return (c for d in list(self._by_robot.values()) for c in list(d))


@dataclass
class _StereoImage:
    """A keyframe at the plane sweep's working size (``stereo.max_width``)."""

    view: StereoView  # K scaled to the working size, gray (h, w) float32
    depth_m: np.ndarray | None  # (h, w) float32: its input depth, or its swept depth; None = neither


def stereo_image(keyframe: Any, config: StereoConfig) -> _StereoImage:
    """``keyframe`` (rgb, K, pose, optional depth) at the sweep's working size."""
    rgb = np.asarray(keyframe.rgb)
    height, width = rgb.shape[:2]
    K = np.asarray(keyframe.K, np.float64)
    gray = gray_image(rgb)
    depth = None if keyframe.depth_m is None else np.asarray(keyframe.depth_m, np.float32)
    if width > config.max_width:
        w = config.max_width
        h = max(1, round(height * w / width))
        gray = np.asarray(cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA), np.float32)
        K = K * np.array([w / width, h / height, w / width, h / height])
        if depth is not None:
            depth = np.asarray(cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST), np.float32)
    elif depth is not None and depth.shape != gray.shape:
        size = (gray.shape[1], gray.shape[0])
        depth = np.asarray(cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST), np.float32)
    view = StereoView(K, np.asarray(keyframe.world_from_cam, np.float64), gray)
    return _StereoImage(view, depth)


def swept_keyframe(
    keyframe: Any, dense: DenseDepth, keep: np.ndarray, config: StereoConfig
) -> TriangulatedKeyframe:
    """The kept swept depths as a depth map of ``keyframe`` (full size, nearest pixel, its OV
    features) with a confidence of ``global_map_weight`` times the score above ``min_ncc``
    (normalised, >= 0.1)."""
    min_ncc = config.min_ncc
    height, width = keyframe.rgb.shape[:2]
    depth = np.where(keep, dense.depth_m, 0.0).astype(np.float32)
    certainty = np.clip((dense.score - min_ncc) / max(1e-6, 1.0 - min_ncc), 0.1, 1.0)
    conf = np.where(keep, config.global_map_weight * certainty, 0.0).astype(np.float32)
    if depth.shape != (height, width):
        depth = np.asarray(cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST), np.float32)
        conf = np.asarray(cv2.resize(conf, (width, height), interpolation=cv2.INTER_NEAREST), np.float32)
    return TriangulatedKeyframe(
        stamp_ns=int(keyframe.stamp_ns), K=np.asarray(keyframe.K, np.float64),
        world_from_cam=np.asarray(keyframe.world_from_cam, np.float64), rgb=keyframe.rgb,
        depth_m=depth, ov=keyframe.ov, confidence=conf,
    )


@dataclass
class _DeferredSweep:
    """A sweep put off while the worker was busy (``stereo.max_backlog``): what it needs later."""

    keyframe: Any  # as triangulated (the refined pose where refine_poses moved it)
    image: _StereoImage
    partners: list[_Candidate]
    points: SparsePoints
    target: GlobalSemanticMap  # the map it belongs to
    generation: int  # the triangulation's generation when it was put off (a load forgets it)
    restored: bool  # a keyframe of a loaded window: its points are in the map already

    @property
    def nbytes(self) -> int:
        """What it keeps alive: its keyframe's colour and OV map, and its working image."""
        kf, image = self.keyframe, self.image
        held = int(np.asarray(kf.rgb).nbytes) + (0 if kf.ov is None else int(np.asarray(kf.ov).nbytes))
        held += image.view.gray.nbytes + (0 if image.depth_m is None else image.depth_m.nbytes)
        return held


class _DeferredSweeps:
    """The sweeps put off while the worker was busy, oldest first (``stereo.max_deferred``,
    ``stereo.max_deferred_mb``), what they hold and their counts. Called with the triangulation's
    lock held."""

    def __init__(self, config: StereoConfig) -> None:
        self.config = config
        self.items: deque[_DeferredSweep] = deque()
        self.nbytes = 0
        self.sweeping = 0  # 1 while a taken one is being swept (``pending`` counts it)
        self.swept = 0
        self.forgotten = 0

    def __len__(self) -> int:
        return len(self.items) + self.sweeping

    def put(self, item: _DeferredSweep) -> None:
        """Remember ``item``; beyond ``max_deferred`` or ``max_deferred_mb`` the oldest is forgotten."""
        if self.config.max_deferred <= 0:
            self.forgotten += 1
            return
        self.items.append(item)
        self.nbytes += item.nbytes
        budget = self.config.max_deferred_mb * 2**20
        while self.items and (len(self.items) > self.config.max_deferred or self.nbytes > budget):
            self.nbytes -= self.items.popleft().nbytes
            self.forgotten += 1

    def take(self) -> _DeferredSweep | None:
        """The oldest, now being swept (:meth:`done` when finished), or None."""
        if not self.items:
            return None
        item = self.items.popleft()
        self.nbytes -= item.nbytes
        self.sweeping = 1
        return item

    def done(self, swept: bool) -> None:
        self.sweeping = 0
        self.swept += int(swept)
        self.forgotten += int(not swept)

    def forget_all(self) -> None:
        self.forgotten += len(self.items)
        self.items.clear()
        self.nbytes = 0

    def stats(self) -> dict[str, int]:
        return {"deferred": len(self), "deferred_swept": self.swept, "deferred_forgotten": self.forgotten}


class _VolumeExtents:
    """Each keyframe's extent for the learned model's volume bounds: its triangulated points, or,
    with too few, its frustum up to the room's depth (the median of recent keyframes' far point
    depth; keyframes seen before any is known wait for it)."""

    def __init__(self, runtime: ExtentSink, config: TriangulationConfig) -> None:
        self.runtime = runtime
        self.config = config
        self.room_depths: deque[float] = deque(maxlen=config.candidate_keyframes)
        self._waiting: deque[tuple[KeyframeKey, PosedView]] = deque(maxlen=config.candidate_keyframes)

    def set(self, key: KeyframeKey, view: PosedView, points: SparsePoints) -> None:
        if len(points) >= self.config.bounds_min_points:
            self.runtime.set_view_extent(key, points.xyz)
            first = not self.room_depths
            self.room_depths.append(float(np.quantile(points.depth_m, self.config.bounds_depth_quantile)))
            if first:  # the keyframes seen before any depth was known get the room's depth now
                while self._waiting:
                    self._frustum(*self._waiting.popleft())
            return
        if self.room_depths:
            self._frustum(key, view)
        else:
            self._waiting.append((key, view))

    def _frustum(self, key: KeyframeKey, view: PosedView) -> None:
        far = float(np.median(self.room_depths))
        near = min(self.config.min_depth_m, 0.5 * far)
        self.runtime.set_view_extent(key, frustum_points(view, near, far))

    def clear(self) -> None:
        self.room_depths.clear()
        self._waiting.clear()


class _LateFeatures:
    """Map points added for keyframes that had no OV features yet (a robot without onboard OV, the
    node's OV backend encoding them later): their depth maps, kept (``ov_backend.max_pending``
    keyframes at most) until the features arrive, then fused into those points."""

    def __init__(self, ctx: NodeContext, lock: threading.Lock,
                 failed: Callable[[Any, BaseException], None]) -> None:
        self.ctx = ctx
        self._lock = lock
        self._failed = failed
        self.pending: OrderedDict[KeyframeKey, tuple[GlobalSemanticMap, list[TriangulatedKeyframe]]] = (
            OrderedDict()
        )  # guarded by ``lock``
        self.points = 0

    def remember(self, keyframe: Any, depth: TriangulatedKeyframe, target: GlobalSemanticMap) -> None:
        with self._lock:
            entry = self.pending.setdefault(keyframe_key(keyframe), (target, []))
            entry[1].append(depth)
            while len(self.pending) > max(1, self.ctx.config.ov_backend.max_pending):
                self.pending.popitem(last=False)  # the backend drops beyond this many too
        current = with_current_features(self.ctx, keyframe)  # swapped in meanwhile: listener too early
        if current.ov is not None:
            self.on_features(current)

    def on_features(self, keyframe: Any) -> None:
        """``keyframe`` got its OV features: fuse them into the points kept for it. Never raises."""
        with self._lock:
            entry = self.pending.pop(keyframe_key(keyframe), None)
        if entry is None or keyframe.ov is None:
            return
        target, depths = entry
        if target is not self.ctx.state.global_map:
            return  # a load replaced that map
        for depth in depths:
            try:
                stats = target.integrate_features(replace(depth, ov=keyframe.ov), pixel_stride=1,
                                                  confidence=depth.confidence)
            except (ValueError, RuntimeError) as exc:
                self._failed(keyframe, exc)
                continue
            self.points += stats.points


class _KeyframeBudget(Generic[T]):
    """Per-keyframe items (newest last) whose sizes sum to at most ``budget``: beyond it the oldest
    keyframes' items go first, but a keyframe's own item is never split or dropped for itself."""

    def __init__(self, budget: int, size: Callable[[T], int]) -> None:
        self.budget = budget
        self._size = size
        self.items: OrderedDict[KeyframeKey, T] = OrderedDict()
        self.total = 0

    def put(self, key: KeyframeKey, item: T) -> int:
        """Keep ``item`` for ``key`` (replacing its previous one); returns the size evicted."""
        old = self.items.pop(key, None)
        if old is not None:
            self.total -= self._size(old)
        self.items[key] = item
        self.total += self._size(item)
        evicted = 0
        while self.total > self.budget and len(self.items) > 1:
            _, dropped = self.items.popitem(last=False)
            self.total -= self._size(dropped)
            evicted += self._size(dropped)
        return evicted

    def clear(self) -> None:
        self.items.clear()
        self.total = 0


class _DepthPriors:
    """The keyframes' depth priors for the runtime (``ModelRuntime.set_view_depth_prior``): a
    keyframe's swept depth where kept, its splatted triangulated points elsewhere, the holes filled
    along the image (``stereo.prior_fill_px``) and, with ``stereo.prior_geometry``, from the surface
    the whole geometry shows, again as the geometry grows (:meth:`refresh`).

    ``lock`` is the triangulation's: it guards :attr:`own` (the methods ending in ``_locked`` are
    called with it held)."""

    def __init__(
        self,
        ctx: NodeContext,
        config: TriangulationConfig,
        stereo: StereoConfig,
        runtime: ExtentSink | None,
        lock: threading.Lock,
    ) -> None:
        self.ctx = ctx
        self.config = config
        self.stereo = stereo
        self.runtime = runtime
        self._lock = lock
        # each keyframe's own depth prior (the latest window.max_keyframes), to fill its holes from
        # the whole geometry again as it grows (stereo.prior_geometry)
        self.own: OrderedDict[KeyframeKey, tuple[np.ndarray, PosedView]] = OrderedDict()
        self.geometry_count = 0  # geometry points when the priors were last filled
        self.refreshes = 0

    def set(
        self, keyframe: Any, points: SparsePoints, swept: TriangulatedKeyframe | None,
        image: _StereoImage | None, geometry_points: Callable[[], tuple[np.ndarray, np.ndarray]],
    ) -> None:
        """Set the keyframe's depth prior in the runtime (none without a runtime)."""
        if self.runtime is None:
            return
        prior = None
        if self.config.depth_prior_radius_px > 0 and len(points):
            sparse = sparse_depth_keyframe(keyframe, points, self.config)
            prior = depth_prior(sparse, self.config.depth_prior_radius_px)
        cfg = self.stereo
        if swept is not None and cfg.depth_prior and bool((swept.depth_m > 0).any()):
            prior = swept.depth_m if prior is None else np.where(swept.depth_m > 0, swept.depth_m, prior)
            if cfg.prior_fill_px > 0 and image is not None:
                prior = self.filled(prior, image)
        if cfg.prior_geometry:  # its holes from the whole geometry (now, and as it grows)
            height, width = keyframe.rgb.shape[:2]
            view = PosedView(np.asarray(keyframe.K, np.float64),
                             np.asarray(keyframe.world_from_cam, np.float64), int(width), int(height))
            own = (np.zeros((int(height), int(width)), np.float32) if prior is None
                   else np.asarray(prior, np.float32))
            with self._lock:
                self.own[keyframe_key(keyframe)] = (own, view)
                while len(self.own) > max(1, self.ctx.config.window.max_keyframes):
                    self.own.popitem(last=False)
            geometry = geometry_points()[0]
            prior = self.with_geometry(own, view, geometry)
        if prior is not None:
            self.runtime.set_view_depth_prior(keyframe_key(keyframe), np.asarray(prior, np.float32))

    def with_geometry(self, own: np.ndarray, view: PosedView, geometry: np.ndarray) -> np.ndarray:
        """``own`` (h, w) prior with its holes (0) set to the surface the (N, 3) geometry shows at
        ``view`` (``mapper.node.queries.surface_depth``, each point over
        ``model.surface_geometry_footprint`` map voxels, as ``render`` splats it)."""
        from mapper.node.queries import surface_depth  # SciPy; only with stereo.prior_geometry

        cfg = self.ctx.config
        footprint_m = cfg.model.surface_geometry_footprint * cfg.global_map.voxel_size_m
        z = surface_depth(geometry, footprint_m, view.K, view.world_from_cam, view.width, view.height,
                          cfg.model)
        if z.shape != own.shape:
            z = cv2.resize(z, (own.shape[1], own.shape[0]), interpolation=cv2.INTER_NEAREST)
        return np.where(own > 0, own, z).astype(np.float32)

    def refresh(self, geometry_points: Callable[[], tuple[np.ndarray, np.ndarray]], force: bool) -> int:
        """``SparseTriangulation.refresh_priors``."""
        if self.runtime is None or not self.stereo.prior_geometry:
            return 0
        geometry = geometry_points()[0]
        last = self.geometry_count
        if not force and abs(len(geometry) - last) <= self.stereo.prior_geometry_refresh * last:
            return 0
        with self._lock:
            kept = list(self.own.items())
        for key, (own, view) in kept:
            self.runtime.set_view_depth_prior(key, self.with_geometry(own, view, geometry))
        self.geometry_count = len(geometry)
        self.refreshes += 1
        return len(kept)

    def filled(self, prior: np.ndarray, image: _StereoImage) -> np.ndarray:
        """``prior`` (H, W) with its holes filled at the working size, back at (H, W)."""
        cfg = self.stereo
        gray = image.view.gray
        small = prior
        if prior.shape != gray.shape:
            small = cv2.resize(prior, (gray.shape[1], gray.shape[0]), interpolation=cv2.INTER_NEAREST)
        filled = fill_depth(gray, small, cfg.prior_fill_px, sigma_gray=cfg.prior_fill_sigma,
                            max_spread=cfg.prior_fill_spread)
        if filled.shape != prior.shape:
            filled = cv2.resize(filled, (prior.shape[1], prior.shape[0]), interpolation=cv2.INTER_NEAREST)
            filled = np.where(prior > 0, prior, filled)
        return filled

    def clear_locked(self) -> None:
        """Forget the kept priors (a map was replaced)."""
        self.own.clear()
        self.geometry_count = 0

    def nbytes_locked(self) -> int:
        """Bytes of the kept priors."""
        return sum(own.nbytes for own, _ in self.own.values())


class SparseTriangulation:
    """Triangulates ``node``'s keyframes without depth in a background worker.

    Args:
        node: the mapper node (its ``state.global_map`` is read at integrate time).
        config: defaults to ``node.config.triangulation``.
        runtime: the learned-model runtime whose volume bounds follow the points (optional).
    """

    def __init__(
        self,
        ctx: NodeContext,
        config: TriangulationConfig | None = None,
        runtime: ExtentSink | None = None,
        stereo: StereoConfig | None = None,
    ) -> None:
        self.ctx = ctx
        self.config = config or ctx.config.triangulation
        self.stereo = stereo or ctx.config.stereo
        self.runtime = runtime
        self.extractor = FeatureExtractor(self.config)
        self._lock = threading.Lock()  # guards the sparse map, the candidates and the map they belong to
        self._work_lock = threading.Lock()  # one process_pending at a time
        self._queue: KeyframeQueue[tuple[Any, int, GlobalSemanticMap, bool]] = KeyframeQueue(
            self.config.max_pending
        )  # (keyframe, its map version, the node's map when it was queued, restored by a load)
        self._candidates = _RobotCandidates(self.config.candidate_keyframes)
        self._points: _KeyframeBudget[SparsePoints] = _KeyframeBudget(self.config.max_points, len)
        self._swept: _KeyframeBudget[tuple[np.ndarray, np.ndarray]] = _KeyframeBudget(  # (xyz, sigma)
            self.stereo.max_points, lambda xyz_sigma: len(xyz_sigma[1])
        )
        self._in_batch = 0  # keyframes of the batch being processed, not yet done (for `pending`)
        self._stop = threading.Event()  # the worker's stop event once it runs
        self.left_at_stop = 0
        self._map: GlobalSemanticMap | None = None  # the map the candidates and points belong to
        self._loaded_version = -1  # map version of the latest load: keyframes up to it are stale
        self._generation = 0  # +1 on every reset: work begun before it is not kept
        self._extents = _VolumeExtents(runtime, self.config) if runtime is not None else None
        self._room_depths: deque[float] = (self._extents.room_depths if self._extents is not None
                                           else deque(maxlen=self.config.candidate_keyframes))
        self.processed = 0
        self.points_total = 0
        self.points_evicted = 0
        self.integrated_points = 0
        self.partners_total = 0
        self.stale = 0
        self.restored = 0  # keyframes of a loaded window worked on again (their points not fused)
        self.failed = 0
        self.seconds: deque[float] = deque(maxlen=1000)
        self.seconds_total = 0.0
        self.stereo_keyframes = 0
        self.stereo_pixels = 0  # swept depths kept (at the working size)
        self.stereo_map_points = 0
        self.stereo_seconds_total = 0.0
        self.stereo_skipped_busy = 0
        self._deferred = _DeferredSweeps(self.stereo)
        self._late = _LateFeatures(ctx, self._lock, self._failed)  # points whose features come later
        self._priors = _DepthPriors(ctx, self.config, self.stereo, runtime, self._lock)
        self.poses = KeyframePoses(self.config)  # triangulation.refine_poses
        self._log = LimitedLog(log)

    # -- wiring -------------------------------------------------------------------------------

    def install(self) -> None:
        """Listen to the node's new keyframes and map loads, report in its status
        (``"triangulation"``) and run the worker with the node (started by ``node.start()``)."""
        self.ctx.keyframe_listeners.append(self.on_keyframe)
        self.ctx.load_listeners.append(self.on_map_loaded)
        self.ctx.feature_listeners.append(self.on_features)
        self.ctx.surface_points.append(lambda: self.geometry_points()[0])
        self.ctx.workers.append(("triangulation", self.run))
        self.ctx.register_pending("triangulation", lambda: self.pending, geometry=True)
        self.ctx.status_providers["triangulation"] = self.stats

    def on_keyframe(self, keyframe: Any, map_version: int) -> None:
        """Queue every keyframe (keyframe-listener thread; O(1), never raises): those without depth are
        triangulated, those with depth only become partner candidates."""
        if self.config.enabled:
            self._queue.put((keyframe, int(map_version), self.ctx.state.global_map, False))

    def on_map_loaded(
        self, global_map: GlobalSemanticMap, map_version: int, keyframes: Sequence[Any] = ()
    ) -> None:
        """A load replaced the map (the loading thread; quick, never raises): forget the replaced
        map's candidates, points and room depth now, skip the keyframes queued for it (those with a
        map version up to ``map_version``) when the worker meets them, and queue the loaded
        window's ``keyframes`` (oldest first) to be worked on again without fusing their points."""
        with self._lock:
            self._loaded_version = max(self._loaded_version, int(map_version))
            self._reset_locked()
            self._map = global_map
        if self.config.enabled:
            for keyframe in keyframes:
                self._queue.put((keyframe, int(map_version), global_map, True))

    # -- work -----------------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Keyframes waiting, including those of the batch the worker took and has not finished,
        and the sweeps put off while busy (``stereo.max_deferred``)."""
        return self._waiting + len(self._deferred)

    @property
    def _waiting(self) -> int:
        """Keyframes queued or in the batch being worked on (what ``stereo.max_backlog`` counts)."""
        return len(self._queue) + self._in_batch

    def process_pending(self) -> int:
        """Triangulate every keyframe pending now; returns the keyframes triangulated (those with
        depth only join the candidates). Safe to call from any thread."""
        if not self._work_lock.acquire(blocking=False):
            return 0
        try:
            batch = self._queue.drain()
            self._in_batch = len(batch)
            done = 0
            for n, (kf, version, target, restored) in enumerate(batch):
                if self._stop.is_set():  # the node is stopping: the rest of the batch is not worked on
                    self.left_at_stop += len(batch) - n
                    break
                try:
                    done += self._process_one(kf, version, target, restored)
                finally:
                    self._in_batch -= 1
            self._in_batch = 0
            swept_later = self.sweep_deferred()
            if done or swept_later:
                try:
                    self.refresh_priors()
                except Exception as exc:  # a bad geometry point must not kill the worker
                    self._log.warning("priors", "triangulation: refreshing the depth priors failed: %s", exc)
            return done
        finally:
            self._in_batch = 0
            self._work_lock.release()

    def sweep_deferred(self) -> int:
        """Do the sweeps put off while busy, oldest first (a sweep keeps the depths its partners'
        own depths confirm, and its partners are older keyframes), while no keyframe waits (the
        worker thread, from :meth:`process_pending`); returns how many were swept."""
        swept = 0
        while not self._stop.is_set() and not len(self._queue):
            with self._lock:
                item = self._deferred.take()
            if item is None:
                break
            kept = 0
            try:
                kept = self._sweep_deferred_one(item)
            finally:
                with self._lock:
                    self._deferred.done(bool(kept))
            swept += kept
        return swept

    def _sweep_deferred_one(self, item: _DeferredSweep) -> int:
        """One put-off sweep, kept, fused and made a prior as :meth:`_process_one` does; 1 when kept."""
        with self._lock:
            if item.generation != self._generation:  # a load since: its map was replaced
                return 0
        try:
            swept = self._sweep(item.image, item.partners, item.points)
        except Exception as exc:  # bad input, OpenCV errors: count, never kill the worker
            self._failed(item.keyframe, exc)
            return 0
        if swept is None:
            return 0
        key = keyframe_key(item.keyframe)
        with self._lock:
            if item.generation != self._generation:
                return 0
            self._store_swept(key, item.image, swept[0], swept[1])
        current = self._current(item.keyframe)
        swept_frame = swept_keyframe(current, swept[0], swept[1], self.stereo)
        self._priors.set(item.keyframe, item.points, swept_frame, item.image, self.geometry_points)
        if not item.restored:
            self._integrate_swept(current, swept_frame, item.target)
        return 1

    def _current(self, keyframe: Any) -> Any:
        """``keyframe`` with its OV features if they came since it was queued, at its pose as
        triangulated (the window's copy carries the pose as sent)."""
        current = with_current_features(self.ctx, keyframe)
        if current is not keyframe:
            current = replace(current, world_from_cam=keyframe.world_from_cam)
        return current

    def _process_one(self, keyframe: Any, map_version: int, target: GlobalSemanticMap,
                     restored: bool = False) -> int:
        """``restored``: a keyframe of the window a load brought (its points are in the map)."""
        started = time.perf_counter()
        with self._lock:
            # acked before a load (or restored by an earlier one): its map was replaced
            if map_version < self._loaded_version or (map_version == self._loaded_version and not restored):
                self.stale += 1
                return 0
            if target is not self._map:  # the first keyframe, or a map swapped in without a load
                if self._map is not None:
                    self._reset_locked()
                self._map = target
            generation = self._generation
            candidates = self._candidates.of(getattr(keyframe, "robot", ""))
        try:
            height, width = keyframe.rgb.shape[:2]
            pose = np.asarray(keyframe.world_from_cam, np.float64)
            view = PosedView(np.asarray(keyframe.K, np.float64), pose, int(width), int(height))
            image = stereo_image(keyframe, self.stereo) if self.stereo.enabled else None
            if keyframe.depth_m is not None:
                candidate = _Candidate(keyframe_key(keyframe), view, keyframe.rgb, stereo=image,
                                       robot=getattr(keyframe, "robot", ""))
                if not self._add_candidate(generation, candidate):
                    self.stale += 1  # a load meanwhile
                return 0
            features = self.extractor.detect(np.asarray(keyframe.rgb))
            chosen = select_partners(view, [c.view for c in candidates], self.config)
            partners = [(candidates[i].view, candidates[i].detected(self.extractor)) for i in chosen]
            matched = [self.extractor.match(features, f) for _, f in partners]
            if self.config.refine_poses:  # its pose against the partners' points, before its own
                if self.config.pose_method == "window":  # the last keyframes adjusted jointly
                    refined = self.poses.refine_window(keyframe_key(keyframe), view.K, pose,
                                                       np.asarray(keyframe.rgb))
                else:
                    refined = self.poses.refine(keyframe_key(keyframe), view.K, pose, features,
                                                [candidates[i].points for i in chosen], matched)
                if refined.accepted:
                    keyframe = replace(keyframe, world_from_cam=refined.world_from_cam)
                    view = replace(view, world_from_cam=refined.world_from_cam)
                    image = stereo_image(keyframe, self.stereo) if image is not None else None
            own = _Candidate(keyframe_key(keyframe), view, None, features, stereo=image,
                             robot=getattr(keyframe, "robot", ""))
            if not self._add_candidate(generation, own):
                self.stale += 1  # a load while it was detected
                return 0
            points = triangulate_keyframe(self.extractor, view, features, partners, self.config, matched)
            if points.feature_index is not None:
                own.points = (points.feature_index, points.xyz)
            swept, deferred = None, None
            if image is not None:
                backlog = self.stereo.max_backlog
                if backlog and self._waiting > backlog:  # keep up: sparse geometry now, the sweep later
                    self.stereo_skipped_busy += 1
                    deferred = _DeferredSweep(keyframe, image, [candidates[i] for i in chosen], points,
                                              target, generation, restored)
                else:
                    swept = self._sweep(image, [candidates[i] for i in chosen], points)
        except Exception as exc:  # bad input, OpenCV errors (cv2.error): count, never kill the worker
            self._failed(keyframe, exc)
            return 0
        with self._lock:
            if generation != self._generation:  # a load while it was triangulated: not kept
                self.stale += 1
                return 0
            self._store(keyframe_key(keyframe), points)
            if swept is not None and image is not None:
                self._store_swept(keyframe_key(keyframe), image, swept[0], swept[1])
            if deferred is not None:
                self._deferred.put(deferred)
            if self._extents is not None and self.config.bounds:
                self._extents.set(keyframe_key(keyframe), view, points)
        current = self._current(keyframe)  # its OV features, if they came meanwhile
        swept_frame = None if swept is None else swept_keyframe(current, swept[0], swept[1], self.stereo)
        self._priors.set(keyframe, points, swept_frame, image, self.geometry_points)
        self.restored += int(restored)
        if not restored:
            self._integrate(current, points, target)
            if swept_frame is not None:
                self._integrate_swept(current, swept_frame, target)
        seconds = time.perf_counter() - started
        self.processed += 1
        self.points_total += len(points)
        self.partners_total += points.partners
        with self._lock:  # stats() copies it from the query thread
            self.seconds.append(seconds)
        self.seconds_total += seconds
        log.debug("triangulation: %d points (%d partners, %d matches) for keyframe at stamp %d in %.0f ms",
                  len(points), points.partners, points.matches, keyframe.stamp_ns, 1e3 * seconds)
        return 1

    def _sweep(
        self, image: _StereoImage, partners: list[_Candidate], points: SparsePoints
    ) -> tuple[DenseDepth, np.ndarray] | None:
        """Plane-sweep depth of a keyframe (``image``) against its best partners; returns the
        sweep and the (h, w) mask of the depths kept (``stereo.min_agreeing`` partners agree), or
        None without enough partners. The keyframe's swept depth is kept for later checks."""
        cfg = self.stereo
        sources = [p.stereo for p in partners if p.stereo is not None][: cfg.max_sources]
        if len(sources) < cfg.top_k:
            return None
        started = time.perf_counter()
        span = depth_range(points.depth_m, cfg) if len(points) else None
        if span is None:
            room = self._room_depths
            far = float(np.median(room)) * cfg.range_margin if room else cfg.fallback_far_m
            span = (cfg.min_depth_m, max(far, 2.0 * cfg.min_depth_m))
        dense = sweep_depth(image.view, [s.view for s in sources], span[0], span[1], cfg)
        image.depth_m = dense.depth_m  # later keyframes check their depths against it
        keep = dense.valid
        if cfg.min_agreeing > 0:
            others = [(s.view.K, s.view.world_from_cam, s.depth_m) for s in sources if s.depth_m is not None]
            agree, _ = agreeing_views(image.view.K, image.view.world_from_cam, dense.depth_m, others,
                                      cfg.consistency_rel)
            keep = keep & (agree >= cfg.min_agreeing)
        self.stereo_keyframes += 1
        self.stereo_pixels += int(np.count_nonzero(keep))
        self.stereo_seconds_total += time.perf_counter() - started
        return dense, keep

    def refresh_priors(self, force: bool = False) -> int:
        """Fill the kept keyframes' own priors from the current geometry again when its point count
        moved by more than ``stereo.prior_geometry_refresh`` since the last fill (or ``force``);
        returns the priors set (worker thread, after a batch)."""
        return self._priors.refresh(self.geometry_points, force)

    @property
    def prior_refreshes(self) -> int:
        """How often the kept priors were filled from the geometry again (:meth:`refresh_priors`)."""
        return self._priors.refreshes

    def _add_candidate(self, generation: int, candidate: _Candidate) -> bool:
        """Append ``candidate`` unless a reset came after ``generation`` (then False)."""
        with self._lock:
            if generation != self._generation:
                return False
            self._candidates.append(candidate)
            return True

    def _reset_locked(self) -> None:
        """Forget the candidates, points and room depth of a map that was replaced (``_lock``
        held); work begun before it is not kept."""
        self._generation += 1
        self._points.clear()
        self._swept.clear()
        self._late.pending.clear()
        self._deferred.forget_all()
        self._candidates.clear()
        if self._extents is not None:
            self._extents.clear()
        else:
            self._room_depths.clear()
        self._priors.clear_locked()
        self.poses.clear()
        self._map = None

    def _failed(self, keyframe: Any, exc: BaseException) -> None:
        self.failed += 1
        self._log.warning("failed", "triangulation of keyframe at stamp %d failed: %s",
                          keyframe.stamp_ns, exc)

    def _store(self, key: KeyframeKey, points: SparsePoints) -> None:
        """Keep ``points`` for ``key`` within ``max_points`` (``_lock`` held)."""
        self.points_evicted += self._points.put(key, points)

    def _integrate(self, keyframe: Any, points: SparsePoints, target: GlobalSemanticMap) -> None:
        if self.config.global_map_weight <= 0.0 or not len(points):
            return
        if target is not self.ctx.state.global_map:
            self.stale += 1  # a map load replaced the map this keyframe belonged to
            return
        self._fuse(keyframe, sparse_depth_keyframe(keyframe, points, self.config), target, swept=False)

    def _fuse(
        self, keyframe: Any, depth: TriangulatedKeyframe, target: GlobalSemanticMap, *, swept: bool
    ) -> None:
        """Integrate a sparse or swept depth map of ``keyframe``; without OV features yet, keep it
        until they arrive (``on_features``)."""
        try:
            stats = target.integrate(depth, map_version=None, pixel_stride=1, confidence=depth.confidence,
                                     count_keyframe=False, carve=False)  # not input depth: no carving
        except (ValueError, RuntimeError) as exc:
            self._failed(keyframe, exc)
            return
        if swept:
            self.stereo_map_points += stats.points
        else:
            self.integrated_points += stats.points
        if depth.ov is None and self.ctx.config.ov_backend.kind:  # only a backend brings features later
            self._late.remember(keyframe, depth, target)

    def on_features(self, keyframe: Any) -> None:
        """``node.feature_listeners``: ``keyframe`` (no input depth) got its OV features; fuse them
        into the map points this plugin added for it without features. Never raises."""
        self._late.on_features(keyframe)

    def _integrate_swept(self, keyframe: Any, swept: TriangulatedKeyframe, target: GlobalSemanticMap) -> None:
        if self.stereo.global_map_weight <= 0.0 or not bool((swept.depth_m > 0).any()):
            return
        if target is not self.ctx.state.global_map:
            return  # a map load replaced the map (counted once by _integrate)
        self._fuse(keyframe, swept, target, swept=True)

    def _store_swept(
        self, key: KeyframeKey, image: _StereoImage, dense: DenseDepth, keep: np.ndarray
    ) -> None:
        """Keep the keyframe's kept swept depths as world points with a sigma (``stereo.sigma_rel``)
        within ``stereo.max_points`` (``_lock`` held)."""
        if self.stereo.max_points <= 0:
            return
        rows, cols, xyz = backproject(dense.depth_m, image.view.K, image.view.world_from_cam, keep)
        z = dense.depth_m[rows, cols].astype(np.float64)
        self._swept.put(key, (xyz, self.stereo.sigma_rel * z))

    def geometry_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The triangulated points and the kept swept depths as points: ``(xyz (N, 3) float64
        world, sigma_m (N,) float64)``; what the rendered-depth points are checked against."""
        xyz, sigma = self.points()
        with self._lock:
            swept = list(self._swept.items.values())
        if not swept:
            return xyz, sigma
        return (np.concatenate([xyz] + [p for p, _ in swept]),
                np.concatenate([sigma] + [s for _, s in swept]))

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """Every kept point: ``(xyz (N, 3) float64 world, sigma_m (N,) float64)``."""
        with self._lock:
            kept = list(self._points.items.values())
        if not kept:
            return np.zeros((0, 3)), np.zeros(0)
        return np.concatenate([p.xyz for p in kept]), np.concatenate([p.sigma_m for p in kept])

    def keyframe_points(self, keyframe: Any) -> SparsePoints | None:
        """The points triangulated for ``keyframe`` (None when it was not, or they were dropped)."""
        with self._lock:
            return self._points.items.get(keyframe_key(keyframe))

    def memory_bytes(self) -> int:
        """Bytes of the sparse map and the candidates' features (reported in ``status`` under
        ``triangulation``; not in the node's ``memory_bytes``, which counts map data, as a load
        restores it)."""
        with self._lock:
            pts = sum(p.xyz.nbytes + p.sigma_m.nbytes * 5 + p.uv.nbytes for p in self._points.items.values())
            pts += self._priors.nbytes_locked()
            pts += self._deferred.nbytes  # the put-off sweeps' keyframes and working images
            candidates = list(self._candidates)
        feats = 0
        for c in candidates:
            f = c.features
            if f is not None:
                feats += f.uv.nbytes + f.descriptors.nbytes + (0 if f.gray is None else f.gray.nbytes)
            elif c.rgb is not None:
                feats += c.rgb.nbytes  # a view of the keyframe's image (shared with the window)
            if c.stereo is not None:
                depth = c.stereo.depth_m
                feats += c.stereo.view.gray.nbytes + (0 if depth is None else depth.nbytes)
        return int(pts + feats)

    def run(self, stop: threading.Event) -> None:
        """Worker loop: process the pending keyframes whenever new ones arrive, until ``stop`` (set
        during a batch, the batch's remaining keyframes are left: ``left_at_stop``)."""
        self._stop = stop
        run_worker(stop, self._queue.wake, self.process_pending, self._unexpected)

    def _unexpected(self, exc: BaseException) -> None:
        self.failed += 1
        log.error("triangulation worker: unexpected error (continuing)", exc_info=exc)

    def stats(self) -> dict[str, Any]:
        """Counters for the node's status reply (points and cost per triangulated keyframe)."""
        with self._lock:
            recent = sorted(self.seconds)
        return {
            "enabled": self.config.enabled,
            "detector": self.config.detector,
            "pending": self.pending,
            "queued": self._queue.queued,
            "dropped": self._queue.dropped,
            "keyframes": self.processed,
            "points": self._points.total,
            "points_evicted": self.points_evicted,
            "points_per_keyframe": round(self.points_total / max(self.processed, 1), 1),
            "partners_per_keyframe": round(self.partners_total / max(self.processed, 1), 2),
            "global_map_points": self.integrated_points,
            "mean_ms": round(1e3 * self.seconds_total / max(self.processed, 1), 1),
            "p90_ms": round(1e3 * recent[int(0.9 * (len(recent) - 1))], 1) if recent else 0.0,
            "stale": self.stale,
            "restored": self.restored,
            "failed": self.failed,
            "left_at_stop": self.left_at_stop,
            "late_feature_points": self._late.points,
            "memory_bytes": self.memory_bytes(),
            "stereo": {
                "enabled": self.stereo.enabled,
                "keyframes": self.stereo_keyframes,
                "depths_per_keyframe": round(self.stereo_pixels / max(self.stereo_keyframes, 1), 1),
                "global_map_points": self.stereo_map_points,
                "points": self._swept.total,
                "skipped_busy": self.stereo_skipped_busy,
                **self._deferred.stats(),
                "mean_ms": round(1e3 * self.stereo_seconds_total / max(self.stereo_keyframes, 1), 1),
                "prior_refreshes": self._priors.refreshes,
            },
            "poses": self.poses.stats(),
        }


def install_triangulation(node: MapperNode, runtime: ExtentSink | None = None) -> SparseTriangulation | None:
    """Install :class:`SparseTriangulation` on ``node`` when ``triangulation.enabled`` (returned;
    None otherwise). ``runtime``: the learned-model runtime whose bounds follow the points."""
    if not node.config.triangulation.enabled:
        return None
    tri = SparseTriangulation(node.ctx, runtime=runtime)
    tri.install()
    return tri
