"""``query_points`` answers reused by the node: the same question on the same map version gets the
same answer without recomputing; on a map that only grew, a stale answer (flagged, with its age
and its own map version) within ``queries.answer_max_age_s``, recomputed in the background; never
across a ``load`` / ``clear`` (another map), never past the age, never for another question."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from mapper.node.queries import AnswerCache, answer_key
from mapper.node.service import MapperNode
from protocol.messages import Load, Ok, Points, QueryPoints, Save, decode, encode
from tests.mapper.node.test_label_cache import HashEncoder, keyframe
from tests.node_helpers import in_process_node


def points(version: int) -> Points:
    return Points(
        map_version=version, xyz=np.zeros((1, 3), np.float32), score=np.ones(1, np.float32),
        label=np.zeros(1, np.int32), timing_ms={"total": 5.0},
    )  # fmt: skip


KEY = answer_key(["chair"], None, None, None, True)


def test_same_version_always_stale_only_within_age_never_other_generation() -> None:
    cache = AnswerCache(max_age_s=1.0, max_entries=8)
    assert cache.get(KEY, 3, 0, 10.0) is None
    cache.put(KEY, points(3), version=3, generation=0, taken_s=10.0)
    # same version: reused whatever its age
    hit = cache.get(KEY, 3, 0, 1000.0)
    assert hit is not None and hit[2] is False and hit[0].timing_ms["answer_reused"] == 1.0
    # the map grew: stale within the age, not beyond it
    hit = cache.get(KEY, 5, 0, 10.5)
    assert hit is not None and hit[2] is True and hit[0].map_version == 3
    assert hit[0].timing_ms["answer_age_ms"] == pytest.approx(500.0)
    assert cache.get(KEY, 5, 0, 11.5) is None
    # another map (load / clear), an older version than the answer, another question
    assert cache.get(KEY, 5, 1, 10.1) is None
    assert cache.get(KEY, 2, 0, 10.1) is None
    assert cache.get(answer_key(["chair"], None, None, 10, True), 3, 0, 10.1) is None
    assert cache.stats() == {
        "computed": 1, "reused_same_version": 1, "reused_stale": 1, "entries": 1, "bytes": 12 + 4 + 4 + 256
    }  # fmt: skip


def test_copies_are_independent_and_newer_answers_win() -> None:
    cache = AnswerCache(max_age_s=1.0, max_entries=8)
    cache.put(KEY, points(3), version=3, generation=0, taken_s=0.0)
    a, b = cache.get(KEY, 3, 0, 0.1), cache.get(KEY, 3, 0, 0.2)
    assert a is not None and b is not None
    a[0].id = 7
    a[0].timing_ms["total"] = 99.0
    assert b[0].id is None and b[0].timing_ms["total"] == 5.0
    # a refresh that finishes after a newer answer does not replace it
    cache.put(KEY, points(9), version=9, generation=0, taken_s=1.0)
    cache.put(KEY, points(6), version=6, generation=0, taken_s=0.5)
    hit = cache.get(KEY, 9, 0, 1.1)
    assert hit is not None and hit[0].map_version == 9 and hit[2] is False
    # a new generation replaces whatever was there
    cache.put(KEY, points(1), version=1, generation=1, taken_s=2.0)
    assert cache.get(KEY, 9, 0, 2.1) is None


def test_bounded_and_off() -> None:
    cache = AnswerCache(max_age_s=1.0, max_entries=2)
    for i in range(5):
        cache.put(answer_key([f"t{i}"], None, None, None, True), points(1), 1, 0, 0.0)
    assert len(cache) == 2
    assert cache.get(answer_key(["t4"], None, None, None, True), 1, 0, 0.0) is not None
    assert cache.get(answer_key(["t0"], None, None, None, True), 1, 0, 0.0) is None
    # the byte budget: a 1-point answer counts its 20 bytes of arrays and 256 for the message
    size = 12 + 4 + 4 + 256
    small = AnswerCache(max_age_s=1.0, max_entries=100, max_bytes=3 * size)
    for i in range(5):
        small.put(answer_key([f"t{i}"], None, None, None, True), points(1), 1, 0, 0.0)
    assert len(small) == 3 and small.stats()["bytes"] == 3 * size
    small.put(KEY, points(1), 1, 0, 0.0)  # replacing an entry does not count it twice
    small.put(KEY, points(1), 1, 0, 0.0)
    assert small.stats()["bytes"] == 3 * size
    tiny = AnswerCache(max_age_s=1.0, max_entries=100, max_bytes=100)  # larger than the budget
    tiny.put(KEY, points(1), 1, 0, 0.0)
    assert tiny.get(KEY, 1, 0, 0.0) is None and tiny.stats()["bytes"] == 0
    off = AnswerCache(max_age_s=1.0, max_entries=0)
    off.put(KEY, points(1), 1, 0, 0.0)
    assert off.get(KEY, 1, 0, 0.0) is None and len(off) == 0


# -- in the node ---------------------------------------------------------------------------------


def node_with_map(tmp_path: Path, **queries: object) -> MapperNode:
    """A node with a small map; frames count as arriving (stale answers are only served then)."""
    node = in_process_node(tmp_path, queries=queries)
    node.ctx.text_encoder = lambda what: HashEncoder()  # type: ignore[method-assign]
    node.ctx.ingest_last = math.inf
    for i in range(3):
        node.state.global_map.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    return node


def ask(node: MapperNode, max_points: int | None = None) -> Points:
    request = QueryPoints(texts=["chair", "table"], max_points=max_points, id=1)
    reply = decode(node.handle_query(encode(request)))
    assert isinstance(reply, Points), reply
    assert reply.id == 1
    return reply


def fresh(node: MapperNode) -> Points:
    """The answer a node without any cache gives on the same map."""
    from mapper.node.queries import query_points

    return query_points(
        node.state.global_map.snapshot(), HashEncoder(), ["chair", "table"], negatives=None, min_score=None,
        max_points=None, objects=True, config=node.config.queries,
    )  # fmt: skip


def same(a: Points, b: Points) -> None:
    assert a.map_version == b.map_version
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.score, b.score)
    assert [(o.text, o.n_points) for o in a.objects] == [(o.text, o.n_points) for o in b.objects]


def test_node_reuses_then_refreshes_a_stale_answer(tmp_path: Path) -> None:
    node = node_with_map(tmp_path, answer_max_age_s=60.0)
    first = ask(node)
    assert first.timing_ms["answer_reused"] == 0.0
    same(first, fresh(node))
    again = ask(node)
    assert again.timing_ms["answer_reused"] == 1.0
    same(again, first)

    node.state.global_map.integrate(keyframe(0.0, 11, 11), map_version=7)
    stale = ask(node)
    assert stale.timing_ms["answer_reused"] == 1.0 and stale.map_version == 3
    assert node.query_points.stats()["reused_stale"] == 1
    ask(node)  # a second stale request queues no second refresh
    assert node.query_points._refresh_jobs.qsize() == 1
    assert node.query_points.refresh_one(0.0) and not node.query_points.refresh_one(0.0)
    refreshed = ask(node)
    assert refreshed.timing_ms["answer_reused"] == 1.0 and refreshed.map_version == 7
    same(refreshed, fresh(node))
    assert node.query_points.stats()["refreshes"] == 1
    # another question is computed, not taken from this one
    other = ask(node, max_points=5)
    assert other.timing_ms["answer_reused"] == 0.0 and other.xyz.shape[0] <= 5


def test_node_recomputes_once_the_stream_stopped(tmp_path: Path) -> None:
    """With no frame for ``limits.ingest_active_s`` a changed map is answered afresh at once."""
    node = node_with_map(tmp_path, answer_max_age_s=60.0)
    ask(node)
    node.state.global_map.integrate(keyframe(0.0, 11, 11), map_version=7)
    node.ctx.ingest_last = time.monotonic() - 10.0
    now = ask(node)
    assert now.timing_ms["answer_reused"] == 0.0 and now.map_version == 7
    same(now, fresh(node))
    assert ask(node).timing_ms["answer_reused"] == 1.0  # unchanged map: the same answer again


def test_node_recomputes_past_the_age_and_after_a_load(tmp_path: Path) -> None:
    node = node_with_map(tmp_path, answer_max_age_s=0.0)
    ask(node)
    node.state.global_map.integrate(keyframe(0.0, 11, 11), map_version=7)
    now = ask(node)
    assert now.timing_ms["answer_reused"] == 0.0 and now.map_version == 7
    same(now, fresh(node))

    node = node_with_map(tmp_path / "b", answer_max_age_s=60.0)
    ask(node)
    arrays, meta = node.state.global_map.to_arrays()
    node.state.global_map.restore(arrays, meta, map_version=3)  # a load: the same version number
    after = ask(node)
    assert after.timing_ms["answer_reused"] == 0.0


def test_node_never_reuses_across_a_load(tmp_path: Path) -> None:
    """A ``load`` puts a fresh map object in place, whose versions start again: its generation,
    unique in the process, keeps the old answers out (even when the version numbers collide)."""
    node = node_with_map(tmp_path, answer_max_age_s=60.0)
    node.state.global_map.retag(1)
    node.handle_query(encode(Save(name="m")))
    saved_version = node.state.global_map.version
    before = ask(node)
    reply = decode(node.handle_query(encode(Load(name="m"))))
    assert isinstance(reply, Ok), reply
    while node.state.global_map.version < saved_version:  # make the version numbers collide
        node.state.global_map.retag(node.state.map_version)
    assert node.state.global_map.version == saved_version
    after = ask(node)
    assert after.timing_ms["answer_reused"] == 0.0
    same(after, fresh(node))
    assert before.xyz.shape == after.xyz.shape


def test_generations_are_unique_per_process() -> None:
    from mapper.map.global_map import GlobalSemanticMap
    from mapper.node.config import GlobalMapConfig

    a, b = GlobalSemanticMap(GlobalMapConfig()), GlobalSemanticMap(GlobalMapConfig())
    seen = {a.generation, b.generation}
    a.integrate(keyframe(0.0, 1, 1), map_version=1)
    assert a.generation in seen and a.snapshot().generation == a.generation
    a.clear()
    seen.add(a.generation)
    arrays, meta = b.to_arrays()
    b.restore(arrays, meta, map_version=0)
    seen.add(b.generation)
    assert len(seen) == 4


def test_started_node_refreshes_in_the_background(tmp_path: Path) -> None:
    node = node_with_map(tmp_path, answer_max_age_s=60.0)
    node.start()
    try:
        ask(node)
        node.state.global_map.integrate(keyframe(0.0, 11, 11), map_version=7)
        assert ask(node).map_version == 3
        deadline = time.monotonic() + 20.0
        while node.query_points.stats()["refreshes"] < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        refreshed = ask(node)
        assert refreshed.map_version == 7
        same(refreshed, fresh(node))
    finally:
        node.stop()


def test_a_loaded_map_is_ready_to_query(tmp_path: Path) -> None:
    """``load`` replies with the map's snapshot and normalised features made, so the first
    ``query_points`` does not compute them; its answer is the one a fresh computation gives."""
    node = node_with_map(tmp_path, answer_max_age_s=0.0)
    node.handle_query(encode(Save(name="m")))
    reply = decode(node.handle_query(encode(Load(name="m"))))
    assert isinstance(reply, Ok), reply
    snap = node.state.global_map.snapshot()
    blocks = snap._cache.get("unit_blocks")
    assert blocks is not None and sum(b.shape[0] for b in blocks) == len(snap) > 0  # made by the load
    after = ask(node)
    assert node.state.global_map.snapshot() is snap and snap._cache["unit_blocks"] is blocks  # used as made
    same(after, fresh(node))
