"""``query_points`` with the per-block label cache answers exactly as scoring every row, across
every kind of map change (integrate, learned features, prune, restore), scores only the blocks
that changed, and stays within its bound. Also the union-find behind ``radius_components``."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mapper.node import global_map, queries
from mapper.node.config import GlobalMapConfig, QueryConfig
from mapper.node.global_map import GlobalSemanticMap
from mapper.node.queries import BlockLabelCache, query_points
from mapper.node.window import Keyframe
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


@pytest.mark.parametrize("seed", range(6))
def test_join_components_equals_scipy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    m = int(rng.integers(0, 2 * n))
    ca, cb = rng.integers(0, n, m), rng.integers(0, n, m)
    count, label = queries._join_components(n, ca, cb)
    graph = coo_matrix((np.ones(m, np.int8), (ca, cb)), shape=(n, n))
    ref_count, ref = connected_components(graph, directed=False)
    assert count == ref_count
    # same partition, labels in order of each component's smallest node (as connected_components)
    np.testing.assert_array_equal(label, ref)


def test_cache_never_keeps_old_blocks_alive(monkeypatch: pytest.MonkeyPatch) -> None:
    """Entries hold their blocks weakly: once no snapshot uses a block, its entry is gone."""
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
