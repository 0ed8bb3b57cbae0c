"""The views of keyframes that left the window, kept per global-map voxel for ``average`` and
``average_depth`` (:mod:`mapper.map.evicted_views`): the store's running means, its persistence
and bad input; and a node with a window of 2 keyframes answering as the same node with an unbounded
window (the point of the feature), with and without the depth test, before and after save / load.

Frames: a fake 4-d embedding space (texts "c0".."c3" are one-hot), each frame's OV map one constant
random direction, cameras looking at the wall z = 2 from x in [-0.6, 0.6]."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapper.map.evicted_views import EvictedViewStore, absorb_rows
from mapper.node.config import ConfigError, config_from_dict
from mapper.node.queries import SOURCE_MAP, SOURCE_WINDOW
from mapper.node.service import MapperNode
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import Frame, Load, Ok, Save, Segmentation, SegmentPoints, decode, encode
from tests.mapper.node.answers.test_whole_map import SPACE as WHOLE_MAP_SPACE
from tests.mapper.node.answers.test_whole_map import D, OneHotEncoder
from tests.mapper.node.answers.test_whole_map import _stream as stream_keyframes

SPACE = WHOLE_MAP_SPACE
W, H = 96, 72  # the averaging leaves out a 10 px border
K = np.array([90.0, 90.0, 48.0, 36.0])
TEXTS = ["c0", "c1", "c2", "c3"]


@pytest.fixture(autouse=True)
def onehot_space() -> Iterator[None]:
    register_text_encoder(SPACE, OneHotEncoder)  # test_whole_map's: "c0".."c3" one-hot
    yield
    unregister_text_encoder(SPACE)


def _frames(n: int = 6, seed: int = 0, depth: bool = True) -> list[Frame]:
    rng = np.random.default_rng(seed)
    frames = []
    for i, x in enumerate(np.linspace(-0.6, 0.6, n)):
        pose = np.eye(4)
        pose[0, 3] = x
        ov = np.broadcast_to(np.abs(rng.standard_normal(D)) + 0.05, (6, 8, D)).astype(np.float16)
        depth_m = np.full((H, W), 2.0, np.float32)
        if i % 2:  # half the frames see an object 0.5 m in front of the wall in their left half
            depth_m[:, : W // 2] = 1.5
        frames.append(Frame(seq=i, stamp_ns=i, width=W, height=H, K=K, world_from_cam=pose,
                            rgb=np.zeros((H, W, 3), np.uint8), depth_m=depth_m if depth else None,
                            ov=ov.copy(), ov_space=SPACE))  # fmt: skip
    return frames


def _node(tmp_path: Path, max_keyframes: int, **queries: Any) -> MapperNode:
    queries.setdefault("evicted_views", "depth")
    config = config_from_dict(
        {"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
         "window": {"max_keyframes": max_keyframes, "min_translation_m": 0.01},
         "global_map": {"pixel_stride": 1}, "queries": queries}
    )  # fmt: skip
    return MapperNode(config)


def _stream(node: MapperNode, frames: Sequence[Frame]) -> None:
    stream_keyframes(node, frames)  # test_whole_map's: every frame acked as a keyframe
    if node.ctx.evicted_views is not None:
        node.ctx.evicted_views.process_pending()  # the worker's job (its thread runs only in node.start())


def _segment(node: MapperNode, method: str, xyz: np.ndarray) -> Segmentation:
    msg = SegmentPoints(xyz=xyz.astype(np.float32), texts=TEXTS, method=method)  # type: ignore[arg-type]
    reply = decode(node.handle_query(encode(msg)), direction="reply")
    assert isinstance(reply, Segmentation), reply
    return reply


@pytest.mark.parametrize("isolate", [False, True])
@pytest.mark.parametrize("method", ["average", "average_depth"])
def test_bounded_window_with_evicted_views_answers_as_an_unbounded_one(
    tmp_path: Path, method: str, isolate: bool
) -> None:
    """With the averaging alone (isolate: no blend, the map only where nothing else answers) the
    same answers; with the shipped rules (the map's cosines blended in) at least as many labels."""
    frames = _frames()
    rules: dict[str, Any] = {"map_blend": 0.0, "map_when_more_confident": False} if isolate else {}
    rules["evicted_views_occlusion"] = False  # the window's own averaging counts views through objects too
    unbounded, bounded = _node(tmp_path, 100, **rules), _node(tmp_path, 2, evicted_views="both", **rules)
    plain = _node(tmp_path, 2, evicted_views="off", **rules)
    for node in (unbounded, bounded, plain):
        _stream(node, frames)
    assert len(bounded.state.window) == 2 and len(unbounded.state.window) == 6
    assert plain.ctx.evicted_views is None
    stats = bounded.ctx.status_providers["evicted_views"]()
    assert stats["done"] == 4 and stats["pending"] == 0 and stats["voxels"] > 0 and stats["bytes"] > 0
    xyz = bounded.state.global_map.snapshot().xyz  # the map's voxels (the two maps are the same)
    want = _segment(unbounded, method, xyz)
    got = _segment(bounded, method, xyz)
    without = _segment(plain, method, xyz)
    if not isolate:
        # the shipped rules blend in the map's answer, which the bounded window gives from the
        # evicted views' mean at the voxel and the unbounded one from the fused feature: the
        # labels agree at least as often as without the evicted views
        assert (got.label == want.label).mean() >= (without.label == want.label).mean()
        return
    same = np.abs(got.score - want.score) < 1e-3
    assert same.mean() > 0.99, same.mean()
    assert (got.label == want.label).mean() > 0.99
    # the feature matters: without it the bounded window answers differently at many voxels
    assert (np.abs(without.score - want.score) > 1e-3).mean() > (0.5 if isolate else 0.05)
    assert got.timing_ms["from_evicted"] > 0
    # points only keyframes that left saw: answered, from the map
    only_left = (want.source != 0) & np.isin(got.source, [SOURCE_MAP, SOURCE_WINDOW])
    assert only_left.mean() > 0.99


@pytest.mark.parametrize("mode", ["depth", "both"])
def test_evicted_views_survive_save_and_load(tmp_path: Path, mode: str) -> None:
    node = _node(tmp_path, 2, evicted_views=mode)
    _stream(node, _frames())
    xyz = node.state.global_map.snapshot().xyz
    before = [_segment(node, m, xyz) for m in ("average", "average_depth")]
    assert isinstance(decode(node.handle_query(encode(Save(name="ev"))), direction="reply"), Ok)
    fresh = _node(tmp_path, 2, evicted_views=mode)
    assert isinstance(decode(fresh.handle_query(encode(Load(name="ev"))), direction="reply"), Ok)
    assert len(fresh.state.global_map.evicted) == len(node.state.global_map.evicted) > 0
    for method, want in zip(("average", "average_depth"), before, strict=True):
        got = _segment(fresh, method, xyz)
        np.testing.assert_allclose(got.score, want.score, atol=1e-6)
        assert np.array_equal(got.label, want.label)
        assert (got.timing_ms["from_evicted"] > 0) == (method == "average_depth" or mode == "both")


def test_depth_mode_keeps_one_channel_and_rgb_only_keyframes_are_not_queued(tmp_path: Path) -> None:
    node = _node(tmp_path, 2)  # "depth"
    assert node.config.queries.evicted_views == "depth"
    assert config_from_dict({}).queries.evicted_views == "both"  # the default
    _stream(node, _frames())
    store = node.state.global_map.evicted
    assert store.stats()["views_depth"] > 0 and store.stats()["views_all"] == 0
    both = _node(tmp_path, 2, evicted_views="both")
    _stream(both, _frames())
    assert 0 < store.nbytes < both.state.global_map.evicted.nbytes  # one channel of means, not two
    rgb_only = _node(tmp_path, 2)
    _stream(rgb_only, _frames(depth=False))
    assert rgb_only.ctx.evicted_views is not None and rgb_only.ctx.evicted_views.done == 0  # nothing to keep
    with pytest.raises(ConfigError, match="evicted_views"):
        _node(tmp_path, 2, evicted_views="yes")


def test_rgb_only_keyframes_count_for_average_only() -> None:
    store = EvictedViewStore()
    keys = np.array([5, 9, 2], np.int64)
    feats = np.eye(3, 4, dtype=np.float32)
    store.absorb(keys, {"all": (feats, np.array([True, True, False]))})
    means, counts = store.lookup(np.array([9, 2, 5, 77], np.int64), "all")
    assert counts.tolist() == [1.0, 0.0, 1.0, 0.0]
    np.testing.assert_array_equal(means[0], feats[1])
    assert store.lookup(keys, "depth")[1].tolist() == [0.0, 0.0, 0.0]


def test_store_running_mean_against_float64() -> None:
    rng = np.random.default_rng(3)
    store = EvictedViewStore()
    keys = rng.permutation(1000)[:200].astype(np.int64)
    total = np.zeros((200, 8))
    count = np.zeros(200)
    for _ in range(7):
        feat = rng.standard_normal((200, 8)).astype(np.float32)
        counted = rng.random(200) < 0.6
        store.absorb(keys, {"all": (feat, counted), "depth": (feat, counted & (rng.random(200) < 0.5))})
        total[counted] += feat[counted]
        count += counted
    means, counts = store.lookup(keys, "all")
    assert np.array_equal(counts, count.astype(np.float32))
    has = count > 0
    np.testing.assert_allclose(means[has], total[has] / count[has, None], atol=1e-5)  # float32 running means
    assert store.stats()["keyframes"] == 7
    # compact keeps exactly the given keys' rows and their values
    kept = keys[::3]
    dropped = store.compact(kept)
    assert len(store) == int(has[::3].sum()) and dropped == int(has.sum() - has[::3].sum())
    m2, c2 = store.lookup(kept, "all")
    np.testing.assert_array_equal(m2, means[::3])
    np.testing.assert_array_equal(c2, counts[::3])


def test_store_round_trip_and_bad_input_changes_nothing() -> None:
    store = EvictedViewStore()
    keys = np.arange(10, dtype=np.int64)
    store.absorb(keys, {"all": (np.ones((10, 3), np.float32), np.ones(10, bool))})
    arrays, manifest = store.to_arrays("g.ev")
    copy = EvictedViewStore()
    copy.restore(arrays, manifest, "g.ev")
    assert np.array_equal(copy.lookup(keys, "all")[1], store.lookup(keys, "all")[1])
    assert arrays["g.ev.all_mean"].dtype == np.float32  # saved as kept: a load answers as before the save
    older = {**arrays, "g.ev.all_mean": arrays["g.ev.all_mean"].astype(np.float16)}  # maps saved before
    EvictedViewStore().restore(older, manifest, "g.ev")
    for bad in ({"keys": np.zeros(10, np.int64)}, {"all_count": np.full(10, -1.0, np.float32)},
                {"all_mean": np.zeros((10, 3), np.float64)},
                {"all_mean": np.full((10, 3), np.nan, np.float32)}):  # fmt: skip
        broken = {**arrays, **{f"g.ev.{k}": v for k, v in bad.items()}}
        with pytest.raises(ValueError, match="evicted views section"):
            copy.restore(broken, manifest, "g.ev")
        assert len(copy) == 10  # unchanged
    with pytest.raises(ValueError, match="unknown channel"):
        store.absorb(keys, {"nope": (np.ones((10, 3), np.float32), np.ones(10, bool))})
    with pytest.raises(ValueError, match="samples must be"):
        store.absorb(keys, {"all": (np.ones((9, 3), np.float32), np.ones(9, bool))})
    with pytest.raises(ValueError, match="dimension 5"):
        store.absorb(keys, {"all": (np.ones((10, 5), np.float32), np.ones(10, bool))})
    assert store.lookup(keys, "all")[1].tolist() == [1.0] * 10


def test_prior_reads_the_table_in_place_and_compact_never_moves_rows_under_a_reader() -> None:
    store = EvictedViewStore()
    keys = np.array([3, 1, 2], np.int64)
    store.absorb(keys, {"all": (np.eye(3, dtype=np.float32), np.array([True, True, False]))})
    table, row, weight = store.prior(np.array([1, 2, 3, 99], np.int64), "all")
    assert weight.tolist() == [1.0, 0.0, 1.0, 0.0] and row[1] == -1 and row[3] == -1
    np.testing.assert_array_equal(table[row[0]], [0, 1, 0])
    np.testing.assert_array_equal(table[row[2]], [1, 0, 0])
    again, _, _ = store.prior(keys, "all")
    assert again is table  # no copy per query
    store.absorb(keys, {"all": (np.eye(3, dtype=np.float32)[::-1].copy(), np.ones(3, bool))})
    after, row2, weight2 = store.prior(np.array([3], np.int64), "all")
    assert weight2.tolist() == [2.0]
    np.testing.assert_allclose(after[row2[0]], [0.5, 0, 0.5])  # mean of e0 and the new sample e2
    held = table.copy()
    assert store.compact(np.array([2, 3], np.int64)) == 1  # key 1 leaves; rows of 3 and 2 move ...
    np.testing.assert_array_equal(table, held)  # ... in new arrays: what a query holds is unchanged
    moved, row3, _ = store.prior(np.array([3], np.int64), "all")
    assert moved is not table
    np.testing.assert_allclose(moved[row3[0]], [0.5, 0, 0.5])


def test_absorb_rows_kernel_against_float64_and_bad_input() -> None:
    rng = np.random.default_rng(5)
    mean = np.zeros((50, 16), np.float32)
    count = np.zeros(50, np.float32)
    total = np.zeros((50, 16))
    n = np.zeros(50)
    for _ in range(20):
        rows = rng.permutation(50)[:30].astype(np.int64)
        feat = (100.0 * rng.standard_normal((40, 16))).astype(np.float32)  # large values: no drift
        at = rng.permutation(40)[:30].astype(np.int64)
        absorb_rows(mean, count, rows, feat, at)
        total[rows] += feat[at]
        n[rows] += 1
    has = n > 0
    np.testing.assert_allclose(mean[has], total[has] / n[has, None], rtol=1e-4, atol=1e-3)
    assert np.array_equal(count, n.astype(np.float32)) and not mean[~has].any()
    before = mean.copy()
    with pytest.raises(TypeError, match="float32"):
        absorb_rows(mean.astype(np.float64), count, rows, feat, at)
    with pytest.raises(ValueError, match="out of range"):
        absorb_rows(mean, count, np.array([50], np.int64), feat, np.array([0], np.int64))
    with pytest.raises(ValueError, match="of one D"):
        absorb_rows(mean, count, rows, feat[:, :8].copy(), at)
    assert np.array_equal(mean, before)


@pytest.mark.parametrize("seed", [0, 1])
def test_in_image_keeps_every_point_the_averaging_counts(seed: int) -> None:
    from mapper.map.evicted_views import in_image
    from mapper.model.baselines import OVView, view_samples

    rng = np.random.default_rng(seed)
    xyz = (rng.random((20000, 3)) * [8, 6, 8] - [4, 3, 2]).astype(np.float32)  # some behind the camera
    pose = np.eye(4)
    angle = rng.uniform(-0.5, 0.5)
    pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    pose[:3, 3] = rng.normal(0, 0.5, 3)
    view = OVView(np.ones((6, 8, D), np.float32), K, pose, (W, H), None)
    _, counted = view_samples(xyz, view, use_depth=False)
    rows = in_image(xyz, K, pose, (W, H), 10.0)
    assert counted.sum() > 500
    assert set(np.flatnonzero(counted)) <= set(rows.tolist())
    assert rows.shape[0] < 1.1 * counted.sum()  # and not many more


def test_worker_thread_absorbs_what_the_window_evicts(tmp_path: Path) -> None:
    import threading
    import time

    node = _node(tmp_path, 2)
    for f in _frames():
        decode(node.handle_ingest(encode(f)), direction="reply")
    worker = node.ctx.evicted_views
    assert worker is not None and worker.pending == 4 and len(node.state.global_map.evicted) == 0
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop,), daemon=True)
    thread.start()
    deadline = time.monotonic() + 60.0
    while worker.pending and time.monotonic() < deadline:
        time.sleep(0.01)
    stop.set()
    worker.queue.wake.set()
    thread.join(timeout=10.0)
    assert worker.pending == 0 and worker.done == 4 and len(node.state.global_map.evicted) > 0


def test_worker_projects_the_maps_points_without_copying_its_features(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    node = _node(tmp_path, 2)
    assert node.ctx.evicted_views is not None
    for f in _frames():
        node.handle_ingest(encode(f))
    assert node.ctx.evicted_views.pending > 0
    gmap = node.state.global_map
    calls = []
    monkeypatch.setattr(gmap, "snapshot", lambda: calls.append(1) or pytest.fail("snapshot() copied the map"))
    version = gmap.version
    assert node.ctx.evicted_views.process_pending() > 0
    assert calls == [] and gmap.version == version  # read only the points and keys; the map unchanged
    assert gmap.evicted.stats()["views_depth"] > 0


def test_the_map_answers_with_the_evicted_views_where_its_voxel_has_them() -> None:
    """``fill_from_map`` with ``evicted_view_cosines``: a point the window does not answer takes
    the evicted views' mean at its nearest voxel (the ``depth`` channel first, then ``all``), and
    the voxel's fused feature where the store has no view of it."""
    from mapper.map.global_map import GlobalMapConfig, GlobalSemanticMap
    from mapper.node.queries import SOURCE_NONE, evicted_view_cosines, fill_from_map

    frame = _frames(1)[0]
    frame.ov = np.zeros_like(frame.ov)
    frame.ov[..., 0] = 1.0  # every voxel's fused feature says c0
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=4))
    gmap.integrate(frame, 1)
    snap = gmap.snapshot()
    assert snap.keys is not None and len(snap) >= 3
    emb = OneHotEncoder().encode(TEXTS)
    xyz = snap.xyz[:3].astype(np.float32)
    nearest = snap.nearest_with_feature(xyz, 0.125)
    assert (nearest == np.arange(3)).all()
    assert evicted_view_cosines(gmap.evicted, snap, nearest, emb) is None  # nothing evicted yet

    def one_hot(i: int) -> np.ndarray:
        return np.eye(D, dtype=np.float32)[[i]]

    gmap.evicted.absorb(snap.keys[:1], {"depth": (one_hot(2), np.ones(1, bool)),
                                        "all": (one_hot(1), np.ones(1, bool))})
    gmap.evicted.absorb(snap.keys[1:2], {"all": (one_hot(3), np.ones(1, bool))})
    map_cos = evicted_view_cosines(gmap.evicted, snap, nearest, emb)
    assert map_cos is not None
    assert map_cos[1].tolist() == [True, True, False]
    unseen = np.zeros(3, bool)
    none = np.full(3, -1, np.int32)
    label, score, source = fill_from_map(snap, xyz, emb, none, np.zeros(3, np.float32), unseen, 0.125,
                                         nearest=nearest, map_cos=map_cos)
    assert label.tolist() == [2, 3, 0] and (source == SOURCE_MAP).all()
    np.testing.assert_allclose(score, 1.0, atol=1e-3)
    # without it, the fused feature answers everywhere; beyond the radius nothing does
    label, _, _ = fill_from_map(snap, xyz, emb, none, np.zeros(3, np.float32), unseen, 0.125, nearest=nearest)
    assert label.tolist() == [0, 0, 0]
    far = np.full((1, 3), 50.0, np.float32)
    label, _, source = fill_from_map(snap, far, emb, none[:1], np.zeros(1, np.float32), unseen[:1], 0.125,
                                     map_cos=(np.ones((1, len(TEXTS)), np.float32), np.ones(1, bool)))
    assert label.tolist() == [-1] and source.tolist() == [SOURCE_NONE]


def test_the_learned_answer_mixes_the_voxel_feature_with_the_evicted_views() -> None:
    """``map_cos_weight`` < 1 (``queries.evicted_views_learned_weight`` for ``govnesf``): the map's
    cosines are ``(1 - w)`` x the voxel's own + ``w`` x the evicted views' mean, exactly."""
    from mapper.map.global_map import GlobalMapConfig, GlobalSemanticMap
    from mapper.node.queries import fill_from_map

    frame = _frames(1)[0]
    frame.ov = np.zeros_like(frame.ov)
    frame.ov[..., 0] = 1.0  # the voxels' own feature: c0
    gmap = GlobalSemanticMap(GlobalMapConfig(pixel_stride=4))
    gmap.integrate(frame, 1)
    snap = gmap.snapshot()
    emb = OneHotEncoder().encode(TEXTS)
    xyz = snap.xyz[:2].astype(np.float32)
    nearest = snap.nearest_with_feature(xyz, 0.125)
    evicted = np.zeros((2, len(TEXTS)), np.float32)
    evicted[:, 1] = 1.0  # the evicted views say c1
    unseen, none = np.zeros(2, bool), np.full(2, -1, np.int32)
    for w, want_label, want_score in ((1.0, 1, 1.0), (0.3, 0, 0.7), (0.7, 1, 0.7), (0.0, 0, 1.0)):
        label, score, _ = fill_from_map(snap, xyz, emb, none, np.zeros(2, np.float32), unseen, 0.125,
                                        nearest=nearest, map_cos=(evicted, np.ones(2, bool)),
                                        map_cos_weight=w)
        assert label.tolist() == [want_label] * 2, w
        np.testing.assert_allclose(score, want_score, atol=2e-3)


def test_store_cosines_equal_a_float64_reference_per_point() -> None:
    """``EvictedViewStore.cosines``: per point, the cosine of its voxel's channel mean (``depth``
    first, then ``all``, at least ``min_views`` views) with each text; repeats share a voxel."""
    from mapper.map.evicted_views import EvictedViewStore

    rng = np.random.default_rng(3)
    store = EvictedViewStore()
    keys = np.array([5, 9, 14, 20], np.int64)
    depth = rng.standard_normal((4, D)).astype(np.float32)
    every = rng.standard_normal((4, D)).astype(np.float32)
    store.absorb(keys[:2], {"depth": (depth[:2], np.ones(2, bool)), "all": (every[:2], np.ones(2, bool))})
    store.absorb(keys[2:], {"all": (every[2:], np.ones(2, bool))})
    store.absorb(keys[3:], {"all": (every[3:], np.ones(1, bool))})  # key 20: two views
    emb = rng.standard_normal((3, D)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    asked = np.array([9, 5, 9, 14, 99, 20], np.int64)  # a repeat and a key the store lacks
    cos, given = store.cosines(asked, emb)
    assert given.tolist() == [True, True, True, True, False, True]
    want = {5: depth[0], 9: depth[1], 14: every[2], 20: every[3]}  # 20's mean of two equal views
    for i, key in enumerate(asked.tolist()):
        if key in want:
            m = want[key].astype(np.float64)
            np.testing.assert_allclose(cos[i], emb.astype(np.float64) @ (m / np.linalg.norm(m)), atol=1e-5)
    assert not cos[4].any()
    cos2, given2 = store.cosines(asked, emb, min_views=2)
    assert given2.tolist() == [False, False, False, False, False, True]
    np.testing.assert_allclose(cos2[5], cos[5], atol=1e-6)


def test_occlusion_keeps_a_keyframe_with_depth_from_recording_what_it_cannot_see(tmp_path: Path) -> None:
    """``queries.evicted_views_occlusion``: the wall behind the object the odd frames measured at
    1.5 m (their left half) takes fewer ``all`` views than without the test; the ``depth`` channel
    is the same either way; keyframes that saw the wall itself count as before."""
    frames = _frames()
    on = _node(tmp_path, 2, evicted_views="both", evicted_views_occlusion=True)
    off = _node(tmp_path, 2, evicted_views="both", evicted_views_occlusion=False)
    for node in (on, off):
        _stream(node, frames)
    keys = off.state.global_map.snapshot().keys
    xyz = off.state.global_map.snapshot().xyz
    assert keys is not None
    wall = np.abs(xyz[:, 2] - 2.0) < 0.05
    _, n_on = on.state.global_map.evicted.lookup(keys[wall], "all")
    _, n_off = off.state.global_map.evicted.lookup(keys[wall], "all")
    assert (n_on <= n_off).all() and (n_on < n_off).any()
    _, d_on = on.state.global_map.evicted.lookup(keys, "depth")
    _, d_off = off.state.global_map.evicted.lookup(keys, "depth")
    np.testing.assert_array_equal(d_on, d_off)


def test_behind_surface_against_a_float64_reference() -> None:
    """Random points against a random depth image: hidden exactly where a point is in front, in the
    image, at a pixel with depth, and more than the tolerance behind it."""
    from mapper.map.evicted_views import behind_surface

    rng = np.random.default_rng(4)
    depth = rng.uniform(0.5, 4.0, (24, 32)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0
    depth[0, 0] = np.nan
    K = np.array([30.0, 30.0, 16.0, 12.0])
    pose = np.eye(4)
    pose[:3, 3] = [0.2, -0.1, 0.3]
    pts = rng.uniform([-3, -3, -1], [3, 3, 8], (4000, 3))
    got = behind_surface(pts, K, pose, depth, 0.25)
    want = np.zeros(len(pts), bool)
    for i, p in enumerate(pts - pose[:3, 3]):
        if p[2] <= 1e-6:
            continue
        c, r = int(np.floor(p[0] / p[2] * 30 + 16)), int(np.floor(p[1] / p[2] * 30 + 12))
        if 0 <= c < 32 and 0 <= r < 24 and np.isfinite(depth[r, c]) and depth[r, c] > 0:
            want[i] = p[2] > depth[r, c] * 1.25
    np.testing.assert_array_equal(got, want)
    assert want.sum() > 100 and (~want).sum() > 100
