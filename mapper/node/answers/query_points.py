"""``query_points``: "find the chair" on the global map's snapshot, with an answer cache.

An answer is reused when it may be (same map version, or, while frames are arriving, a stale answer
within ``queries.answer_max_age_s``, then recomputed by the answer-refresh thread), else computed on
the current snapshot by :func:`mapper.node.queries.query_points`. Once the stream stops (no frame for
``limits.ingest_active_s``) every answer is of the current map. A request with ``settle_timeout_s``
first waits (bounded) for the node's background work and is answered from the current map; the
reply's ``settled`` says whether none was pending.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.node.context import NodeContext
from protocol.errors import ProtocolError
from protocol.messages import Message, Points, QueryPoints

if TYPE_CHECKING:
    from mapper.map.tile_store import TileInfo
    from mapper.node.queries import AnswerCache, AnswerKey, BlockLabelCache

__all__ = ["QueryPointsAnswers"]

log = logging.getLogger("mapper.node.service")


def _region(msg: QueryPoints) -> tuple[np.ndarray, np.ndarray] | None:
    """The request's box (``region_min``, ``region_max``), or None."""
    if msg.region_min is None or msg.region_max is None:
        return None
    return np.asarray(msg.region_min, np.float64), np.asarray(msg.region_max, np.float64)


def _tile_filter(encoder: Any, msg: QueryPoints, rule: str = "exact") -> Callable[[TileInfo], bool]:
    """Whether a paged tile may hold a match of ``msg`` (``global_map.tile_skip``: "exact":
    :func:`mapper.map.tile_store.cone_may_match` on its feature summary; "centroids":
    :func:`mapper.map.tile_store.centroids_may_match`, approximate). The negatives are those
    :func:`mapper.node.queries.query_points` uses, or fewer where it falls back to the default set
    (fewer negatives only let more tiles through), so with "exact" a skipped tile holds no match."""
    from mapper.map.tile_store import centroids_may_match, cone_may_match
    from mapper.node.queries import DEFAULT_NEGATIVES, NEGATIVE_DROP_SIMILARITY, normalise_query

    text_emb = np.asarray(encoder.encode([normalise_query(t) for t in msg.texts]), np.float32)
    negatives = [normalise_query(n) for n in (DEFAULT_NEGATIVES if msg.negatives is None else msg.negatives)]
    neg_emb = np.asarray(encoder.encode(negatives), np.float32) if negatives else text_emb[:0]
    if neg_emb.shape[0]:
        neg_emb = neg_emb[(neg_emb @ text_emb.T).max(axis=1) < NEGATIVE_DROP_SIMILARITY]

    def may_match(info: TileInfo) -> bool:
        if info.centroids.shape[1] != text_emb.shape[1]:
            return info.centroids.shape[0] > 0  # the query reports the mismatch
        if rule == "centroids":
            return centroids_may_match(info.centroids, text_emb, neg_emb, msg.min_score)
        return cone_may_match(info.centroids, info.least_cos, text_emb, neg_emb, msg.min_score)

    return may_match


class QueryPointsAnswers:
    """The ``query_points`` handler, its caches and its refresh worker (registered in
    ``ctx.workers`` as ``answer-refresh``)."""

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx
        self._label_cache: BlockLabelCache | None = None
        """Per-block scoring, reused across map versions (``queries.label_cache_blocks``; made by
        the first query: :mod:`mapper.node.queries` imports SciPy)."""
        self._answer_cache: AnswerCache | None = None
        """Recent answers (``queries.answer_max_age_s``); made with the label cache."""
        self._lock = threading.Lock()
        """Guards making the two caches and the refresh bookkeeping."""
        self._refresh_jobs: queue.Queue[tuple[AnswerKey, QueryPoints]] = queue.Queue(
            maxsize=max(1, ctx.config.queries.answer_cache_entries)
        )
        """Stale answers to recompute (the answer-refresh thread)."""
        self._refresh_pending: set[AnswerKey] = set()
        self.refreshes = 0
        ctx.workers.append(("answer-refresh", self._refresh_loop))

    def handle(self, msg: Message) -> Message:
        """The reply to one ``query_points`` (module docstring)."""
        assert isinstance(msg, QueryPoints)
        from mapper.node.queries import answer_key

        waited = bool(msg.settle_timeout_s)
        self.ctx.wait_settled(msg.settle_timeout_s)
        answers = self._caches()[1]
        key = answer_key(msg.texts, msg.negatives, msg.min_score, msg.max_points, msg.objects, _region(msg))
        gmap = self.ctx.state.global_map
        t0 = time.monotonic()
        stale_ok = self.ctx.streaming(t0) and not waited  # a settled answer is of the current map
        hit = answers.get(key, gmap.version, gmap.generation, t0, allow_stale=stale_ok)
        if hit is None:
            answer = self._compute(key, msg)
        else:
            answer, _age, stale = hit
            if stale:
                self._schedule_refresh(key, msg)
            answer.timing_ms["total"] = 1e3 * (time.monotonic() - t0)
        answer.settled = self.ctx.settled()
        return answer

    def prompts_are_heavy(self, msg: Message) -> bool:
        """Whether a ``query_points`` holds more than ``queries.light_text_chars`` characters of
        prompts the text encoder has not embedded yet (embedding them is the slow part: seconds for
        many long prompts): the transport then answers it on the worker pool, so that it does not
        hold up the light requests behind it."""
        if not isinstance(msg, QueryPoints):
            return False
        from mapper.node.queries import DEFAULT_NEGATIVES, normalise_query

        negatives = DEFAULT_NEGATIVES if msg.negatives is None else msg.negatives
        try:
            encoder = self.ctx.text_encoder("query_points")
            prompts = [normalise_query(t) for t in (*msg.texts, *negatives)]
            measure = getattr(encoder, "uncached_chars", None)
            new_chars = measure(prompts) if callable(measure) else sum(len(t) for t in prompts)
        except Exception:  # not_ready or an encoder's fault: the handler answers it, at once
            return False
        return bool(new_chars > self.ctx.config.queries.light_text_chars)

    def stats(self) -> dict[str, int]:
        """``status`` key ``answers``: computed, reused (same version / stale), background
        refreshes, cached questions, label-cache blocks scored and reused."""
        answers, labels = self._answer_cache, self._label_cache
        out = answers.stats() if answers is not None else {
            "computed": 0, "reused_same_version": 0, "reused_stale": 0, "entries": 0, "bytes": 0
        }  # fmt: skip
        out["refreshes"] = self.refreshes
        out["label_blocks_scored"] = labels.misses if labels is not None else 0
        out["label_blocks_reused"] = labels.hits if labels is not None else 0
        return out

    def _caches(self) -> tuple[BlockLabelCache, AnswerCache]:
        from mapper.node.queries import AnswerCache, BlockLabelCache

        with self._lock:
            if self._label_cache is None or self._answer_cache is None:
                cfg = self.ctx.config.queries
                self._label_cache = BlockLabelCache(cfg.label_cache_blocks)
                self._answer_cache = AnswerCache(
                    cfg.answer_max_age_s, cfg.answer_cache_entries, int(cfg.answer_cache_mb * 2**20)
                )
            return self._label_cache, self._answer_cache

    def _compute(self, key: AnswerKey, msg: QueryPoints) -> Points:
        """``query_points`` on the current snapshot; the answer is cached for ``key``."""
        from mapper.node.queries import query_points

        labels, answers = self._caches()
        encoder = self.ctx.text_encoder("query_points")
        taken = time.monotonic()
        gmap = self.ctx.state.global_map
        # paged tiles that may match (exact: the others cannot) are read for the query, not paged in
        if gmap.paged_points:
            rule = self.ctx.config.global_map.tile_skip
            snapshot = gmap.query_snapshot(_region(msg), _tile_filter(encoder, msg, rule))
        else:
            snapshot = gmap.snapshot()
        answer = query_points(
            snapshot,
            encoder,
            msg.texts,
            negatives=msg.negatives,
            min_score=msg.min_score,
            max_points=msg.max_points,
            objects=msg.objects,
            config=self.ctx.config.queries,
            label_cache=labels,
            region=_region(msg),
        )
        answers.put(key, answer, snapshot.version, snapshot.generation, taken)
        return answer

    def _schedule_refresh(self, key: AnswerKey, msg: QueryPoints) -> None:
        """Queue one background recomputation of ``key`` (none when one is already queued or the
        queue is full: the next stale request queues it)."""
        with self._lock:
            if key in self._refresh_pending:
                return
            try:
                self._refresh_jobs.put_nowait((key, msg))
            except queue.Full:
                return
            self._refresh_pending.add(key)

    def _refresh_loop(self, stop: threading.Event) -> None:
        """The answer-refresh thread: recompute stale answers on the current map (paced like the
        query threads: ingest first), so the next request gets a fresh one."""
        while not stop.is_set():
            started = time.monotonic()
            if self.refresh_one(self.ctx.config.poll_interval_s):
                self.ctx.pace(started)

    def refresh_one(self, timeout_s: float) -> bool:
        """Recompute one queued stale answer (waiting up to ``timeout_s`` for one); False when
        none was queued. Never raises (a failed refresh leaves the next request to compute)."""
        try:
            key, msg = self._refresh_jobs.get(timeout=timeout_s)
        except queue.Empty:
            return False
        try:
            gmap = self.ctx.state.global_map
            if not self._caches()[1].current(key, gmap.version, gmap.generation):
                self._compute(key, msg)
                self.refreshes += 1
        except ProtocolError as exc:  # e.g. the map was cleared: the next request says so
            log.debug("answer refresh: %s", exc.message)
        except Exception:
            log.exception("answer refresh failed (the next request computes its answer)")
        finally:
            with self._lock:
                self._refresh_pending.discard(key)
        return True
