"""Paging of the global map (:mod:`mapper.map.tile_store`): beyond ``max_points`` the least recently
observed tiles go to the tile store and come back when observed, with every voxel's arrays exactly as
they were; saving holds them; the per-tile feature summary skips only tiles that cannot match."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mapper.errors import ConfigError
from mapper.map.global_map import GlobalSemanticMap
from mapper.map.tile_store import (
    SCALAR_FIELDS,
    TileStore,
    centroids_may_match,
    cone_may_match,
    tile_ids,
    tile_summary,
)
from mapper.node.config import GlobalMapConfig, config_from_dict
from tests.mapper.map.test_global_map import make_kf, plane_depth

ROOM_B = np.eye(4)
ROOM_B[:3, 3] = [10.0, 0.0, 0.0]


def _ov(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(3, 4, 8)).astype(np.float16)


def _cfg(**kw: object) -> GlobalMapConfig:
    base = GlobalMapConfig(pixel_stride=1, voxel_size_m=0.02, tile_m=0.2, prune_to_fraction=0.5)
    return dataclasses.replace(base, **kw)


def _two_rooms(gmap: GlobalSemanticMap, again: bool = False) -> None:
    """Room A (two views), then room B 10 m away; ``again``: room A once more."""
    gmap.integrate(make_kf(plane_depth(2.0), ov=_ov(1), stamp_ns=1))
    gmap.integrate(make_kf(plane_depth(2.0), ov=_ov(2), stamp_ns=2))
    gmap.integrate(make_kf(plane_depth(1.0), world_from_cam=ROOM_B, ov=_ov(3), stamp_ns=3))
    if again:
        gmap.integrate(make_kf(plane_depth(2.0), ov=_ov(4), stamp_ns=4))


def _by_key(gmap: GlobalSemanticMap) -> dict[str, np.ndarray]:
    arrays, _ = gmap.to_arrays()
    order = np.argsort(arrays["global.keys"])
    return {name: a[order] for name, a in arrays.items() if not name.startswith("global.evicted")}


def _assert_same_voxels(a: GlobalSemanticMap, b: GlobalSemanticMap) -> None:
    got, want = _by_key(a), _by_key(b)
    assert sorted(got) == sorted(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_paged_tiles_keep_every_voxel_and_come_back_when_observed() -> None:
    full, bounded = GlobalSemanticMap(_cfg()), GlobalSemanticMap(_cfg(max_points=1000))
    _two_rooms(full)
    _two_rooms(bounded)
    assert len(full) == 1536 and len(bounded) <= 1000 < bounded.total_points == len(full)
    assert bounded.paged_points > 0 and np.all(bounded.snapshot().xyz[:, 0] > 5.0)  # room A paged out
    _assert_same_voxels(bounded, full)  # xyz, features, weights, hits, stamps: all as they were
    np.testing.assert_array_equal(np.sort(bounded.all_keys()), np.sort(full.snapshot().keys))
    stats = bounded.stats()
    assert stats["global_points"] == len(bounded) and stats["global_points_total"] == len(full)
    assert stats["global_points_paged"] == bounded.paged_points and stats["global_points_pruned"] == 0
    assert stats["global_tiles_paged"] > 0 and stats["global_tile_store_bytes"] > 0
    # room A observed again: its tiles come back and fuse as if they had never left
    full.integrate(make_kf(plane_depth(2.0), ov=_ov(4), stamp_ns=4))
    bounded.integrate(make_kf(plane_depth(2.0), ov=_ov(4), stamp_ns=4))
    assert bounded.points_paged_in > 0 and np.all(bounded.snapshot().xyz[:, 0] < 5.0)
    _assert_same_voxels(bounded, full)


def test_paging_off_prunes_and_forgets() -> None:
    pruned = GlobalSemanticMap(_cfg(max_points=1000, paging=False))
    _two_rooms(pruned)
    assert pruned.paged_points == 0 and pruned.points_pruned > 0 and pruned.total_points <= 1000


def test_query_snapshot_reads_paged_tiles_without_paging_them_in() -> None:
    full, bounded = GlobalSemanticMap(_cfg()), GlobalSemanticMap(_cfg(max_points=1000))
    _two_rooms(full)
    _two_rooms(bounded)
    resident, version = len(bounded), bounded.version
    snap = bounded.query_snapshot()
    assert len(snap) == len(full) and len(bounded) == resident and bounded.version == version
    assert snap.version == version and snap.feat is not None and snap.keys is not None
    order, want = np.argsort(snap.keys), full.snapshot()
    ref = np.argsort(want.keys)
    assert want.feat is not None and want.keys is not None
    np.testing.assert_array_equal(snap.keys[order], want.keys[ref])
    np.testing.assert_array_equal(snap.feat[order], want.feat[ref])
    np.testing.assert_array_equal(snap.xyz[order], want.xyz[ref])
    # a region around room B needs no paged tile; one around room A reads them
    box_b = (np.array([9.0, -5.0, -5.0]), np.array([11.0, 5.0, 5.0]))
    assert bounded.query_snapshot(region=box_b) is bounded.snapshot()
    box_a = (np.array([-2.0, -2.0, 1.0]), np.array([2.0, 2.0, 3.0]))
    assert len(bounded.query_snapshot(region=box_a)) == len(full)
    assert bounded.query_snapshot(may_match=lambda info: False) is bounded.snapshot()
    kept = bounded.query_snapshot()
    assert bounded.query_snapshot() is kept  # kept for the version
    bounded.integrate(make_kf(plane_depth(1.0), world_from_cam=ROOM_B, ov=_ov(5), stamp_ns=5))
    assert bounded.query_snapshot() is not kept and len(bounded.query_snapshot()) == len(full)


def test_segment_lookup_pages_in_the_tiles_of_the_asked_points() -> None:
    bounded = GlobalSemanticMap(_cfg(max_points=1000))
    _two_rooms(bounded)
    paged_before = bounded.paged_points
    at = np.array([[0.0, 0.0, 2.0]])  # on room A's wall
    assert bounded.snapshot().nearest_with_feature(at, 0.1)[0] == -1
    assert bounded.page_in_near(at, 0.1) > 0 and bounded.paged_points < paged_before
    snap = bounded.snapshot()
    row = snap.nearest_with_feature(at, 0.1)[0]
    assert row >= 0 and np.linalg.norm(snap.xyz[row] - at[0]) < 0.05
    assert bounded.page_in_near(np.array([[50.0, 0.0, 0.0]]), 0.1) == 0  # nothing paged there
    _two_rooms(bounded)  # room B last again: room A pages out
    assert bounded.page_in_near(np.array([[0.0, 0.0, 2.0]]), 3.0) > 0  # a radius of many tiles
    assert bounded.paged_points == 0


def test_save_restore_holds_paged_tiles() -> None:
    full, bounded = GlobalSemanticMap(_cfg()), GlobalSemanticMap(_cfg(max_points=1000))
    _two_rooms(full)
    _two_rooms(bounded)
    arrays, manifest = bounded.to_arrays()
    assert manifest["points"] == len(full)
    again = GlobalSemanticMap(_cfg(max_points=1000))  # loaded beyond the bound: pages out again
    again.restore(arrays, manifest, map_version=2)
    assert len(again) <= 1000 and again.total_points == len(full)
    everything = GlobalSemanticMap(_cfg())
    everything.restore(arrays, manifest, map_version=2)
    assert len(everything) == len(full) and everything.paged_points == 0
    _assert_same_voxels(everything, full)
    _assert_same_voxels(again, full)
    again.clear()
    assert again.total_points == 0 and again.stats()["global_points_paged"] == 0


def test_disk_budget_prunes_the_paged_store() -> None:
    gmap = GlobalSemanticMap(_cfg(max_points=1000, max_disk_points=300))
    _two_rooms(gmap)
    stats = gmap.stats()
    assert 0 < gmap.paged_points <= 300 and stats["global_points_pruned"] > 0
    total = stats["global_points_total"]
    assert total == len(gmap) + gmap.paged_points == 1536 - stats["global_points_pruned"]


def test_the_store_file_goes_with_the_map(tmp_path: Path) -> None:
    gmap = GlobalSemanticMap(_cfg(max_points=1000), tile_dir=tmp_path / ".tiles")
    _two_rooms(gmap)
    files = sorted((tmp_path / ".tiles").glob("tiles-*.sqlite3"))
    assert len(files) == 1
    del gmap
    import gc

    gc.collect()
    assert not files[0].exists()


def test_tile_store_round_trip_and_region_select(tmp_path: Path) -> None:
    store = TileStore(tmp_path / "t.sqlite3")
    rng = np.random.default_rng(0)

    def part(n: int, key0: int) -> dict[str, np.ndarray]:
        out = {name: rng.integers(0, 100, n).astype(t) for name, t in SCALAR_FIELDS.items()}
        out["keys"] = np.arange(key0, key0 + n, dtype=np.int64)
        out["xyz"] = rng.normal(size=(n, 3)).astype(np.float32)
        out["feat"] = rng.normal(size=(n, 4)).astype(np.float16)
        return out

    a, b = part(5, 0), part(3, 100)
    empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))
    store.put([1, 2], [a, b], [empty[0]] * 2, [empty[1]] * 2, [(0, 0, 0), (5, 0, 0)], [3, 4])
    assert store.points == 8 and len(store) == 2 and store.disk_bytes > 0
    np.testing.assert_array_equal(np.sort(store.keys()), np.concatenate([a["keys"], b["keys"]]))
    assert store.select(1.0, (np.array([4.5, -1, -1]), np.array([9.0, 1, 1]))) == [2]
    got = store.take([2, 99], dim=4)  # unknown tiles are ignored
    for name in b:
        np.testing.assert_array_equal(got[name], b[name])
    assert store.points == 5 and list(store.info) == [1]
    assert store.read([1], dim=None).keys() == {"xyz", *SCALAR_FIELDS}
    store.destroy()
    assert not (tmp_path / "t.sqlite3").exists() and store.points == 0


def test_tile_ids_are_cubes_of_tile_voxels() -> None:
    from mapper.map.voxels import voxel_keys

    at = np.array([[0.01, 0.0, 0.0], [0.19, 0.0, 0.0], [0.21, 0.0, 0.0], [-0.01, 0, 0]])
    keys, _ = voxel_keys(at, 0.02)
    tiles = tile_ids(keys, 10)  # 0.2 m tiles
    assert tiles[0] == tiles[1] != tiles[2] and tiles[3] != tiles[0]


def test_cone_summary_skips_only_tiles_that_cannot_match() -> None:
    rng = np.random.default_rng(5)
    dim, skipped = 16, 0
    protos = rng.normal(size=(6, dim))
    for trial in range(60):
        # a tile of a few classes, each a tight bundle around its prototype
        classes = rng.choice(6, size=rng.integers(1, 3), replace=False)
        bundles = [protos[c] + 0.1 * rng.normal(size=(40, dim)) for c in classes]
        feats = np.concatenate(bundles).astype(np.float32)
        unit = feats / np.linalg.norm(feats, axis=1, keepdims=True)
        cent, least = tile_summary(unit, 4)
        assert np.all(np.max(unit @ cent.T, axis=1) >= least[np.argmax(unit @ cent.T, axis=1)] - 1e-6)
        text = protos[rng.integers(6)][None] / np.linalg.norm(protos[0])
        neg = (protos / np.linalg.norm(protos, axis=1, keepdims=True))[rng.choice(6, 3, replace=False)]
        min_score = 0.3 if trial % 2 else None
        sims = unit @ np.concatenate([text, neg]).T
        match = (sims[:, 0] > sims[:, 1:].max(axis=1)) & (sims[:, 0] >= (min_score or -np.inf))
        may = cone_may_match(cent, least, text.astype(np.float32), neg.astype(np.float32), min_score)
        assert may or not match.any()  # never skips a tile that holds a match
        skipped += not may
        approximate = centroids_may_match(cent, text.astype(np.float32), neg.astype(np.float32), min_score)
        assert may or not approximate  # skips at least what the exact test skips
    assert skipped > 10  # and does skip tiles


@pytest.mark.parametrize(
    "setting, fragment",
    [
        ({"tile_m": 0.01}, "global_map.tile_m"),
        ({"tile_summary_k": 0}, "global_map.tile_summary_k"),
        ({"max_disk_points": -1}, "global_map.max_disk_points"),
        ({"tile_skip": "some"}, "global_map.tile_skip"),
    ],
)
def test_bad_paging_settings_are_refused(setting: dict[str, object], fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        config_from_dict({"global_map": setting})


def test_learned_features_reach_paged_voxels_without_paging_them_in() -> None:
    full, bounded = GlobalSemanticMap(_cfg()), GlobalSemanticMap(_cfg(max_points=1000))
    first = make_kf(plane_depth(2.0), ov=_ov(1), stamp_ns=1)
    seen = []
    for gmap in (full, bounded):
        gmap.integrate(first)
        gmap.integrate(make_kf(plane_depth(1.0), world_from_cam=ROOM_B, ov=_ov(3), stamp_ns=3))
        keys, xyz = gmap.seen_voxels(first, unlearned=True)  # paged ones too, read
        seen.append((keys, xyz))
        feats = np.random.default_rng(7).normal(size=(keys.shape[0], 8)).astype(np.float32)
        assert gmap.set_features(keys, feats) == keys.shape[0] == 768
    assert bounded.points_paged_in == 0 and bounded.paged_points == 768  # set in the store
    np.testing.assert_array_equal(seen[0][0], seen[1][0])
    np.testing.assert_array_equal(seen[0][1], seen[1][1])
    _assert_same_voxels(bounded, full)
    assert bounded.set_features(keys, feats) == full.set_features(keys, feats) == 0  # once


def test_learned_features_reach_paged_voxels_of_a_map_without_features() -> None:
    full, bounded = GlobalSemanticMap(_cfg()), GlobalSemanticMap(_cfg(max_points=1000))
    first = make_kf(plane_depth(2.0), stamp_ns=1)  # geometry only: the map has no feature dimension
    for gmap in (full, bounded):
        gmap.integrate(first)
        gmap.integrate(make_kf(plane_depth(1.0), world_from_cam=ROOM_B, stamp_ns=3))
        keys, _ = gmap.seen_voxels(first)
        assert gmap.dim is None and keys.shape[0] == 768
        feats = np.random.default_rng(3).normal(size=(keys.shape[0], 8)).astype(np.float32)
        assert gmap.set_features(keys, feats) == 768 and gmap.dim == 8
    assert bounded.paged_points == 768
    _assert_same_voxels(bounded, full)
