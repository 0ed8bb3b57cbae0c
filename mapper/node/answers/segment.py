"""``segment_points``: label the requested points, by the method the request names.

The method picks a backend (:mod:`mapper.node.backends`): ``average`` / ``average_depth``
(:class:`mapper.node.backends.average.AveragingBackend`) are always there; ``govnesf`` answers
``not_ready`` until the learned model registers its backend. Whatever the backend, the points it
does not answer are then answered from the global map's snapshot, and where both answer the two
are blended (``queries.map_blend``) or the more confident wins (:func:`mapper.node.queries.fill_from_map`),
here, once, for every backend; the reply's ``source`` says per point which answered.

Do no harm: a backend that falls back to averaging (``govnesf``) is answered by ``average`` (or
``average_depth`` with ``use_depth``) while the window's keyframes mostly lack input depth and the
node's geometry work is pending (``queries.learned_fallback``), and per point, where the
averaging's whole answer is far more decided than the learned one's, the learned answer is mixed
toward it (``queries.learned_toward_average``, :func:`toward_averaging`); the reply's ``fallback``
says so per point. A request's ``settle_timeout_s`` first waits (bounded) for the node's background work;
the reply's ``settled`` says whether none was pending when it answered.
"""

from __future__ import annotations

import time

import numpy as np

from mapper.map.evicted_views import EvictedViewStore
from mapper.map.global_map import GlobalMapSnapshot
from mapper.node.backends import PointAnswer, SegmentBackend
from mapper.node.backends.average import AveragingBackend
from mapper.node.context import NodeContext
from protocol.errors import ProtocolError
from protocol.messages import Message, Segmentation, SegmentPoints

__all__ = ["SegmentAnswers", "answer_from_map", "evicted_frame_cosines", "mix_answers", "toward_averaging"]


class _LearnedNotLoaded:
    """``govnesf`` before the learned model registered its backend: ``not_ready``."""

    ready = False

    def depth_tested(self, msg: SegmentPoints) -> bool:
        return bool(msg.use_depth)

    def segment(self, msg: SegmentPoints, want_cos: bool) -> PointAnswer:
        raise ProtocolError(
            "not_ready",
            "segment_points method 'govnesf' (learned blending): the learned model is not loaded on this "
            "node yet; use method 'average' or 'average_depth'",
        )


def answer_from_map(
    ctx: NodeContext,
    xyz: np.ndarray,  # (N, 3) float32 world metres
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    label: np.ndarray,  # (N,) int32 the window's labels
    score: np.ndarray,  # (N,) float32 the window's scores
    window_seen: np.ndarray,  # (N,) bool: the window answered the point
    snap: GlobalMapSnapshot | None = None,  # the snapshot to use (default: the current one)
    window_cos: np.ndarray | None = None,  # (N, T) the window's cosines (for queries.map_blend)
    depth_tested: bool = False,  # the window's answer already passed a depth test
    nearest: np.ndarray | None = None,  # (N,) int64 the snapshot's nearest rows, if looked up already
    learned: bool = False,  # the window's answer is the learned model's (not averaging's)
    out_cos: np.ndarray | None = None,  # (N, T) float32 holding window_cos: takes the answers' cosines
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the points the window did not answer from the global map's snapshot (nearest point
    with a feature within ``queries.map_radius_voxels`` voxels) and, with ``window_cos``, blend
    the two where both answer (``queries.map_blend``): (label, score, source (N,) uint8), see
    :func:`mapper.node.queries.fill_from_map`. Where the nearest voxel holds views of keyframes
    that left the window (``queries.evicted_views``), the map answers with their average there
    (:func:`mapper.node.queries.evicted_view_cosines`) instead of the voxel's fused feature; for
    the ``learned`` model's answers, mixed with the voxel's own feature (which holds the model's
    blend), ``queries.evicted_views_learned_weight``. Points nothing answers take the kept views of
    evicted keyframes without depth (``queries.evicted_frames_mb``) where one sees them, for every
    method (a depth-tested answer only there, unless ``queries.evicted_frames_depth_tested`` is
    "first" and the window lacks depth: then before the map's voxels, as the learned answer).
    ``out_cos`` (the window's cosines where it answered) takes every text's cosine of the answer
    where the map answered or blended."""
    from mapper.node.queries import evicted_view_cosines, fill_from_map

    gmap = ctx.state.global_map
    if snap is None:
        snap = gmap.snapshot()
    map_cos = None
    if len(gmap.evicted) and ctx.map_radius_m > 0:  # the evicted views' answer at the map's voxels
        if nearest is None:
            nearest = snap.nearest_with_feature(xyz, ctx.map_radius_m)
        map_cos = evicted_view_cosines(gmap.evicted, snap, nearest, text_emb)
    frames_cos = None
    if depth_tested:  # in a window without depth (queries.evicted_frames_depth_tested)
        first = ctx.config.queries.evicted_frames_depth_tested == "first" and not ctx.window_has_depth()
    else:
        first = learned
    if first:  # the kept views of evicted keyframes without depth, before the map's voxels
        if nearest is None and ctx.map_radius_m > 0 and snap.n_with_features > 0:
            nearest = snap.nearest_with_feature(xyz, ctx.map_radius_m)
        frames_cos = evicted_frame_cosines(ctx, gmap.evicted, snap, nearest, xyz, text_emb, learned=learned)
        if frames_cos is not None:
            map_cos = _overlaid(map_cos, frames_cos)
    label, score, source = fill_from_map(
        snap, xyz, text_emb, label, score, window_seen, ctx.map_radius_m,
        more_confident=ctx.config.queries.map_when_more_confident, window_cos=window_cos,
        blend=ctx.map_blend(depth_tested=depth_tested), nearest=nearest, map_cos=map_cos,
        map_cos_weight=ctx.config.queries.evicted_views_learned_weight if learned else 1.0, out_cos=out_cos)
    from mapper.node.queries import SOURCE_MAP, SOURCE_NONE, best_text

    def take(todo: np.ndarray, cos: np.ndarray) -> None:  # the kept views' answer (cos) at those points
        label[todo], score[todo] = best_text(cos, np.ones(todo.shape[0], bool))
        source[todo] = SOURCE_MAP
        if out_cos is not None:
            out_cos[todo] = cos

    if frames_cos is not None:  # no map voxel near, unseen by the window: the kept views answer
        todo = np.flatnonzero((source == SOURCE_NONE) & frames_cos[1])
        take(todo, frames_cos[0][todo])
    elif depth_tested and len(gmap.evicted.frames):
        # a depth-tested answer never mixes views without depth in, but a point nothing else
        # answers takes the kept views' answer rather than none
        none = np.flatnonzero(source == SOURCE_NONE)
        if none.size:
            sub = evicted_frame_cosines(ctx, gmap.evicted, snap, None if nearest is None else nearest[none],
                                        np.asarray(xyz)[none], text_emb, learned=learned)
            if sub is not None:
                take(none[sub[1]], sub[0][sub[1]])
    return label, score, source


def _overlaid(
    under: tuple[np.ndarray, np.ndarray] | None, over: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Map cosines ``(cos (N, T), given (N,))``: ``over``'s where it gives one, else ``under``'s."""
    if under is None:
        return over
    cos = np.where(over[1][:, None], over[0], under[0])
    return cos, over[1] | under[1]


def evicted_frame_cosines(
    ctx: NodeContext,
    store: EvictedViewStore,
    snap: GlobalMapSnapshot,
    nearest: np.ndarray | None,  # (N,) int64 nearest map rows with a feature (-1: none), or None
    xyz: np.ndarray,  # (N, 3) float32
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    learned: bool = False,  # for the learned method: the kept views' learned maps where they have one
) -> tuple[np.ndarray, np.ndarray] | None:
    """The evicted views' answer at each point that a kept view of an evicted keyframe without
    depth counts for (``queries.evicted_frames_mb``, :mod:`mapper.map.evicted_frames`): cosines
    (N, T) of the mean of those views' samples at the point together with the ``all`` views of its
    nearest voxel (each weighted by its views), and (N,) bool where given; None where none is."""
    frames = store.frames
    if ctx.evicted_views is None or not ctx.evicted_views.both or frames.dim != text_emb.shape[1] \
            or len(frames) == 0:
        return None
    from mapper.map.evicted_frames import merged_prior

    n = xyz.shape[0]
    rows, mean, count = frames.means(np.asarray(xyz, np.float32), learned=learned)
    if rows.size == 0:
        return None
    voxel = None
    if nearest is not None and snap.keys is not None and len(store) and store.dim == text_emb.shape[1]:
        hit = nearest[rows] >= 0
        v_mean, v_count = store.lookup(snap.keys[nearest[rows][hit]], "all")
        voxel = (v_mean, np.where(hit, np.cumsum(hit) - 1, -1).astype(np.int64),
                 np.zeros(rows.shape[0], np.float32))
        voxel[2][hit] = v_count
    merged = merged_prior(rows.shape[0], voxel, np.arange(rows.shape[0]), mean, count, text_emb.shape[1])
    assert merged is not None  # every row has a kept view
    feat = merged[0]
    feat /= np.maximum(np.linalg.norm(feat, axis=1, keepdims=True), 1e-12)
    cos = np.zeros((n, text_emb.shape[0]), np.float32)
    cos[rows] = feat @ np.asarray(text_emb, np.float32).T
    given = np.zeros(n, bool)
    given[rows] = True
    return cos, given


def mix_answers(learned: PointAnswer, averaging: PointAnswer, weight: float | np.ndarray) -> PointAnswer:
    """The learned answer mixed with the averaging's over the same window (``queries.learned_average_mix``,
    ``queries.learned_evicted_views``): where both answer, the best text of ``(1 - weight) * learned +
    weight * averaging`` cosines (score: that cosine; ``weight`` one for all points or (N,) per
    point); where only one answers, its answer (a point only views that left the window saw keeps
    the averaging's ``map_only``). Without both answers' cosines, the learned answer as it is."""
    if learned.cos is None or averaging.cos is None or learned.cos.shape != averaging.cos.shape:
        return learned
    seen_l, seen_a = learned.answered(), averaging.answered()
    w = np.broadcast_to(np.asarray(weight, np.float32), seen_l.shape)
    cos = np.where(seen_l[:, None], learned.cos, averaging.cos).astype(np.float32, copy=True)
    both = seen_l & seen_a
    wb = w[both][:, None]
    cos[both] = (np.float32(1.0) - wb) * learned.cos[both] + wb * averaging.cos[both]
    seen = seen_l | seen_a
    label = np.where(seen, np.argmax(cos, axis=1), -1).astype(np.int32)
    score = np.where(seen, cos[np.arange(cos.shape[0]), np.maximum(label, 0)], 0.0).astype(np.float32)
    map_only = None
    if averaging.map_only is not None:
        map_only = averaging.map_only & ~seen_l
    timing = {**learned.timing_ms, "mixed": float(np.count_nonzero(both))}
    return PointAnswer(label=label, score=score, timing_ms=timing, seen=seen, cos=cos,
                       text_emb=learned.text_emb if learned.text_emb is not None else averaging.text_emb,
                       snapshot=learned.snapshot if learned.snapshot is not None else averaging.snapshot,
                       nearest=learned.nearest if learned.snapshot is not None else averaging.nearest,
                       map_only=map_only)


def _top_margin(cos: np.ndarray) -> np.ndarray:
    """(N,) the best text's cosine minus the second best's (the best's alone for one text)."""
    if cos.shape[1] < 2:
        return cos.max(axis=1) if cos.shape[1] else np.zeros(cos.shape[0], np.float32)
    top = np.partition(cos, cos.shape[1] - 2, axis=1)[:, -2:]
    return (top[:, 1] - top[:, 0]).astype(np.float32)


def toward_averaging(
    label: np.ndarray,  # (N,) int32 the learned answer (-1: none)
    score: np.ndarray,  # (N,) float32
    cos: np.ndarray,  # (N, T) float32 its cosines (rows where it answers)
    a_label: np.ndarray,  # (N,) int32 the averaging's answer (-1: none)
    a_score: np.ndarray,  # (N,) float32
    a_cos: np.ndarray,  # (N, T) float32 its cosines
    ratio: float,  # > 0: how many times the learned margin the averaging's must exceed
    ramp: float,  # > 0: the lead over which the averaging's weight goes from 0 to 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Do no harm per point (``queries.learned_toward_average``): where both answer a point and the
    averaging's margin (best text's cosine minus the second's) exceeds ``ratio`` times the learned
    answer's by ``d`` > 0, the best text of ``(1 - w)`` x the learned cosines + ``w`` x the
    averaging's, ``w = min(1, d / ramp)``; elsewhere the learned answer stays. A point only the
    averaging answers takes its answer. Returns (label, score, (N,) bool where the label is now the
    averaging's and was not the learned one's)."""
    seen_l, seen_a = label >= 0, a_label >= 0
    out_label = np.array(label, np.int32, copy=True)
    out_score = np.array(score, np.float32, copy=True)
    both = np.flatnonzero(seen_l & seen_a)
    if both.size:
        lc, ac = np.asarray(cos, np.float32)[both], np.asarray(a_cos, np.float32)[both]
        lead = _top_margin(ac) - np.float32(ratio) * _top_margin(lc)
        w = np.clip(lead / np.float32(ramp), 0.0, 1.0)[:, None]
        moved = np.flatnonzero(w[:, 0] > 0)
        mixed = (np.float32(1.0) - w[moved]) * lc[moved] + w[moved] * ac[moved]
        best = np.argmax(mixed, axis=1)
        out_label[both[moved]] = best.astype(np.int32)
        out_score[both[moved]] = mixed[np.arange(moved.size), best]
    only_a = np.flatnonzero(~seen_l & seen_a)
    out_label[only_a] = a_label[only_a]
    out_score[only_a] = a_score[only_a]
    took = (out_label != label) & (out_label == a_label)
    return out_label, out_score, took


def _map_only_to_map(window: PointAnswer, source: np.ndarray) -> None:
    """Points only views that left the window saw (``window.map_only``) have the map as source."""
    if window.map_only is not None:
        from mapper.node.queries import SOURCE_MAP, SOURCE_WINDOW

        source[window.map_only & (source == SOURCE_WINDOW)] = SOURCE_MAP


def _evicted_answer(averaging: PointAnswer, where: np.ndarray) -> PointAnswer:
    """The evicted views' own answer from an averaging answer made ``want_evicted``: their mean's
    cosines where any counts (``evicted_views`` > 0) and ``where`` (N,) bool."""
    assert averaging.evicted_cos is not None and averaging.evicted_views is not None
    from mapper.node.queries import best_text

    seen = (averaging.evicted_views > 0) & where
    label, score = best_text(averaging.evicted_cos, seen)
    return PointAnswer(label=label, score=score, seen=seen, cos=averaging.evicted_cos,
                       text_emb=averaging.text_emb, snapshot=averaging.snapshot, nearest=averaging.nearest)


class SegmentAnswers:
    """The ``segment_points`` handler and its backends by method name."""

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx
        self.backends: dict[str, SegmentBackend] = {
            "govnesf": _LearnedNotLoaded(),
            "average": AveragingBackend(ctx, use_depth=False),
            "average_depth": AveragingBackend(ctx, use_depth=True),
        }
        """Method name -> backend (the learned model registers ``govnesf``)."""

    def register(self, method: str, backend: SegmentBackend) -> None:
        """Serve ``segment_points`` requests naming ``method`` with ``backend`` (replacing any)."""
        self.backends[method] = backend

    def ready_methods(self) -> list[str]:
        """The methods that can answer (``status``: ``segment_methods``)."""
        return sorted(m for m, b in self.backends.items() if b.ready)

    def handle(self, msg: Message) -> Message:
        """The reply to one ``segment_points`` (module docstring)."""
        assert isinstance(msg, SegmentPoints)
        backend = self.backends.get(msg.method)
        if backend is None:
            raise ProtocolError(
                "bad_request", f"method: {msg.method!r} unknown; served: {', '.join(sorted(self.backends))}"
            )
        ctx = self.ctx
        started = time.perf_counter()
        ctx.wait_settled(msg.settle_timeout_s)
        # the map's answer at points in paged tiles comes from those tiles: page them in
        ctx.state.global_map.page_in_near(np.asarray(msg.xyz, np.float32), ctx.map_radius_m)
        depth_tested = backend.depth_tested(msg)
        want_cos = ctx.map_blend(depth_tested=depth_tested) > 0 and ctx.map_radius_m > 0
        learned = bool(getattr(backend, "fallback_to_averaging", False))
        ratio = ctx.config.queries.learned_toward_average if learned else 0.0
        window, fell_back, other = self._window_answer(backend, msg, want_cos or ratio > 0, depth_tested)
        t_map = time.perf_counter()
        seen = window.answered()
        emb = window.text_emb if window.text_emb is not None else self._text_emb(msg)
        out_cos = None
        if ratio > 0 and not fell_back and emb is not None and window.cos is not None:
            out_cos = np.array(window.cos, np.float32, copy=True)  # the answer's cosines, map rows filled in
        if emb is None:  # no text encoder for the map's space: the backend's answer alone
            label, score, source = window.label, window.score, seen.astype(np.uint8)  # 1 window, 0 none
        else:
            label, score, source = answer_from_map(
                ctx, np.asarray(msg.xyz, np.float32), emb, window.label, window.score, seen,
                window.snapshot, window_cos=window.cos, depth_tested=depth_tested, nearest=window.nearest,
                learned=learned and not fell_back, out_cos=out_cos,
            )
        _map_only_to_map(window, source)
        timing = dict(window.timing_ms)
        took = None
        if out_cos is not None and emb is not None:
            t_avg = time.perf_counter()
            answer = (label, score, source, out_cos)
            label, score, source, took = self._toward_averaging(msg, other, depth_tested, emb, answer, ratio)
            timing["toward_average"] = (time.perf_counter() - t_avg) * 1e3
            timing["from_average"] = float(np.count_nonzero(took))
        done = time.perf_counter()
        timing["map"] = (done - t_map) * 1e3
        timing["from_map"] = float(np.count_nonzero(source == 2))
        timing["handler"] = (done - started) * 1e3
        fallback = None
        if learned:
            fallback = np.full(label.shape[0], int(fell_back), np.uint8)
            if took is not None:
                fallback[took] = 1
        return Segmentation(label=label, score=score, timing_ms=timing, id=msg.id, source=source,
                            settled=ctx.settled(), fallback=fallback)

    def _window_answer(
        self, backend: SegmentBackend, msg: SegmentPoints, want_cos: bool, depth_tested: bool
    ) -> tuple[PointAnswer, bool, PointAnswer | None]:
        """The backend's answer, or, do no harm (``queries.learned_fallback``), the averaging's for
        a backend that falls back to it (the learned one) while an RGB-only window's geometry is
        pending; whether it fell back; and the averaging's window answer where it was asked (for
        the learned one's mixes). Averaging that cannot answer (e.g. no depth test possible) leaves
        the answer to the backend."""
        learned = getattr(backend, "fallback_to_averaging", False)
        averaging = self.backends["average_depth" if depth_tested else "average"]
        if learned and self._learned_not_ready():
            try:
                window = averaging.segment(msg, want_cos)
            except ProtocolError:
                return backend.segment(msg, want_cos), False, None
            window.timing_ms["fallback"] = 1.0
            return window, True, None
        q = self.ctx.config.queries
        mix, share = q.learned_average_mix, q.learned_evicted_views
        if self.ctx.map_blend(depth_tested=depth_tested) > 0:  # a window with depth, no depth test
            share = q.learned_evicted_views_blended
        if share > 0 and not self._has_evicted_views():
            share = 0.0
        if not learned or (mix <= 0 and share <= 0):
            return backend.segment(msg, want_cos), False, None
        answer = backend.segment(msg, True)
        started = time.perf_counter()
        try:
            if share > 0 and isinstance(averaging, AveragingBackend):
                other = averaging.segment(msg, True, want_evicted=True)
            else:
                other = averaging.segment(msg, True)
        except ProtocolError:  # averaging cannot answer (e.g. no depth test possible): the model's alone
            return answer, False, None
        weight: float | np.ndarray = mix
        if share > 0 and other.views is not None and other.evicted_views is not None \
                and other.evicted_cos is not None:
            # the views of keyframes that left count for a point by their share of its views, the
            # model's answer standing for the window's: (1 - s) x model + s x their mean
            evicted = other.evicted_views
            part = share * evicted / np.maximum(evicted + other.views, np.float32(1e-6))
            # only where the model answers: the points it does not see keep the map's answer
            answer = mix_answers(answer, _evicted_answer(other, answer.answered()), part)
        mixed = mix_answers(answer, other, weight) if mix > 0 else answer
        mixed.timing_ms["mix_average"] = (time.perf_counter() - started) * 1e3
        return mixed, False, other

    def _toward_averaging(
        self, msg: SegmentPoints, other: PointAnswer | None, depth_tested: bool, emb: np.ndarray,
        answer: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], ratio: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Do no harm per point (``queries.learned_toward_average``): the learned ``answer``
        (label, score, source, cosines: after the map's) mixed with the averaging's whole answer
        (its window's, ``other`` when asked already, then the map's as for its own method) by
        :func:`toward_averaging`; returns (label, score, source, (N,) bool where the averaging's
        answer was taken). Averaging that cannot answer leaves the learned answer as it is."""
        label, score, source, cos = answer
        if other is None or other.cos is None:
            try:
                other = self.backends["average_depth" if depth_tested else "average"].segment(msg, True)
            except ProtocolError:
                return label, score, source, np.zeros(label.shape[0], bool)
        if other.cos is None or other.cos.shape != cos.shape:
            return label, score, source, np.zeros(label.shape[0], bool)
        a_cos = np.array(other.cos, np.float32, copy=True)
        a_label, a_score, a_source = answer_from_map(
            self.ctx, np.asarray(msg.xyz, np.float32), emb, other.label, other.score, other.answered(),
            other.snapshot, window_cos=other.cos, depth_tested=depth_tested, nearest=other.nearest,
            out_cos=a_cos)
        _map_only_to_map(other, a_source)
        new_label, new_score, took = toward_averaging(label, score, cos, a_label, a_score, a_cos, ratio,
                                                      self.ctx.config.queries.learned_toward_average_ramp)
        source = np.where(took, a_source, source).astype(np.uint8)
        return new_label, new_score, source, took

    def _has_evicted_views(self) -> bool:
        """Whether views of keyframes that left the window are kept for the averaging that would
        mix (``queries.learned_evicted_views``)."""
        ctx = self.ctx
        if ctx.evicted_views is None:
            return False
        store = ctx.state.global_map.evicted
        return len(store) > 0 or (len(store.frames) > 0 and ctx.config.queries.point_occlusion)

    def _learned_not_ready(self) -> bool:
        """``queries.learned_fallback``: "geometry": an RGB-only window's geometry work is pending;
        "pending": that, or any background work; "off": never."""
        mode, ctx = self.ctx.config.queries.learned_fallback, self.ctx
        if mode == "off":
            return False
        if not ctx.window_has_depth() and ctx.geometry_pending() > 0:
            return True
        return mode == "pending" and not ctx.settled()

    def _text_emb(self, msg: SegmentPoints) -> np.ndarray | None:
        """(T, D) unit text embeddings in the map's space, or None when the node has no encoder."""
        try:
            return np.asarray(self.ctx.text_encoder(f"segment_points ({msg.method})").encode(list(msg.texts)),
                              np.float32)
        except ProtocolError:
            return None
