"""Snapshots share the normalised fp32 feature blocks that did not change since the last one:
the blocks equal a full renormalisation after every kind of change (integrate, features set,
prune, restore, clear), and unchanged blocks are the same objects."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.map import global_map
from mapper.map.global_map import GlobalSemanticMap
from mapper.map.window import Keyframe
from mapper.node.config import GlobalMapConfig

W, H = 32, 24
K = np.array([30.0, 28.0, 16.0, 12.0])


def keyframe(x_m: float, stamp_ns: int, seed: int) -> Keyframe:
    pose = np.eye(4)
    pose[:3, 3] = [x_m, 0.0, 0.0]
    ov = np.random.default_rng(seed).standard_normal((3, 4, 8)).astype(np.float16)
    return Keyframe(
        seq=stamp_ns, stamp_ns=stamp_ns, camera="cam0", K=K.copy(), world_from_cam=pose,
        rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.full((H, W), 2.0, np.float32), ov=ov, ov_space="test",
    )  # fmt: skip


def full_unit(snap: global_map.GlobalMapSnapshot) -> np.ndarray:
    """Every row renormalised now (the same row function, which does not depend on the batch)."""
    assert snap.feat is not None
    return global_map._unit_rows(snap.feat)


@pytest.mark.parametrize("dim", [8, 384])
def test_unit_rows_match_a_float64_reference(dim: int) -> None:
    rng = np.random.default_rng(dim)
    scale = rng.choice([1e-3, 1.0, 300.0], size=(500, 1))
    feat = (rng.standard_normal((500, dim)) * scale).astype(np.float16)
    feat[:5] = 0  # rows without a feature stay zero
    feat[5] = 65504.0  # the largest fp16: no overflow in the norm
    ref = feat.astype(np.float64)
    ref /= np.maximum(np.linalg.norm(ref, axis=1), 1e-12)[:, None]
    got = global_map._unit_rows(feat)
    assert got.dtype == np.float32 and got.shape == feat.shape
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-7)
    assert not got[:5].any()
    # a row's result does not depend on the rows computed with it (patched blocks rely on it)
    parts = np.concatenate([global_map._unit_rows(feat[i : i + 7]) for i in range(0, 500, 7)])
    np.testing.assert_array_equal(parts, got)


def check(snap: global_map.GlobalMapSnapshot) -> list[np.ndarray]:
    blocks = snap.unit_feature_blocks()
    np.testing.assert_array_equal(np.concatenate(blocks), full_unit(snap))
    np.testing.assert_array_equal(snap.unit_features_f32(), full_unit(snap))
    emb = np.random.default_rng(0).standard_normal((3, 8)).astype(np.float32)
    np.testing.assert_allclose(snap.similarities(emb), full_unit(snap) @ emb.T, rtol=1e-5, atol=1e-6)
    assert all(not b.flags.writeable for b in blocks)
    return blocks


def test_unchanged_blocks_are_shared_and_every_change_is_seen(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(4):  # disjoint regions: rows appended block after block
        gmap.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    first = gmap.snapshot()
    b1 = check(first)
    assert len(b1) > 3
    # a new region: the old full blocks are shared, the appended rows are new
    gmap.integrate(keyframe(50.0, 10, 10), map_version=6)
    second = gmap.snapshot()
    b2 = check(second)
    n_full = len(first) // 16
    assert all(b2[i] is b1[i] for i in range(n_full))
    assert len(b2) > len(b1)
    # the first region again: its blocks change (fused), the others stay shared
    gmap.integrate(keyframe(0.0, 11, 11), map_version=7)
    third = gmap.snapshot()
    b3 = check(third)
    changed = [i for i in range(len(b3)) if b3[i] is not b2[i]]
    assert changed and len(changed) < len(b3)
    assert not np.array_equal(b3[0], b2[0])
    # learned features for two voxels: their block is a patched copy, the others are shared
    keys, _ = gmap.seen_voxels(keyframe(50.0, 12, 12))
    assert gmap.set_features(keys[:2], np.ones((2, 8), np.float32)) == 2
    b4 = check(gmap.snapshot())
    patched = [i for i in range(len(b4)) if b4[i] is not b3[i]]
    assert 1 <= len(patched) <= 2
    # learned features for many voxels
    gmap.set_features(keys, np.ones((keys.shape[0], 8), np.float32))
    check(gmap.snapshot())
    # prune (rows move), restore, clear: still equal to a full renormalisation
    small = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=200))
    for i in range(3):
        small.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
        check(small.snapshot())
    arrays, manifest = gmap.to_arrays()
    gmap.restore(arrays, manifest, map_version=20)
    check(gmap.snapshot())
    gmap.clear(map_version=21)
    assert gmap.snapshot().unit_feature_blocks() == []
    gmap.integrate(keyframe(0.0, 30, 30), map_version=22)
    check(gmap.snapshot())


def test_old_snapshots_keep_their_own_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2))
    gmap.integrate(keyframe(0.0, 1, 1), map_version=1)
    old = gmap.snapshot()
    gmap.integrate(keyframe(0.0, 2, 2), map_version=2)  # fuses into the same voxels
    new = gmap.snapshot()
    check(new)  # computed first: the old snapshot has not published blocks
    check(old)  # then the old one: its rows differ, it must not take the new blocks


@pytest.mark.parametrize("seed", range(5))
def test_random_changes_blocks_equal_full_renormalisation(monkeypatch: pytest.MonkeyPatch, seed: int) -> None:
    """Random sequences of every kind of change, snapshots taken (and their blocks computed) in
    random order, sometimes an older one after a newer: the blocks always equal a full
    renormalisation (prunes, restores and clears move rows: those blocks are compared by bytes)."""
    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    rng = np.random.default_rng(seed)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=400))
    pending: list[global_map.GlobalMapSnapshot] = []
    checked = 0
    for step in range(40):
        op = rng.choice(["integrate", "integrate", "integrate", "features", "set", "restore", "clear"],
                        p=[0.25, 0.25, 0.2, 0.1, 0.1, 0.05, 0.05])  # fmt: skip
        x = float(rng.integers(0, 6)) * 3.0
        if op == "integrate":
            gmap.integrate(keyframe(x, step + 1, step), map_version=step + 1)
        elif op == "features" and gmap.dim is not None:
            kf = keyframe(x, step + 1, step)
            gmap.integrate_features(kf, map_version=step + 1)
        elif op == "set":
            keys, _ = gmap.seen_voxels(keyframe(x, step + 1, step))
            if keys.size:
                some = keys[: int(rng.integers(1, keys.size + 1))]
                gmap.set_features(some, rng.standard_normal((some.size, 8)))
        elif op == "restore":
            arrays, manifest = gmap.to_arrays()
            gmap.restore(arrays, manifest, map_version=step + 1)
        elif op == "clear":
            gmap.clear(map_version=step + 1)
        pending.append(gmap.snapshot())
        while pending and rng.random() < 0.6:  # compute some of the snapshots, in random order
            snap = pending.pop(int(rng.integers(0, len(pending))))
            if snap.feat is not None and len(snap):
                check(snap)
                checked += 1
    assert checked > 10


def test_stamps_find_the_changed_rows_without_comparing(monkeypatch: pytest.MonkeyPatch) -> None:
    """A stream of integrates and learned features, each snapshot computed in turn: the changed
    rows come from the write stamps, no row bytes are compared."""
    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    compares: list[int] = []
    original = global_map._row_words

    def counting(a: np.ndarray) -> np.ndarray:
        compares.append(a.shape[0])
        return original(a)

    monkeypatch.setattr(global_map, "_row_words", counting)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(12):
        gmap.integrate(keyframe(3.0 * (i % 4), i + 1, i), map_version=i + 1)
        if i % 3 == 2:
            keys, _ = gmap.seen_voxels(keyframe(0.0, 100 + i, 100 + i))
            gmap.set_features(keys[:5], np.ones((min(5, keys.size), 8)))
        check(gmap.snapshot())
    assert compares == []


def test_similarities_kept_per_text_set() -> None:
    """``similarities_cached``: the same cosines as ``similarities``, computed once per snapshot and
    text set (read-only), at most a few text sets kept, none carried to the next map version."""
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    gmap.integrate(keyframe(0.0, 1, 1), map_version=1)
    snap = gmap.snapshot()
    rng = np.random.default_rng(0)
    sets = [rng.standard_normal((3, 8)).astype(np.float32) for _ in range(global_map._SIMILARITY_SETS + 2)]
    first = snap.similarities_cached(sets[0])
    np.testing.assert_array_equal(first, snap.similarities(sets[0]))
    assert snap.similarities_cached(sets[0].copy()) is first and not first.flags.writeable
    for emb in sets[1:]:
        snap.similarities_cached(emb)
    kept = [k for k in snap._cache if isinstance(k, tuple) and k[0] == "similarities"]
    assert len(kept) == global_map._SIMILARITY_SETS
    assert snap.similarities_cached(sets[0]) is not first  # the oldest set was dropped
    gmap.integrate(keyframe(0.5, 2, 2), map_version=2)
    later = gmap.snapshot()
    np.testing.assert_array_equal(later.similarities_cached(sets[0]), later.similarities(sets[0]))


def test_map_cosines_of_a_few_rows_or_of_every_row(monkeypatch: pytest.MonkeyPatch) -> None:
    """``row_similarities`` equals ``similarities`` at the rows (the same per-row bits), across
    blocks; the map's answers take every row's cosines (kept) only when the map is not much larger
    than the request, else just the rows asked for (nothing kept)."""
    from mapper.node import queries

    monkeypatch.setattr(global_map, "UNIT_BLOCK_ROWS", 16)
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=2, max_points=1_000_000))
    for i in range(3):
        gmap.integrate(keyframe(10.0 * i, i + 1, i), map_version=i + 1)
    snap = gmap.snapshot()
    n = len(snap)
    assert len(snap.unit_feature_blocks()) > 2
    emb = np.random.default_rng(1).standard_normal((3, 8)).astype(np.float32)
    rows = np.random.default_rng(2).integers(0, n, 40)
    np.testing.assert_array_equal(snap.row_similarities(rows, emb), snap.similarities(emb)[rows])
    assert snap.similarities_cached(emb, compute=False) is None
    few = rows[: max(1, n // 4)]
    np.testing.assert_array_equal(queries._map_similarities(snap, few, emb), snap.similarities(emb)[few])
    assert snap.similarities_cached(emb, compute=False) is None  # a few rows of a larger map: not kept
    many = np.random.default_rng(3).integers(0, n, n)
    np.testing.assert_array_equal(queries._map_similarities(snap, many, emb), snap.similarities(emb)[many])
    assert snap.similarities_cached(emb, compute=False) is not None  # every row's, kept
