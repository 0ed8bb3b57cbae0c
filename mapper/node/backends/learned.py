"""The learned backend ``govnesf``: ``segment_points`` and ``render`` from the GOV-NeSF model.

``install_learned_backend(node, runtime)`` attaches the runtime
(:class:`mapper.runtime.model_runtime.ModelRuntime`; one per robot window on the same model,
:mod:`mapper.node.backends.robot_runtimes`) to the node's keyframe windows and registers
:class:`LearnedBackend` as the node's ``govnesf`` segment method and its render backend. What comes
after the backend's answer (the global map's answer beyond the window, surfaces for renders) is
the node's, the same for every backend (:mod:`mapper.node.answers`). With
``global_map.learned_features``, the map voxels a keyframe saw take the model's blended features
just before it leaves the window (:mod:`mapper.node.workers.map_features`, fed by
``ModelRuntime.point_features``); with ``global_map.rendered_depth``, keyframes without input depth
add map points from the model's rendered depth (:mod:`mapper.node.workers.depth_points`).

The heavy work never holds the node's state lock: the window callbacks only record changes, and the
runtime computes on its own state under its own lock. Errors: a missing checkpoint, an empty window
or missing OV features answer ``not_ready`` with the runtime's message (naming the checkpoint path
when that is what is missing); a request the runtime refuses (too many pixels or points) answers
``bad_request``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.node.backends import PointAnswer
from mapper.node.backends.robot_runtimes import RobotRuntimes
from mapper.node.workers.depth_points import RenderedDepthPoints, render_opaque_depth
from mapper.node.workers.map_features import PreEvictionFeatures
from mapper.runtime.model_runtime import ModelRuntime, RuntimeNotReady
from protocol.errors import ProtocolError
from protocol.messages import SegmentPoints

if TYPE_CHECKING:
    from mapper.node.context import NodeContext
    from mapper.node.service import MapperNode

__all__ = ["LearnedBackend", "install_learned_backend", "install_pre_eviction_features", "learned_view_map"]

log = logging.getLogger("mapper.node.backends.learned")


class LearnedBackend:
    """``govnesf`` over a :class:`ModelRuntime` (or anything with its ``segment``,
    ``segment_cosines``, ``render``, ``config`` and ``load_error``)."""

    fallback_to_averaging = True
    """While an RGB-only window's geometry is pending, averaging answers instead
    (:mod:`mapper.node.answers.segment`, ``queries.learned_fallback``)."""

    def __init__(self, runtime: Any) -> None:
        self.runtime = runtime

    @property
    def ready(self) -> bool:
        return not getattr(self.runtime, "load_error", None)

    @property
    def config(self) -> Any:
        return self.runtime.config

    def depth_tested(self, msg: SegmentPoints) -> bool:
        return bool(msg.use_depth)

    def segment(self, msg: SegmentPoints, want_cos: bool) -> PointAnswer:
        """The model's blend at the points; every text's cosines with ``want_cos`` (for the blend
        with the map's)."""
        started = time.perf_counter()
        cos = None
        try:
            if want_cos:
                label, score, cos, timing = self.runtime.segment_cosines(
                    msg.xyz, msg.texts, use_depth=msg.use_depth
                )
            else:
                label, score, timing = self.runtime.segment(msg.xyz, msg.texts, use_depth=msg.use_depth)
        except RuntimeNotReady as exc:
            raise ProtocolError("not_ready", f"segment_points (govnesf): {exc}") from None
        except ValueError as exc:
            raise ProtocolError("bad_request", f"segment_points: {exc}") from None
        timing = dict(timing)
        timing["backend"] = (time.perf_counter() - started) * 1e3
        return PointAnswer(label=label, score=score, timing_ms=timing, cos=cos)

    def render(
        self, K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int, outputs: Sequence[str],
        texts: Sequence[str], surface_depth_m: np.ndarray | None = None,
    ) -> Any:
        """The model's render (:meth:`ModelRuntime.render`), its refusals as wire errors."""
        try:
            return self.runtime.render(K, world_from_cam, width, height, outputs, texts,
                                       surface_depth_m=surface_depth_m)
        except RuntimeNotReady as exc:
            raise ProtocolError("not_ready", f"render: {exc}") from None
        except ValueError as exc:
            raise ProtocolError("bad_request", f"render: {exc}") from None


def install_learned_backend(
    node: MapperNode, runtime: ModelRuntime | RobotRuntimes
) -> RenderedDepthPoints | None:
    """Attach ``runtime`` to ``node``'s windows and serve ``render`` and ``segment_points`` (govnesf).

    Each robot's window gets a runtime of its own on the same loaded model
    (:class:`mapper.node.backends.robot_runtimes.RobotRuntimes`, made here around ``runtime`` unless
    given; the first robot's is ``runtime`` itself). With a loaded model and
    ``global_map.rendered_depth`` (the default), keyframes without input depth also add global-map
    points from the model's rendered depth
    (:class:`mapper.node.workers.depth_points.RenderedDepthPoints`, returned; None otherwise).
    Its worker thread runs from ``node.start()``.

    Call once, after the node is constructed (before ``start()`` for the workers); a map loaded
    earlier is picked up (the runtimes record the keyframes already in the windows).
    """
    ctx = node.ctx
    robots = runtime if isinstance(runtime, RobotRuntimes) else \
        RobotRuntimes(runtime, ctx.config.global_map.max_depth_m)
    with ctx.state.lock:
        robots.attach(ctx.state.window)
    backend = LearnedBackend(robots)
    if robots.load_error:
        # status' "serving" and "segment_methods" leave out a backend that is not ready
        log.warning("learned backend installed without a model: %s", robots.load_error)
    node.segment.register("govnesf", backend)
    node.render.backend = backend
    ctx.memory_providers.append(robots.memory_bytes)
    ctx.status_providers["model"] = robots.stats
    if not robots.load_error and robots.device.type == "cpu":
        # the point answers' compiled kernels, warmed by node.start()
        ctx.kernel_modules += ["mapper.model.ops.sample_kernel", "mapper.model.ops.fusion_kernel",
                               "mapper.model.ops.answer_kernel"]
    if not robots.load_error and ctx.config.global_map.learned_features:
        install_pre_eviction_features(ctx, robots)
    if robots.load_error or not ctx.config.global_map.rendered_depth:
        return None
    points = RenderedDepthPoints(ctx, robots)
    points.install()
    return points


def install_pre_eviction_features(
    ctx: NodeContext, runtime: ModelRuntime | RobotRuntimes
) -> PreEvictionFeatures:
    """Write the model's blended features into the global map before keyframes leave the window
    (:mod:`mapper.node.workers.map_features`); returns the installed worker (its thread runs from
    ``node.start()``; :meth:`PreEvictionFeatures.process_pending` runs it in place)."""

    def features(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        try:  # with input depth, only views whose depth confirms a voxel blend into its feature
            return runtime.point_features(xyz, use_depth=ctx.config.global_map.learned_features_depth_test
                                          and ctx.window_has_depth())
        except RuntimeNotReady:
            return None

    view_features = None
    if ctx.config.queries.evicted_frames_learned:
        min_opacity = ctx.config.global_map.rendered_min_opacity

        def view_features(keyframe: Any, grid_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
            try:
                return learned_view_map(runtime, keyframe, grid_hw, min_opacity)
            except RuntimeNotReady:
                return None

    worker = PreEvictionFeatures(ctx, features, view_features)
    worker.install()
    return worker


def learned_view_map(
    runtime: ModelRuntime | RobotRuntimes,
    keyframe: Any,  # a Keyframe: rgb (H, W, 3), K (4,) in its pixels, world_from_cam (4, 4)
    grid_hw: tuple[int, int],  # (h', w') cells over the whole image
    min_opacity: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The model's blended features at a keyframe's grid of cells: (features (h', w', D) float32,
    valid (h', w') bool), or None where no cell's ray meets a surface. Each cell's ray (through its
    centre) is rendered for depth at the keyframe's pose; where its opacity reaches ``min_opacity``
    the point at that depth takes :meth:`ModelRuntime.point_features` (cross-view blend over the
    window). Raises :class:`RuntimeNotReady` like the runtime."""
    from mapper.geometry.triangulation import backproject

    h, w = (int(v) for v in grid_hw)
    K, depth, _ = render_opaque_depth(runtime, keyframe, (h, w), min_opacity)
    pose = np.asarray(keyframe.world_from_cam, np.float64)
    rows, cols, xyz = backproject(depth, K, pose)
    if rows.size == 0:
        return None
    feats, valid = runtime.point_features(xyz.astype(np.float32))
    out = np.zeros((h, w, feats.shape[1]), np.float32)
    ok = np.zeros((h, w), bool)
    out[rows[valid], cols[valid]] = feats[valid]
    ok[rows[valid], cols[valid]] = True
    return (out, ok) if ok.any() else None
