"""Global-map points for keyframes without input depth, from the learned model's rendered depth.

A robot with a plain RGB camera sends frames without ``depth_m``. The global semantic point map
(:mod:`mapper.map.global_map`) back-projects input depth, so such keyframes would add no points. With
the learned model served, :class:`RenderedDepthPoints` fills the gap: for each such keyframe it
renders the model's depth at the keyframe's own pose (density only, no appearance pass: the cost
of a depth render is the 3D U-Net once per runtime version with the window's volume, or a cost
volume and U-Net pass per keyframe over the ``rendered_volume_views`` keyframes that best overlap
it when that is set, plus a density MLP per sample), at
``1 / rendered_depth_stride`` of the keyframe's size, keeps the pixels whose accumulated opacity
reaches ``rendered_min_opacity`` (the ray met a clear surface), and fuses them into the global map
exactly as input depth (same voxels, same OV sampling of the keyframe's own ``ov`` map, same
quality weights) with the weights scaled by ``rendered_weight * opacity``, so input depth outranks
rendered depth where both exist.

Multi-view consistency (``rendered_consistency``, :func:`consistency_mask`): an opacity threshold
alone keeps floaters (a density field fit to few views puts confident surfaces where there are
none). So a rendered pixel is kept only where it agrees with the geometry from other views: with
the **triangulated points** and the kept **plane-sweep depths** as points
(:mod:`mapper.node.workers.triangulation`, ``geometry_points``) that project within
``rendered_consistency_radius_px`` of it (their depth in this camera within
``max(rendered_consistency_sigmas * sigma, rendered_consistency_voxels * voxel_size_m)`` of the
rendered depth, at least one of them), or, where no triangulated point projects near it, with the
**rendered depth of at least one other keyframe** (rendered in the same batch or one of the last
``rendered_consistency_views``, camera centre at least ``rendered_consistency_min_baseline_m``
away) that sees it (``rendered_view_agreement``: by default only while the node sweeps no stereo
depths): the pixel's 3D point reprojected there lies within
``rendered_consistency_voxels * voxel_size_m`` of that keyframe's rendered depth. Points behind a
camera or outside its image are no evidence either way. The triangulated points come from the
node's installed :class:`~mapper.node.workers.triangulation.SparseTriangulation` (found at
render time, so either plugin may be installed first) or from :attr:`RenderedDepthPoints.sparse_source`;
the dense optical-flow points (:mod:`mapper.node.workers.flow_points`) join them when installed.

Scheduling: the node calls :meth:`RenderedDepthPoints.on_keyframe` on the keyframe-listener thread
(integrator; the ingest thread when integration is inline) after a keyframe entered the window
(O(1): a deque append). A background worker (``mapper-depth-points``) renders the pending keyframes
in batches: one runtime sync serves every keyframe pending at that moment.
Until the model's window holds ``rendered_min_views`` keyframes the pending ones wait (a density
field from one or two views is not a surface). Beyond ``rendered_max_pending`` waiting keyframes the
oldest is dropped and counted. A map load replaces the global map; keyframes queued for the old map
are dropped (counted as ``stale``).

Errors never reach the listener thread: a keyframe whose render fails is logged (rate limited) and
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
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from mapper.geometry.triangulation import backproject
from mapper.node.config import GlobalMapConfig
from mapper.node.keyframe_queue import KeyframeQueue, LimitedLog, run_worker, with_current_features
from mapper.runtime.model_runtime import ModelRuntime, RuntimeNotReady

if TYPE_CHECKING:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.backends.robot_runtimes import RobotRuntimes
    from mapper.node.context import NodeContext

__all__ = [
    "RenderedDepthPoints",
    "RenderedKeyframe",
    "consistency_mask",
    "render_opaque_depth",
    "sparse_agreement",
    "view_agreement",
]

log = logging.getLogger("mapper.node.workers.depth_points")

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


def depth_edges(depth: np.ndarray, rel: float) -> np.ndarray:
    """(h, w) bool: pixels with a depth whose 4-neighbour (with a depth) differs from it by more
    than ``rel`` of the nearer of the two (an occlusion edge; 0 = no depth, never an edge).

    Args:
        depth: (h, w) z-depth (m), 0 = none.
    """
    d = np.asarray(depth, np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth must be (h, w), got shape {d.shape}")
    edge = np.zeros(d.shape, bool)
    # each pair of vertical, then horizontal neighbours: (a, b) and the views of ``edge`` at them
    for a, b, at_a, at_b in ((d[:-1], d[1:], edge[:-1], edge[1:]),
                             (d[:, :-1], d[:, 1:], edge[:, :-1], edge[:, 1:])):
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > rel * np.minimum(a, b))
        at_a |= jump
        at_b |= jump
    return edge


def render_opaque_depth(
    runtime: ModelRuntime | RobotRuntimes,
    keyframe: Any,  # rgb (H, W, 3), K (4,) in its pixels, world_from_cam (4, 4)
    size_hw: tuple[int, int],  # (h, w) of the render over the whole image
    min_opacity: float,
    volume_views: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's depth at ``keyframe``'s pose at ``size_hw``: (K (4,) float64 scaled to that size,
    z-depth (h, w) float32 with 0 where the ray's opacity stays below ``min_opacity``, opacity
    (h, w) float32). Raises :class:`RuntimeNotReady` like the runtime's render."""
    h, w = (int(v) for v in size_hw)
    height, width = keyframe.rgb.shape[:2]
    sx, sy = w / width, h / height
    fx, fy, cx, cy = (float(v) for v in keyframe.K)
    K = np.array([fx * sx, fy * sy, cx * sx, cy * sy], np.float64)
    pose = np.asarray(keyframe.world_from_cam, np.float64)
    frame = runtime.render(K, pose, w, h, outputs=("depth",), volume_views=volume_views)
    assert frame.depth_m is not None and frame.opacity is not None
    opacity = np.nan_to_num(np.asarray(frame.opacity, np.float32), nan=0.0)
    depth = np.where(opacity >= min_opacity, frame.depth_m, 0.0).astype(np.float32)
    return K, depth, opacity


def render_keyframe_depth(
    runtime: ModelRuntime | RobotRuntimes, keyframe: Any, config: GlobalMapConfig
) -> RenderedKeyframe:
    """Render the model's depth at ``keyframe``'s pose at ``1 / rendered_depth_stride`` of its size,
    from the window's volume, or (``rendered_volume_views`` > 1) from a cost volume over that many
    keyframes that best overlap it.

    Raises :class:`RuntimeNotReady` (no model, no keyframes) like the runtime's render.
    """
    height, width = keyframe.rgb.shape[:2]
    stride = config.rendered_depth_stride
    w, h = max(1, width // stride), max(1, height // stride)
    K, depth, opacity = render_opaque_depth(runtime, keyframe, (h, w), config.rendered_min_opacity,
                                            config.rendered_volume_views)
    pose = np.asarray(keyframe.world_from_cam, np.float64)
    if config.rendered_edge_rel > 0:
        depth[depth_edges(depth, config.rendered_edge_rel)] = 0.0
    return RenderedKeyframe(
        stamp_ns=int(keyframe.stamp_ns),
        K=K,
        world_from_cam=pose,
        rgb=np.zeros((h, w, 3), np.uint8),
        depth_m=depth,
        ov=keyframe.ov,
        confidence=(config.rendered_weight * np.clip(opacity, 0.0, 1.0)).astype(np.float32),
    )


class DepthView(Protocol):
    """A z-depth image with its camera (a :class:`RenderedKeyframe`, or any keyframe with depth)."""

    @property
    def K(self) -> np.ndarray: ...  # (4,) [fx, fy, cx, cy]

    @property
    def world_from_cam(self) -> np.ndarray: ...  # (4, 4)

    @property
    def depth_m(self) -> np.ndarray: ...  # (h, w) z-depth, 0 = none


def _project(xyz: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> (pixel coordinates (N, 2) with pixel centres at +0.5, z-depth (N,))."""
    pose = np.asarray(world_from_cam, np.float64)
    cam = (np.asarray(xyz, np.float64) - pose[:3, 3]) @ pose[:3, :3]  # R^T (x - t), row-wise
    z = cam[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    fx, fy, cx, cy = (float(v) for v in K)
    uv = np.stack([fx * cam[:, 0] / safe + cx, fy * cam[:, 1] / safe + cy], axis=1)
    return uv, z


def sparse_agreement(
    view: DepthView,
    xyz: np.ndarray,
    sigma_m: np.ndarray,
    *,
    radius_px: int,
    sigmas: float,
    min_tolerance_m: float,
    min_depth_m: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels of ``view`` have triangulated points near them, and which agree with one.

    Args:
        view: the rendered depth (h, w) with its ``K`` and ``world_from_cam``.
        xyz: (N, 3) triangulated points, world metres; ``sigma_m`` (N,) their 1-sigma uncertainty.
        radius_px: a point is a neighbour of every pixel within this (Euclidean, in pixels)
            distance of the pixel it projects into.
        sigmas, min_tolerance_m: a neighbour agrees when its z-depth in this camera is within
            ``max(sigmas * sigma, min_tolerance_m)`` of the pixel's depth.
        min_depth_m: points closer than this in front of the camera (or behind it) are ignored.

    Returns:
        ``(neighbour, agrees)``, both (h, w) bool; ``agrees`` implies ``neighbour`` and depth > 0.
    """
    depth = np.asarray(view.depth_m)
    h, w = depth.shape
    neighbour = np.zeros((h, w), bool)
    agrees = np.zeros((h, w), bool)
    if len(xyz) == 0:
        return neighbour, agrees
    uv, z = _project(xyz, view.K, view.world_from_cam)
    ok = z > min_depth_m
    uv, z = uv[ok], z[ok]
    tol = np.maximum(sigmas * np.asarray(sigma_m, np.float64)[ok], min_tolerance_m)
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    has_depth = np.isfinite(depth) & (depth > 0)
    for dy in range(-radius_px, radius_px + 1):
        for dx in range(-radius_px, radius_px + 1):
            if dx * dx + dy * dy > radius_px * radius_px:
                continue
            r, c = row + dy, col + dx
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            r, c = r[inside], c[inside]
            neighbour[r, c] = True
            match = has_depth[r, c] & (np.abs(depth[r, c] - z[inside]) <= tol[inside])
            agrees[r[match], c[match]] = True
    return neighbour, agrees


def view_agreement(
    view: DepthView,
    others: Sequence[DepthView],
    *,
    tolerance_m: float,
    min_baseline_m: float,
    min_depth_m: float = 1e-3,
) -> np.ndarray:
    """(h, w) bool: pixels of ``view`` whose 3D point agrees with at least one of ``others``.

    Each pixel with depth is back-projected, reprojected into every other view whose camera centre
    is at least ``min_baseline_m`` from ``view``'s, and agrees when it lands inside that image, in
    front of its camera (> ``min_depth_m``), on a pixel with depth within ``tolerance_m`` of the
    point's z-depth there. Points behind a camera, outside its image or on a pixel without depth
    are no evidence.
    """
    depth = np.asarray(view.depth_m)
    agrees = np.zeros(depth.shape, bool)
    rows, cols, xyz = backproject(view.depth_m, view.K, view.world_from_cam)
    if len(xyz) == 0:
        return agrees
    centre = np.asarray(view.world_from_cam, np.float64)[:3, 3]
    found = np.zeros(len(xyz), bool)
    for other in others:
        if np.linalg.norm(np.asarray(other.world_from_cam, np.float64)[:3, 3] - centre) < min_baseline_m:
            continue
        other_depth = np.asarray(other.depth_m)
        oh, ow = other_depth.shape
        uv, z = _project(xyz, other.K, other.world_from_cam)
        c, r = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = (z > min_depth_m) & (c >= 0) & (c < ow) & (r >= 0) & (r < oh)
        idx = np.nonzero(ok)[0]
        d = other_depth[r[idx].astype(np.int64), c[idx].astype(np.int64)]
        good = np.isfinite(d) & (d > 0) & (np.abs(d - z[idx]) <= tolerance_m)
        found[idx[good]] = True
    agrees[rows[found], cols[found]] = True
    return agrees


def consistency_mask(
    view: DepthView,
    xyz: np.ndarray,
    sigma_m: np.ndarray,
    others: Sequence[DepthView],
    config: GlobalMapConfig,
    *,
    by_views: bool = True,
) -> tuple[np.ndarray, dict[str, int]]:
    """(h, w) bool: the pixels of ``view`` to keep (see the module docstring), and counts
    ``{"checked", "by_points", "by_views", "rejected"}`` of its pixels with depth. ``by_views=False``:
    only the points' agreement keeps a pixel (``global_map.rendered_view_agreement``)."""
    tol = config.rendered_consistency_voxels * config.voxel_size_m
    depth = np.asarray(view.depth_m)
    has_depth = np.isfinite(depth) & (depth > 0)
    neighbour, agrees = sparse_agreement(
        view, xyz, sigma_m, radius_px=config.rendered_consistency_radius_px,
        sigmas=config.rendered_consistency_sigmas, min_tolerance_m=tol,
    )
    if by_views:
        agree_views = view_agreement(view, others, tolerance_m=tol,
                                     min_baseline_m=config.rendered_consistency_min_baseline_m)
        agree_views &= has_depth & ~neighbour
    else:
        agree_views = np.zeros_like(has_depth)
    keep = (agrees | agree_views) & has_depth
    counts = {
        "checked": int(has_depth.sum()),
        "by_points": int(agrees.sum()),
        "by_views": int(agree_views.sum()),
        "rejected": int(has_depth.sum() - keep.sum()),
    }
    return keep, counts


SparseSource = Callable[[], tuple[np.ndarray, np.ndarray]]
"""Returns every triangulated point: ``(xyz (N, 3) world, sigma_m (N,))``."""


class RenderedDepthPoints:
    """Adds rendered-depth points to ``node``'s global map for keyframes without input depth.

    Args:
        node: the mapper node (its ``state.global_map`` is read at integrate time, so a map load
            is followed).
        runtime: the learned-model runtime serving ``node``'s window.
        config: defaults to ``node.config.global_map``.
    """

    def __init__(
        self, ctx: NodeContext, runtime: ModelRuntime | RobotRuntimes, config: GlobalMapConfig | None = None
    ) -> None:
        self.ctx = ctx
        self.runtime = runtime
        self.config = config or ctx.config.global_map
        self._lock = threading.Lock()
        self._queue: KeyframeQueue[tuple[Any, GlobalSemanticMap]] = KeyframeQueue(
            self.config.rendered_max_pending
        )
        self._busy = False
        self._in_batch = 0  # keyframes of the batch being processed, not yet done (for `pending`)
        self.integrated = 0
        self.points = 0
        self.stale = 0
        self.failed = 0
        self.seconds_total = 0.0
        self.sparse_source: SparseSource | None = None
        """Where the triangulated points come from; None: the node's installed triangulation plugin."""
        self._recent: deque[tuple[RenderedKeyframe, GlobalSemanticMap]] = deque(
            maxlen=self.config.rendered_consistency_views
        )  # unfiltered recent renders, the second views of the consistency check
        self.consistency = {"checked": 0, "by_points": 0, "by_views": 0, "rejected": 0}
        self._log = LimitedLog(log)

    # -- wiring -------------------------------------------------------------------------------

    def install(self) -> None:
        """Listen to the node's new keyframes, report in its status (``"rendered_depth"``) and run
        the worker thread with the node (started by ``node.start()``)."""
        self.ctx.keyframe_listeners.append(self.on_keyframe)
        self.ctx.workers.append(("depth-points", self.run))
        self.ctx.register_pending("rendered_depth", lambda: self.pending, geometry=True)
        self.ctx.status_providers["rendered_depth"] = self.stats

    def on_keyframe(self, keyframe: Any, map_version: int) -> None:
        """Queue ``keyframe`` if it has no input depth (keyframe-listener thread; O(1), never raises)."""
        if keyframe.depth_m is not None or not self.config.rendered_depth:
            return
        self._queue.put((keyframe, self.ctx.state.global_map))

    # -- work -----------------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Keyframes waiting, including those of the batch the worker took and has not finished."""
        return len(self._queue) + self._in_batch

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
            taken = self._queue.drain()
            self._in_batch = len(taken)
            batch = [(kf, target, self._render(kf, target)) for kf, target in taken]
            done = 0
            for i, (keyframe, target, rendered) in enumerate(batch):
                self._in_batch = len(batch) - i
                if rendered is None:
                    continue
                others = [r for j, (_, t, r) in enumerate(batch) if j != i and t is target and r is not None]
                done += self._integrate_one(keyframe, target, rendered, others)
            self._in_batch = 0
            for _, target, rendered in batch:
                if rendered is not None:
                    self._recent.append((rendered[0], target))
            return done
        finally:
            with self._lock:
                self._busy = False
                self._in_batch = 0

    def _render(self, keyframe: Any, target: GlobalSemanticMap) -> tuple[RenderedKeyframe, float] | None:
        """The keyframe's rendered depth (unfiltered) and the seconds it took; None when stale or
        failed (counted)."""
        if target is not self.ctx.state.global_map:
            self.stale += 1  # a map load replaced the map this keyframe belonged to
            return None
        started = time.perf_counter()
        if keyframe.ov is None:
            keyframe = with_current_features(self.ctx, keyframe)
        try:
            rendered = render_keyframe_depth(self.runtime, keyframe, self.config)
        except (RuntimeNotReady, ValueError, RuntimeError) as exc:
            self.failed += 1
            self._log.warning("failed", "rendered depth for keyframe at stamp %d failed: %s",
                              keyframe.stamp_ns, exc)
            return None
        return rendered, time.perf_counter() - started

    def _view_agreement(self) -> bool:
        """``global_map.rendered_view_agreement``: "auto" is on unless the node's triangulation
        plugin sweeps dense stereo depths."""
        mode = self.config.rendered_view_agreement
        if mode != "auto":
            return mode == "on"
        stereo = getattr(self._triangulation(), "stereo", None)
        return not (stereo is not None and bool(getattr(stereo, "enabled", False)))

    def _triangulation(self) -> Any:
        """The node's installed triangulation plugin (the owner of its ``status`` provider), or None."""
        return getattr(self.ctx.status_providers.get("triangulation"), "__self__", None)

    def _sparse_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The triangulated points and swept depths, and the dense-flow points
        (:mod:`mapper.node.workers.flow_points`) when that worker is installed (empty without either)."""
        source = self.sparse_source
        if source is None:
            owner = self._triangulation()
            # triangulated points and plane-sweep depths when the plugin has them
            source = getattr(owner, "geometry_points", None) or getattr(owner, "points", None)
        xyz, sigma = (np.zeros((0, 3)), np.zeros(0)) if source is None else source()
        flow = getattr(self.ctx.status_providers.get("dense_flow"), "__self__", None)
        if self.sparse_source is None and flow is not None:  # dense optical-flow points too
            flow_xyz, flow_sigma = flow.geometry_points()
            if len(flow_sigma):
                xyz, sigma = np.concatenate([xyz, flow_xyz]), np.concatenate([sigma, flow_sigma])
        return xyz, sigma

    def _filtered(self, rendered: RenderedKeyframe, others: list[RenderedKeyframe],
                  target: GlobalSemanticMap) -> RenderedKeyframe:
        """``rendered`` with the pixels that fail the consistency check zeroed."""
        if not self.config.rendered_consistency:
            return rendered
        views = others + [r for r, t in self._recent if t is target]
        xyz, sigma = self._sparse_points()
        keep, counts = consistency_mask(rendered, xyz, sigma, views, self.config,
                                        by_views=self._view_agreement())
        for key, value in counts.items():
            self.consistency[key] += value
        return replace(rendered, depth_m=np.where(keep, rendered.depth_m, 0.0).astype(np.float32),
                       confidence=np.where(keep, rendered.confidence, 0.0).astype(np.float32))

    def _integrate_one(self, keyframe: Any, target: GlobalSemanticMap,
                       render: tuple[RenderedKeyframe, float],
                       others: list[tuple[RenderedKeyframe, float]]) -> int:
        if target is not self.ctx.state.global_map:
            self.stale += 1  # a map load during the batch
            return 0
        rendered, render_s = render
        started = time.perf_counter()
        try:
            rendered = self._filtered(rendered, [r for r, _ in others], target)
            stats = target.integrate(
                rendered,
                map_version=None,  # the map already carries a version >= this keyframe's
                pixel_stride=1,
                confidence=rendered.confidence,
                count_keyframe=False,
                carve=False,  # rendered depth: its errors follow the map's (mapper.map.carving)
            )
        except (RuntimeNotReady, ValueError, RuntimeError) as exc:
            self.failed += 1
            self._log.warning("failed", "rendered depth for keyframe at stamp %d failed: %s",
                              keyframe.stamp_ns, exc)
            return 0
        seconds = render_s + time.perf_counter() - started
        self.integrated += 1
        self.points += stats.points
        self.seconds_total += seconds
        log.debug("rendered depth: %d points for keyframe at stamp %d in %.0f ms (%s)",
                  stats.points, keyframe.stamp_ns, 1e3 * seconds, stats.skipped or "ok")
        return 1

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
            "consistency": {"enabled": self.config.rendered_consistency, **self.consistency},
        }
