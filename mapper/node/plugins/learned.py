"""Query handlers backed by the learned model: ``render`` and ``segment_points`` method ``govnesf``.

``install_learned_handlers(node, runtime)`` attaches the runtime to the node's keyframe window and
registers the handlers on the node's dispatch table:

* ``Render`` -> :meth:`mapper.runtime.model_runtime.ModelRuntime.render`;
* ``SegmentPoints`` with ``method == "govnesf"`` -> :meth:`mapper.runtime.model_runtime.ModelRuntime.segment`;
  every other method falls through to the handler that served ``SegmentPoints`` before (read from
  ``node.query_handlers`` at install time, e.g. the ``average`` baselines).

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

from mapper.node.plugins.depth_points import RenderedDepthPoints
from mapper.runtime.model_runtime import ModelRuntime, RuntimeNotReady
from protocol.errors import ProtocolError
from protocol.messages import Message, Render, RenderResult, Segmentation, SegmentPoints

if TYPE_CHECKING:
    from mapper.node.service import MapperNode, QueryHandler

__all__ = ["install_learned_handlers", "make_render_handler", "make_segment_handler"]

log = logging.getLogger("mapper.node.plugins.learned")


def make_segment_handler(runtime: ModelRuntime, previous: QueryHandler | None) -> QueryHandler:
    """A ``SegmentPoints`` handler: ``govnesf`` -> the runtime, other methods -> ``previous``."""

    def handle_segment(msg: Message) -> Message:
        assert isinstance(msg, SegmentPoints)
        if msg.method != "govnesf":
            if previous is None:
                raise ProtocolError("not_ready", f"segment_points method {msg.method!r} is not served")
            return previous(msg)
        started = time.perf_counter()
        try:
            label, score, timing = runtime.segment(msg.xyz, msg.texts, use_depth=msg.use_depth)
        except RuntimeNotReady as exc:
            raise ProtocolError("not_ready", f"segment_points (govnesf): {exc}") from None
        except ValueError as exc:
            raise ProtocolError("bad_request", f"segment_points: {exc}") from None
        timing = dict(timing)
        timing["handler"] = (time.perf_counter() - started) * 1e3
        return Segmentation(label=label, score=score, timing_ms=timing, id=msg.id)

    return handle_segment


def make_render_handler(runtime: ModelRuntime) -> QueryHandler:
    """A ``Render`` handler backed by the runtime."""

    def handle_render(msg: Message) -> Message:
        assert isinstance(msg, Render)
        started = time.perf_counter()
        try:
            frame = runtime.render(msg.K, msg.world_from_cam, msg.width, msg.height, msg.outputs, msg.texts)
        except RuntimeNotReady as exc:
            raise ProtocolError("not_ready", f"render: {exc}") from None
        except ValueError as exc:
            raise ProtocolError("bad_request", f"render: {exc}") from None
        timing = dict(frame.timing_ms)
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
    segment = make_segment_handler(runtime, previous)
    render = make_render_handler(runtime)
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
    if runtime.load_error or not node.config.global_map.rendered_depth:
        return None
    points = RenderedDepthPoints(node, runtime)
    points.install()
    return points
