"""Query handlers backed by the learned model: ``render`` and ``segment_points`` method ``govnesf``.

``install_learned_handlers(node, runtime)`` attaches the runtime to the node's keyframe window and
registers the handlers on the node's dispatch table:

* ``Render`` -> :meth:`mapper.runtime.model_runtime.ModelRuntime.render`; with
  ``model.surface_from_map`` the pixels where a measured surface is known
  (:func:`mapper.node.queries.surface_depth` of the global map's points, or for an RGB-only
  window of ``node.surface_points``: triangulated and plane-sweep points) are rendered at it, the
  others marched;
* ``SegmentPoints`` with ``method == "govnesf"`` -> :meth:`mapper.runtime.model_runtime.ModelRuntime.segment`;
  every other method falls through to the handler that served ``SegmentPoints`` before (read from
  ``node.query_handlers`` at install time, e.g. the ``average`` baselines).

Answers from the whole map: points (``segment_points``) and pixels (``render`` labels and
scores) the window's keyframes do not answer are answered from the global map's fused features
(``MapperNode.answer_from_map``, :func:`mapper.node.queries.render_from_map`); the replies' ``source``
says which answered. With ``global_map.learned_features``, the map voxels a keyframe saw take the
model's blended features just before it leaves the window (:mod:`mapper.node.map_features`,
fed by ``ModelRuntime.point_features``).

The heavy work never holds the node's state lock: the window callbacks only record changes (see
:mod:`mapper.runtime.model_runtime`), and the handlers compute on the runtime's own state under its own lock.
Errors: a missing checkpoint, an empty window or missing OV features answer ``not_ready`` with the
runtime's message (naming the checkpoint path when that is what is missing); a request the
runtime refuses (too many pixels or points) answers ``bad_request``.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from mapper.geometry.planes import Plane
from mapper.node.map_features import PreEvictionFeatures
from mapper.node.plugins.depth_points import RenderedDepthPoints
from mapper.runtime.config import ModelRuntimeConfig
from mapper.runtime.model_runtime import ModelRuntime, RuntimeNotReady
from protocol.errors import ProtocolError
from protocol.messages import Message, Render, RenderResult, Segmentation, SegmentPoints

if TYPE_CHECKING:
    from mapper.node.queries import PlaneCache
    from mapper.node.service import MapperNode, QueryHandler

__all__ = [
    "install_learned_handlers",
    "install_pre_eviction_features",
    "make_render_handler",
    "make_segment_handler",
]

log = logging.getLogger("mapper.node.plugins.learned")


def _text_emb(node: MapperNode, texts: list[str], what: str) -> np.ndarray | None:
    """(T, D) unit text embeddings in the map's space, or None when the node has no encoder."""
    try:
        return np.asarray(node.text_encoder(what).encode(texts), np.float32)
    except ProtocolError:
        return None


def make_segment_handler(
    runtime: ModelRuntime, previous: QueryHandler | None, node: MapperNode | None = None
) -> QueryHandler:
    """A ``SegmentPoints`` handler: ``govnesf`` -> the runtime, other methods -> ``previous``.
    With ``node``, points the window does not see are answered from its global map."""

    def handle_segment(msg: Message) -> Message:
        assert isinstance(msg, SegmentPoints)
        if msg.method != "govnesf":
            if previous is None:
                raise ProtocolError("not_ready", f"segment_points method {msg.method!r} is not served")
            return previous(msg)
        started = time.perf_counter()
        blend = node is not None and node.map_blend(depth_tested=msg.use_depth) > 0 and node.map_radius_m > 0
        cos = None
        try:
            if blend:  # every text's cosine, for the blend with the map's
                label, score, cos, timing = runtime.segment_cosines(
                    msg.xyz, msg.texts, use_depth=msg.use_depth
                )
            else:
                label, score, timing = runtime.segment(msg.xyz, msg.texts, use_depth=msg.use_depth)
        except RuntimeNotReady as exc:
            raise ProtocolError("not_ready", f"segment_points (govnesf): {exc}") from None
        except ValueError as exc:
            raise ProtocolError("bad_request", f"segment_points: {exc}") from None
        timing = dict(timing)
        source = None
        if node is not None:
            t_map = time.perf_counter()
            emb = _text_emb(node, list(msg.texts), "segment_points (govnesf)")
            seen = label >= 0
            if emb is not None:
                label, score, source = node.answer_from_map(
                    np.asarray(msg.xyz, np.float32), emb, label, score, seen, window_cos=cos,
                    depth_tested=msg.use_depth,
                )
            else:
                source = seen.astype(np.uint8)  # 1 = window, 0 = none
            timing["map"] = (time.perf_counter() - t_map) * 1e3
            timing["from_map"] = float(np.count_nonzero(source == 2))
        timing["handler"] = (time.perf_counter() - started) * 1e3
        return Segmentation(label=label, score=score, timing_ms=timing, id=msg.id, source=source)

    return handle_segment


def _surface_points(node: MapperNode, config: ModelRuntimeConfig) -> tuple[np.ndarray, float, str] | None:
    """The points ``render`` takes surfaces from (``model.surface_from_map``): (xyz (N, 3) world,
    footprint in metres, which). "off": none; "on": every global-map point; "auto": the global
    map while at least half of the window's keyframes carry input depth (its surfaces are then
    measured ones), else the node's other measured surface points (``node.surface_points``:
    triangulated points and kept plane-sweep depths, each over ``surface_geometry_footprint``
    voxels), else none."""
    mode = config.surface_from_map
    if mode == "off":
        return None
    if mode == "auto":
        if not node.window_has_depth():  # mostly RGB-only: its geometry
            parts = [np.asarray(provide(), np.float64).reshape(-1, 3) for provide in node.surface_points]
            if not parts:
                return None
            footprint_m = config.surface_geometry_footprint * node.config.global_map.voxel_size_m
            return np.concatenate(parts), footprint_m, "geometry"
    snap = node.state.global_map.snapshot()
    return snap.xyz, snap.voxel_size_m, "map"


def make_render_handler(runtime: ModelRuntime, node: MapperNode | None = None) -> QueryHandler:
    """A ``Render`` handler backed by the runtime. With ``node``, pixels the window does not label
    are answered from its global map (the render then also computes depth and label)."""

    plane_cache: list[PlaneCache] = []  # the planes of the RGB-only geometry, made when first needed

    def handle_render(msg: Message) -> Message:
        assert isinstance(msg, Render)
        started = time.perf_counter()
        semantic = "label" in msg.outputs or "score" in msg.outputs
        outputs = list(msg.outputs)
        more_confident = node is not None and node.config.queries.map_when_more_confident
        if node is not None and semantic:
            wanted = ("depth", "label", "score") if more_confident else ("depth", "label")
            outputs += [o for o in wanted if o not in outputs]
        surface, surface_source, plane_pixels = None, None, 0
        planes: list[Plane] | None = None
        t_surface = time.perf_counter()
        points = _surface_points(node, runtime.config) if node is not None else None
        if points is not None:
            # pixels with a measured surface are rendered at it (docs/RENDERING.md)
            from mapper.node.queries import PlaneCache, map_surface_depth, surface_depth, with_planes

            xyz, footprint_m, surface_source = points
            surface = surface_depth(xyz, footprint_m, np.asarray(msg.K, np.float64), msg.world_from_cam,
                                    msg.width, msg.height, runtime.config)  # fmt: skip
            if surface_source == "geometry" and runtime.config.surface_planes:
                if not plane_cache:
                    plane_cache.append(PlaneCache())
                planes = plane_cache[0].planes(xyz, runtime.config)
                surface, plane_pixels = with_planes(surface, planes, np.asarray(msg.K, np.float64),
                                                    np.asarray(msg.world_from_cam, np.float64))
            if surface_source == "geometry" and runtime.config.surface_map_fill and node is not None:
                snap = node.state.global_map.snapshot()
                fill = map_surface_depth(snap, np.asarray(msg.K, np.float64), msg.world_from_cam,
                                         msg.width, msg.height, runtime.config)  # fmt: skip
                surface = np.where(surface > 0, surface, fill)
            if surface_source == "geometry" and runtime.config.surface_nearest_fill_px > 0:
                from mapper.geometry.splat import fill_nearest

                surface = fill_nearest(surface, runtime.config.surface_nearest_fill_px)
        surface_ms = (time.perf_counter() - t_surface) * 1e3
        try:
            frame = runtime.render(
                msg.K, msg.world_from_cam, msg.width, msg.height, outputs, msg.texts, surface_depth_m=surface
            )
        except RuntimeNotReady as exc:
            raise ProtocolError("not_ready", f"render: {exc}") from None
        except ValueError as exc:
            raise ProtocolError("bad_request", f"render: {exc}") from None
        timing = dict(frame.timing_ms)
        if surface is not None:
            timing["map_surface"] = surface_ms
            timing["surface_pixels"] = float(np.count_nonzero(surface))
            timing["surface_from_geometry"] = float(surface_source == "geometry")
            if planes is not None:
                timing["planes"] = float(len(planes))
                timing["plane_pixels"] = float(plane_pixels)
        source = None
        if node is not None and semantic and frame.label is not None and msg.texts:
            t_map = time.perf_counter()
            emb = _text_emb(node, list(msg.texts), "render")
            window = frame.label >= 0
            source = window.astype(np.uint8)  # 1 = window, 0 = none
            if emb is not None and node.map_radius_m > 0:  # radius 0: window only (no splat either)
                from mapper.node.queries import SOURCE_MAP, render_from_map, render_more_confident

                snap, K = node.state.global_map.snapshot(), np.asarray(msg.K, np.float64)
                lab, cos, answered = render_from_map(
                    snap, K, msg.world_from_cam, msg.width, msg.height, frame.depth_m, ~window, emb,
                    node.map_radius_m,
                )  # fmt: skip
                if more_confident and frame.score is not None and frame.depth_m is not None:
                    m_lab, m_cos, over = render_more_confident(
                        snap, K, msg.world_from_cam, frame.depth_m, frame.label, frame.score, emb,
                        node.map_radius_m,
                    )
                    lab, cos = np.where(over, m_lab, lab), np.where(over[..., None], m_cos, cos)
                    answered |= over
                frame.label = np.where(answered, lab, frame.label).astype(np.int32)
                if frame.score is not None:
                    frame.score = np.where(answered[..., None], cos, frame.score).astype(np.float32)
                source[answered] = SOURCE_MAP
            timing["map"] = (time.perf_counter() - t_map) * 1e3
            timing["from_map"] = float(np.count_nonzero(source == 2))
            if "depth" not in msg.outputs:
                frame.depth_m = None
            if "score" not in msg.outputs:
                frame.score = None
            if "label" not in msg.outputs:
                frame.label = None
                source = None
        timing["handler"] = (time.perf_counter() - started) * 1e3
        log.debug(
            "render %dx%d %s: %.0f ms, %s", msg.width, msg.height, msg.outputs, timing["handler"], frame.stats
        )
        return RenderResult(
            rgb=frame.rgb,
            depth_m=frame.depth_m,
            label=frame.label,
            score=frame.score,
            timing_ms=timing,
            id=msg.id,
            source=source,
        )

    return handle_render


def install_learned_handlers(node: MapperNode, runtime: ModelRuntime) -> RenderedDepthPoints | None:
    """Attach ``runtime`` to ``node``'s window and serve ``render`` and ``segment_points`` (govnesf).

    With a loaded model and ``global_map.rendered_depth`` (the default), keyframes without input
    depth also add global-map points from the model's rendered depth
    (:class:`mapper.node.plugins.depth_points.RenderedDepthPoints`, returned; None otherwise).
    Its worker thread runs from ``node.start()``.

    Call once, after the node is constructed (before ``start()`` for the rendered-depth worker); a
    map loaded earlier is picked up (the runtime records the keyframes already in the window).
    """
    with node.state.lock:
        runtime.attach(node.state.window)
    previous = node.query_handlers.get(SegmentPoints)
    segment = make_segment_handler(runtime, previous, node)
    render = make_render_handler(runtime, node)
    if runtime.load_error:
        # The status reply's "serving" list leaves out handlers marked not_ready.
        render.not_ready = True  # type: ignore[attr-defined]
        segment.not_ready = True  # type: ignore[attr-defined]
        log.warning("learned handlers installed without a model: %s", runtime.load_error)
    node.register_query_handler(SegmentPoints, segment)
    # Listed in status' "segment_methods"; requests reach it through the wrapper above.
    node.register_segment_method("govnesf", segment)  # type: ignore[arg-type]
    node.register_query_handler(Render, render)
    node.memory_providers.append(runtime.memory_bytes)
    node.status_providers["model"] = runtime.stats
    if not runtime.load_error and runtime.device.type == "cpu":
        # the point answers' compiled kernels, warmed by node.start()
        node.kernel_modules += ["mapper.model.ops.sample_kernel", "mapper.model.ops.fusion_kernel",
                                "mapper.model.ops.answer_kernel"]
    if not runtime.load_error and node.config.global_map.learned_features:
        install_pre_eviction_features(node, runtime)
    if runtime.load_error or not node.config.global_map.rendered_depth:
        return None
    points = RenderedDepthPoints(node, runtime)
    points.install()
    return points


def install_pre_eviction_features(node: MapperNode, runtime: ModelRuntime) -> PreEvictionFeatures:
    """Write the model's blended features into the global map before keyframes leave the window
    (:mod:`mapper.node.map_features`); returns the installed worker (its thread runs from
    ``node.start()``; :meth:`PreEvictionFeatures.process_pending` runs it in place)."""

    def features(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        try:
            return runtime.point_features(xyz)
        except RuntimeNotReady:
            return None

    worker = PreEvictionFeatures(node, features)
    worker.install()
    return worker
