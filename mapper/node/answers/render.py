"""``render``: colour, depth and semantics of a view, from a render backend (the learned model).

Before the backend renders, the pixels where a measured surface is known are given to it as
surface depth (``model.surface_from_map``: the global map's points, or for an RGB-only window the
node's other surface points: triangulated and plane-sweep points, with planes fitted to them);
after it renders, the pixels its window does not label are labelled from the global map's fused
features (:func:`mapper.node.queries.render_from_map`), and where the map is more confident it
wins (``queries.map_when_more_confident``); the reply's ``source`` says which answered. Without a
backend ``render`` answers ``not_ready``.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.node.backends import RenderBackend
from mapper.node.context import NodeContext
from protocol.errors import ProtocolError
from protocol.messages import Message, Render, RenderResult

if TYPE_CHECKING:
    from mapper.geometry.planes import Plane
    from mapper.node.queries import PlaneCache

__all__ = ["RenderAnswers"]

log = logging.getLogger("mapper.node.answers.render")


class RenderAnswers:
    """The ``render`` handler over the registered render backend."""

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx
        self.backend: RenderBackend | None = None
        self._plane_cache: list[PlaneCache] = []  # the RGB-only geometry's planes, made when first needed

    @property
    def not_ready(self) -> bool:
        """No backend, or one that cannot render (``status`` leaves ``render`` out of ``serving``)."""
        return self.backend is None or not self.backend.ready

    def handle(self, msg: Message) -> Message:
        """The reply to one ``render`` (module docstring)."""
        assert isinstance(msg, Render)
        backend = self.backend
        if backend is None:
            raise ProtocolError(
                "not_ready",
                "render (rendering) is not served by this node yet: the model stage is not installed; "
                "status, save and load are served",
            )
        started = time.perf_counter()
        self.ctx.wait_settled(msg.settle_timeout_s)
        semantic = "label" in msg.outputs or "score" in msg.outputs
        outputs = list(msg.outputs)
        more_confident = self.ctx.config.queries.map_when_more_confident
        if semantic:
            wanted = ("depth", "label", "score") if more_confident else ("depth", "label")
            outputs += [o for o in wanted if o not in outputs]
        t_surface = time.perf_counter()
        surface, surface_timing = self._surface(msg, backend.config)
        surface_ms = (time.perf_counter() - t_surface) * 1e3
        frame = backend.render(msg.K, msg.world_from_cam, msg.width, msg.height, outputs, msg.texts or [],
                               surface_depth_m=surface)
        timing = dict(frame.timing_ms)
        if surface is not None:
            timing["map_surface"] = surface_ms
            timing.update(surface_timing)
        source = None
        if semantic and frame.label is not None and msg.texts:
            t_map = time.perf_counter()
            source = self._labels_from_map(msg, frame, more_confident)
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
        log.debug("render %dx%d %s: %.0f ms, %s", msg.width, msg.height, msg.outputs, timing["handler"],
                  frame.stats)
        return RenderResult(rgb=frame.rgb, depth_m=frame.depth_m, label=frame.label, score=frame.score,
                            timing_ms=timing, id=msg.id, source=source, settled=self.ctx.settled())

    def _surface_points(self, config: Any) -> tuple[np.ndarray, float, str] | None:
        """The points ``render`` takes surfaces from (``model.surface_from_map``): (xyz (N, 3) world,
        footprint in metres, which). "off": none; "on": every global-map point; "auto": the global
        map while at least half of the window's keyframes carry input depth (its surfaces are then
        measured ones), else the node's other measured surface points (``ctx.surface_points``:
        triangulated points and kept plane-sweep depths, each over ``surface_geometry_footprint``
        voxels), else none."""
        ctx = self.ctx
        mode = config.surface_from_map
        if mode == "off":
            return None
        if mode == "auto" and not ctx.window_has_depth():  # mostly RGB-only: its geometry
            parts = [np.asarray(provide(), np.float64).reshape(-1, 3) for provide in ctx.surface_points]
            if not parts:
                return None
            footprint_m = config.surface_geometry_footprint * ctx.config.global_map.voxel_size_m
            return np.concatenate(parts), footprint_m, "geometry"
        snap = ctx.state.global_map.snapshot()
        return snap.xyz, snap.voxel_size_m, "map"

    def _surface(self, msg: Render, config: Any) -> tuple[np.ndarray | None, dict[str, float]]:
        """The (H, W) surface depth the backend renders at (0: march), or None; and its timings."""
        points = self._surface_points(config)
        if points is None:
            return None, {}
        # pixels with a measured surface are rendered at it (docs/concepts/rendering.md)
        from mapper.node.queries import PlaneCache, map_surface_depth, surface_depth, with_planes

        xyz, footprint_m, surface_source = points
        K = np.asarray(msg.K, np.float64)
        surface = surface_depth(xyz, footprint_m, K, msg.world_from_cam, msg.width, msg.height, config)
        planes: list[Plane] | None = None
        plane_pixels = 0
        if surface_source == "geometry" and config.surface_planes:
            if not self._plane_cache:
                self._plane_cache.append(PlaneCache())
            planes = self._plane_cache[0].planes(xyz, config)
            pose = np.asarray(msg.world_from_cam, np.float64)
            surface, plane_pixels = with_planes(surface, planes, K, pose)
        if surface_source == "geometry" and config.surface_map_fill:
            snap = self.ctx.state.global_map.snapshot()
            fill = map_surface_depth(snap, K, msg.world_from_cam, msg.width, msg.height, config)
            surface = np.where(surface > 0, surface, fill)
        if surface_source == "geometry" and config.surface_nearest_fill_px > 0:
            from mapper.geometry.splat import fill_nearest

            surface = fill_nearest(surface, config.surface_nearest_fill_px)
        timing = {
            "surface_pixels": float(np.count_nonzero(surface)),
            "surface_from_geometry": float(surface_source == "geometry"),
        }
        if planes is not None:
            timing["planes"] = float(len(planes))
            timing["plane_pixels"] = float(plane_pixels)
        return surface, timing

    def _labels_from_map(self, msg: Render, frame: Any, more_confident: bool) -> np.ndarray:
        """Label the pixels the window leaves (and, ``more_confident``, those the map knows better)
        from the global map, in place on ``frame``; returns the (H, W) uint8 ``source``."""
        ctx = self.ctx
        window = frame.label >= 0
        source = window.astype(np.uint8)  # 1 = window, 0 = none
        try:
            emb = np.asarray(ctx.text_encoder("render").encode(list(msg.texts or [])), np.float32)
        except ProtocolError:
            return source
        if ctx.map_radius_m <= 0:  # radius 0: window only (no splat either)
            return source
        from mapper.node.queries import SOURCE_MAP, render_from_map, render_more_confident

        snap, K = ctx.state.global_map.snapshot(), np.asarray(msg.K, np.float64)
        lab, cos, answered = render_from_map(snap, K, msg.world_from_cam, msg.width, msg.height,
                                             frame.depth_m,
                                             ~window, emb, ctx.map_radius_m)
        if more_confident and frame.score is not None and frame.depth_m is not None:
            m_lab, m_cos, over = render_more_confident(snap, K, msg.world_from_cam, frame.depth_m,
                                                       frame.label,
                                                       frame.score, emb, ctx.map_radius_m)
            lab, cos = np.where(over, m_lab, lab), np.where(over[..., None], m_cos, cos)
            answered |= over
        frame.label = np.where(answered, lab, frame.label).astype(np.int32)
        if frame.score is not None:
            frame.score = np.where(answered[..., None], cos, frame.score).astype(np.float32)
        source[answered] = SOURCE_MAP
        return source
