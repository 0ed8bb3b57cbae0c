"""``query_points`` with the per-block label cache answers exactly as scoring every row, across
every kind of map change (integrate, learned features, prune, restore), scores only the blocks
that changed, and stays within its bound."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from mapper.map import global_map
from mapper.map.global_map import GlobalSemanticMap
from mapper.map.window import Keyframe
from mapper.node.config import GlobalMapConfig, QueryConfig
from mapper.node.queries import BlockLabelCache, query_points
from protocol.messages import Points

W, H, D = 32, 24, 8
K = np.array([30.0, 28.0, 16.0, 12.0])


class HashEncoder:
    """A deterministic stand-in text encoder: each text's unit vector comes from its CRC."""

    space = "test"
    dim = D

    def encode(self, texts: list[str]) -> np.ndarray:
        rows = [np.random.default_rng(zlib.crc32(t.encode())).standard_normal(D) for t in texts]
        out = np.asarray(rows, np.float32).reshape(len(texts), D)
        return out / np.linalg.norm(out, axis=1, keepdims=True)


def keyframe(x_m: float, stamp_ns: int, seed: int) -> Keyframe:
    pose = np.eye(4)
    pose[:3, 3] = [x_m, 0.0, 0.0]
    ov = np.random.default_rng(seed).standard_normal((3, 4, D)).astype(np.float16)
    return Keyframe(
        seq=stamp_ns, stamp_ns=stamp_ns, camera="cam0", K=K.copy(), world_from_cam=pose,
        rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.full((H, W), 2.0, np.float32), ov=ov, ov_space="test",
    )  # fmt: skip


def ask(snap: global_map.GlobalMapSnapshot, cache: BlockLabelCache | None, texts: list[str]) -> Points:
    return query_points(
        snap, HashEncoder(), texts, negatives=["wall", "floor"], min_score=None, max_points=None,
        objects=True, config=QueryConfig(cluster_radius_m=0.3, min_object_points=2), label_cache=cache,
    )  # fmt: skip


def assert_same(a: Points, b: Points) -> None:
    assert a.map_version == b.map_version
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.score, b.score)
    np.testing.assert_array_equal(a.label, b.label)
    def objects(p: Points) -> list[tuple[str, int, float]]:
        return [(o.text, o.n_points, o.score) for o in p.objects]

    assert objects(a) == objects(b)


def test_cached_answers_equal_scoring_every_row(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(4):  # disjoint regions: rows appended block after block
        gmap.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    cache = BlockLabelCache(max_blocks=10_000)
    texts = ["chair", "table"]

    first = gmap.snapshot()
    n_blocks = len(first.unit_feature_blocks())
    assert n_blocks > 3
    answer = ask(first, cache, texts)
    assert_same(answer, ask(first, None, texts))
    assert answer.xyz.shape[0] > 0 and answer.objects
    assert (cache.hits, cache.misses) == (0, n_blocks)

    # the same query again: nothing is scored
    assert_same(ask(first, cache, texts), answer)
    assert (cache.hits, cache.misses) == (n_blocks, n_blocks)

    # another text set shares no entry
    assert_same(ask(first, cache, ["sofa"]), ask(first, None, ["sofa"]))
    assert cache.misses == 2 * n_blocks

    # the first region again: only its (changed) blocks are scored
    gmap.integrate(keyframe(0.0, 11, 11), map_version=7)
    second = gmap.snapshot()
    blocks = second.unit_feature_blocks()
    changed = sum(1 for b, old in zip(blocks, first.unit_feature_blocks(), strict=False) if b is not old)
    changed += max(0, len(blocks) - n_blocks)
    assert 0 < changed < len(blocks)
    misses = cache.misses
    assert_same(ask(second, cache, texts), ask(second, None, texts))
    assert cache.misses - misses == changed

    # learned features, prune (rows move), restore: still the same answers
    keys, _ = gmap.seen_voxels(keyframe(30.0, 12, 12))
    gmap.set_features(keys, np.ones((keys.shape[0], D), np.float32))
    assert_same(ask(gmap.snapshot(), cache, texts), ask(gmap.snapshot(), None, texts))
    small = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=200))
    for i in range(4):
        small.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
        assert_same(ask(small.snapshot(), cache, texts), ask(small.snapshot(), None, texts))
    arrays, meta = gmap.to_arrays()
    restored = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    restored.restore(arrays, meta, map_version=99)
    assert_same(ask(restored.snapshot(), cache, texts), ask(restored.snapshot(), None, texts))


def test_cache_bound_and_off(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(3):
        gmap.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    snap = gmap.snapshot()
    reference = ask(snap, None, ["chair"])
    bounded = BlockLabelCache(max_blocks=2)
    off = BlockLabelCache(max_blocks=0)
    for _ in range(2):
        assert_same(ask(snap, bounded, ["chair"]), reference)
        assert_same(ask(snap, off, ["chair"]), reference)
        assert len(bounded) <= 2
        assert len(off) == 0


def test_cache_never_keeps_old_blocks_alive(monkeypatch: pytest.MonkeyPatch) -> None:
    """Entries hold their blocks weakly: once no snapshot uses a block, its entry is retired (its
    results kept for patching, at most one map's worth of blocks)."""
    import gc

    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(3):
        gmap.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    cache = BlockLabelCache(max_blocks=10_000)
    for step in range(4):  # every region changes: every block is replaced
        snap = gmap.snapshot()
        ask(snap, cache, ["chair"])
        del snap
        for i in range(3):
            n = 10 * step + i + 10
            gmap.integrate(keyframe(10.0 * i, n, n), map_version=n)
    gc.collect()
    ask(gmap.snapshot(), cache, ["chair"])
    gc.collect()
    live = {id(b) for b in gmap.snapshot().unit_feature_blocks()}
    assert len(cache) <= len(live)
    assert cache.retired <= len(live)  # the results of freed blocks (no blocks), one map's worth


@pytest.mark.parametrize("keep_old_snapshot", [True, False])
def test_a_few_changed_rows_are_rescored_alone(
    monkeypatch: pytest.MonkeyPatch, keep_old_snapshot: bool
) -> None:
    """A block copied from a scored one with a few rows normalised again is answered by rescoring
    those rows (from the live entry, or from the retired one once the old snapshot is gone), with
    the same bits as scoring every row."""
    import gc

    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 64)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(4):
        gmap.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    cache = BlockLabelCache(max_blocks=10_000)
    texts = ["chair", "table"]
    old = gmap.snapshot()
    ask(old, cache, texts)
    assert cache.patched == 0
    keys, _ = gmap.seen_voxels(keyframe(10.0, 5, 5))
    rng = np.random.default_rng(0)
    few = rng.choice(keys, size=5, replace=False)
    gmap.set_features(few, rng.standard_normal((5, D)).astype(np.float32))
    if not keep_old_snapshot:
        del old
    new = gmap.snapshot()
    patched = [p for p in new.unit_block_patches() if p is not None]
    gc.collect()
    assert (cache.retired > 0) == (not keep_old_snapshot)  # the map let go of the old blocks
    assert patched and sum(p[1].size for p in patched) == 5
    answer = ask(new, cache, texts)
    assert cache.patched == len(patched)
    assert_same(answer, ask(new, None, texts))


def test_row_cosines_are_the_same_bits_for_any_rows() -> None:
    from mapper.map.query_kernels import row_cosines

    rng = np.random.default_rng(1)
    feat = rng.standard_normal((1000, 384)).astype(np.float32)
    feat /= np.linalg.norm(feat, axis=1, keepdims=True)
    emb = rng.standard_normal((7, 384)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    full = row_cosines(feat, emb)
    np.testing.assert_allclose(full, feat.astype(np.float64) @ emb.T.astype(np.float64), atol=2e-6)
    for rows in (np.array([3]), np.array([999, 0, 3]), rng.choice(1000, 300, replace=False)):
        np.testing.assert_array_equal(row_cosines(feat, emb, rows), full[rows])
    assert row_cosines(feat, emb[:0]).shape == (1000, 0)
    with pytest.raises(ValueError, match="share D"):
        row_cosines(feat, emb[:, :10])


def test_kernels_launched_from_many_threads_at_once() -> None:
    """The query threads, the answer-refresh thread and the query workers may all launch compiled
    kernels at once: every launch takes the process-wide launch lock, and each result is the one
    computed alone."""
    import threading

    from mapper.map.query_kernels import row_cosines
    from mapper.node.queries import _pair_components, radius_components

    rng = np.random.default_rng(2)
    feat = rng.standard_normal((5000, 64)).astype(np.float32)
    emb = rng.standard_normal((5, 64)).astype(np.float32)
    pts = rng.uniform(0, 2, (3000, 3))
    want_cos = row_cosines(feat, emb)
    want_n = _pair_components(pts, 0.1)[0]
    errors: list[str] = []

    def work(i: int) -> None:
        for _ in range(5):
            if i % 2:
                if not np.array_equal(row_cosines(feat, emb), want_cos):
                    errors.append("cosines")
            elif radius_components(pts, 0.1)[0] != want_n:
                errors.append("components")

    threads = [threading.Thread(target=work, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
