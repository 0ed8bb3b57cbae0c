"""The ways of answering a request for points or pixels, behind one small interface.

A *segment backend* (:class:`SegmentBackend`) labels the requested points from what the keyframe
window (and, for averaging, the views that left it) sees: :class:`PointAnswer`, ``label == -1``
where it has no answer. A *render backend* (:class:`RenderBackend`) renders a view. The node's
answers (:mod:`mapper.node.answers.segment`, :mod:`mapper.node.answers.render`) choose the backend
per request (``segment_points``' ``method``) and apply, once and for every backend, what comes after:
answering from the global map beyond the window (:func:`mapper.node.queries.fill_from_map`), the
reply's per-point ``source`` and the timings.

Backends: :mod:`~mapper.node.backends.average` (``average``, ``average_depth``: OpenScene-2D
averaging, torch-free) and :mod:`~mapper.node.backends.learned` (``govnesf``: the learned blend of
:class:`mapper.runtime.model_runtime.ModelRuntime`, for points and renders).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from protocol.messages import SegmentPoints

if TYPE_CHECKING:
    from mapper.map.global_map import GlobalMapSnapshot

__all__ = ["PointAnswer", "RenderBackend", "SegmentBackend", "gather_answers"]


@dataclass
class PointAnswer:
    """A backend's answer for a request's N points, before the global map fills in."""

    label: np.ndarray
    """(N,) int32: the best text per point, -1 where the backend has no answer."""
    score: np.ndarray
    """(N,) float32: that text's cosine (0 where no answer)."""
    timing_ms: dict[str, float] = field(default_factory=dict)
    """The backend's own timings (and counters) for the reply's ``timing_ms``."""
    seen: np.ndarray | None = None
    """(N,) bool: points the backend answered (default: ``label >= 0``)."""
    cos: np.ndarray | None = None
    """(N, T) float32: every text's cosine, when computed (the blend with the map's cosines)."""
    text_emb: np.ndarray | None = None
    """(T, D) float32 unit rows: the texts' embeddings, when the backend made them already."""
    snapshot: GlobalMapSnapshot | None = None
    """The global map snapshot the backend looked at (the fill then uses the same one)."""
    nearest: np.ndarray | None = None
    """(N,) int64: the snapshot's nearest rows with a feature, when looked up already (-1: none)."""
    map_only: np.ndarray | None = None
    """(N,) bool: points only views that left the window answered: their ``source`` is the map."""
    views: np.ndarray | None = None
    """(N,) float32: the window's views that counted for each point (the averaging's)."""
    evicted_views: np.ndarray | None = None
    """(N,) float32: the views of keyframes that left the window that counted (the averaging's:
    its nearest voxel's and the kept views'), 0 where none."""
    evicted_cos: np.ndarray | None = None
    """(N, T) float32: the cosines of those evicted views' mean alone, when asked for."""

    def answered(self) -> np.ndarray:
        """(N,) bool: :attr:`seen`, or ``label >= 0``."""
        return self.seen if self.seen is not None else self.label >= 0


def gather_answers(n: int, parts: Sequence[tuple[np.ndarray, PointAnswer]]) -> PointAnswer:
    """One answer for ``n`` points from answers for parts of them (``(point indices, answer)``,
    each index in one part): each point keeps its part's answer; cosines (and the other optional
    per-point arrays) where every part has them; no snapshot or nearest rows (each part may have
    looked at another snapshot: the map's fill looks again); timings summed."""
    answers = [a for _, a in parts]
    first = answers[0]
    out = PointAnswer(label=np.full(n, -1, np.int32), score=np.zeros(n, np.float32),
                      seen=np.zeros(n, bool), text_emb=first.text_emb)
    for idx, answer in parts:
        out.label[idx] = answer.label
        out.score[idx] = answer.score
        out.seen[idx] = answer.answered()  # type: ignore[index]
        for key, value in answer.timing_ms.items():
            out.timing_ms[key] = out.timing_ms.get(key, 0.0) + float(value)
    for name in ("cos", "map_only", "views", "evicted_views", "evicted_cos"):
        arrays = [getattr(a, name) for a in answers]
        if any(a is None for a in arrays):
            continue
        full = np.zeros((n, *arrays[0].shape[1:]), arrays[0].dtype)
        for (idx, _), array in zip(parts, arrays, strict=True):
            full[idx] = array
        setattr(out, name, full)
    return out


class SegmentBackend(Protocol):
    """Labels points for ``segment_points`` (one or more methods). A backend whose class sets
    ``fallback_to_averaging = True`` is answered by averaging while an RGB-only window's geometry is
    pending (:mod:`mapper.node.answers.segment`)."""

    @property
    def ready(self) -> bool:
        """Whether it can answer at all (a learned backend without a model cannot): ``status``
        lists only ready methods in ``segment_methods``."""
        ...

    def depth_tested(self, msg: SegmentPoints) -> bool:
        """Whether its answer to ``msg`` passed a depth test (the map then answers only where it is
        more confident, never blended)."""
        ...

    def segment(self, msg: SegmentPoints, want_cos: bool) -> PointAnswer:
        """The window's answer for ``msg.xyz`` (every text's cosines too when ``want_cos``; a
        backend may return them anyway). Raises ``ProtocolError`` (``not_ready``, ``bad_request``)."""
        ...


class RenderBackend(Protocol):
    """Renders a view for ``render`` (:mod:`mapper.node.answers.render`)."""

    @property
    def ready(self) -> bool: ...

    @property
    def config(self) -> Any:
        """Its :class:`mapper.runtime.config.ModelRuntimeConfig` (surfaces from the map, planes)."""
        ...

    def render(
        self, K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int, outputs: Sequence[str],
        texts: Sequence[str], surface_depth_m: np.ndarray | None = None,
    ) -> Any:
        """A :class:`mapper.runtime.model_runtime.RenderFrame` (``rgb``, ``depth_m``, ``label``,
        ``score``, ``timing_ms``, ``stats``). Raises ``ProtocolError``."""
        ...
