"""The reduced views of evicted keyframes without depth (:mod:`mapper.map.evicted_frames`): the
reduction, the samples against the averaging kernel over the same views (the frustum culling
loses none), the memory budget, persistence and bad input; and a node with a window of 2 RGB-only
keyframes answering ``average`` as the same node with an unbounded window, where without the store
the points only evicted keyframes saw get no answer.

Node frames: test_evicted_views' (a fake 4-d space, each frame's OV map one constant direction,
cameras at x in [-0.6, 0.6] looking at the wall z = 2), without depth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapper.kernels.average import OVView, kernel_average
from mapper.map.evicted_frames import EvictedFrameStore, as_dtype, merged_prior, reduce_ov
from mapper.node.config import ConfigError, config_from_dict
from mapper.node.queries import SOURCE_MAP, SOURCE_NONE
from mapper.node.service import MapperNode
from protocol.messages import Load, Ok, Save, decode, encode
from tests.mapper.map.test_evicted_views import _frames, _segment, _stream, onehot_space  # noqa: F401

_BIG = 1 << 30


def test_reduce_ov_area_averages_within_the_cells() -> None:
    rng = np.random.default_rng(0)
    ov = rng.standard_normal((30, 40, 5)).astype(np.float16)
    small = reduce_ov(ov, 300)
    assert small.shape == (15, 20, 5) and small.dtype == np.float32
    want = ov.astype(np.float32).reshape(15, 2, 20, 2, 5).mean(axis=(1, 3))
    np.testing.assert_allclose(small, want, atol=1e-5)
    odd = reduce_ov(ov[:29, :37], 100)  # not a whole factor: fractional areas, the mean kept
    assert odd.shape[0] * odd.shape[1] <= 100
    np.testing.assert_allclose(odd.mean(axis=(0, 1)), ov[:29, :37].astype(np.float32).mean(axis=(0, 1)),
                               atol=1e-4)
    assert reduce_ov(ov[:1, :40], 7).shape[:2] == (1, 7)
    np.testing.assert_array_equal(reduce_ov(ov[:10, :10], 300), ov[:10, :10].astype(np.float32))
    with pytest.raises(ValueError):
        reduce_ov(ov[0], 10)


def test_reduce_ov_whole_blocks_equal_the_area_weights() -> None:
    """Where the reduced size divides the map's, the block mean (the fast path) equals the area
    weights' average (the general path) in float64."""
    from mapper.map.evicted_frames import _area_weights

    ov = np.random.default_rng(1).standard_normal((120, 160, 6)).astype(np.float16)
    small = reduce_ov(ov, 4800)  # 60 x 80: 2 x 2 blocks
    want = np.einsum("ih,hwd,jw->ijd", _area_weights(120, 60).astype(np.float64), ov.astype(np.float64),
                     _area_weights(160, 80).astype(np.float64))
    assert small.shape == (60, 80, 6) and small.dtype == np.float32
    np.testing.assert_allclose(small, want, atol=1e-6)


def test_as_dtype_converts_half_floats_as_numpy_does() -> None:
    """float16 <-> float32 through OpenCV: bit for bit numpy's cast (rounding, overflow to Inf,
    signed zeros, subnormals, NaN), any shape and strides; other dtypes as numpy."""
    rng = np.random.default_rng(3)
    wide = (rng.standard_normal((7, 9, 5)) * 10.0 ** rng.integers(-9, 6, (7, 9, 5))).astype(np.float32)
    wide.flat[:6] = [70000.0, -1e-9, -0.0, np.inf, -np.inf, np.nan]
    with np.errstate(over="ignore"):
        want16 = wide.astype(np.float16)
    got16 = as_dtype(wide, np.float16)
    assert got16.dtype == np.float16 and got16.flags.c_contiguous
    assert np.array_equal(got16.view(np.uint16) & 0x7FFF >= 0x7C01, want16.view(np.uint16) & 0x7FFF >= 0x7C01)
    finite = np.isfinite(want16)
    assert np.array_equal(got16[finite].view(np.uint16), want16[finite].view(np.uint16))  # signed zeros too
    assert np.array_equal(np.isinf(got16), np.isinf(want16))
    half = want16[:, ::2, :]  # strided
    got32 = as_dtype(half, np.float32)
    assert got32.dtype == np.float32 and got32.shape == half.shape
    np.testing.assert_array_equal(got32, half.astype(np.float32))
    assert as_dtype(np.arange(4, dtype=np.int32), np.float32).tolist() == [0.0, 1.0, 2.0, 3.0]
    assert as_dtype(np.zeros((0, 3), np.float16), np.float32).shape == (0, 3)


def _random_views(rng: np.random.Generator, n: int, dim: int) -> list[tuple[Any, ...]]:
    views = []
    for _ in range(n):
        yaw = rng.uniform(-np.pi, np.pi)
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
        pose[:3, 3] = rng.uniform(-2, 2, 3)
        ov = rng.standard_normal((12, 16, dim)).astype(np.float32)
        views.append((ov, np.array([60.0, 60.0, 40.0, 30.0]), pose, (80, 60)))
    return views


@pytest.mark.parametrize("seed", [0, 1])
def test_means_equal_the_averaging_kernel_over_the_reduced_views(seed: int) -> None:
    rng = np.random.default_rng(seed)
    store = EvictedFrameStore()
    views = _random_views(rng, 40, 6)
    for ov, k, pose, wh in views:
        assert store.add(ov, k, pose, wh, max_cells=48, budget_bytes=_BIG) == []
    pts = rng.uniform(-4, 4, (3000, 3)).astype(np.float32)
    rows, mean, count = store.means(pts, block=128)  # many blocks: the culling is exercised
    parsed = [OVView(reduce_ov(ov, 48), k, pose, wh, None) for ov, k, pose, wh in views]
    want, n = kernel_average(pts, parsed, use_depth=False, border_px=10.0, depth_rel_tol=0.25,
                             distance_power=0.0, vw=None, dim=6, texts=None, raw=True, cache_table=False)
    assert np.array_equal(rows, np.flatnonzero(n > 0)) and 0 < rows.size < pts.shape[0]
    np.testing.assert_array_equal(count, n[rows].astype(np.float32))
    np.testing.assert_allclose(mean, want[rows], atol=1e-5)


def test_means_with_occlusion_equal_the_kernel_against_the_points_z_buffers() -> None:
    """With an occlusion footprint a kept view counts for a point only where the points' own
    z-buffer in that view (``occluder_depths``, as ``average_depth`` tests window keyframes
    without depth) passes it: the same as the averaging kernel with those z-buffers as depth."""
    from mapper.geometry.splat import occluder_depths

    rng = np.random.default_rng(5)
    store = EvictedFrameStore()
    views = _random_views(rng, 30, 6)  # 80 x 60 images: the z-buffers at full size
    for ov, k, pose, wh in views:
        store.add(ov, k, pose, wh, max_cells=48, budget_bytes=_BIG)
    pts = rng.uniform(-4, 4, (2000, 3)).astype(np.float32)
    footprint = 0.3
    rows, mean, count = store.means(pts, block=128, occlusion_footprint_m=footprint)
    Ks, poses = np.stack([v[1] for v in views]), np.stack([v[2] for v in views])
    z = occluder_depths(pts, Ks, poses, 80, 60, footprint)
    parsed = [OVView(reduce_ov(ov, 48), k, pose, wh, z[i]) for i, (ov, k, pose, wh) in enumerate(views)]
    want, n = kernel_average(pts, parsed, use_depth=True, border_px=10.0, depth_rel_tol=0.25,
                             distance_power=0.0, vw=None, dim=6, texts=None, raw=True, cache_table=False)
    assert np.array_equal(rows, np.flatnonzero(n > 0))
    np.testing.assert_array_equal(count, n[rows].astype(np.float32))
    np.testing.assert_allclose(mean, want[rows], atol=1e-5)
    _, _, untested = store.means(pts, block=128)
    assert count.sum() < untested.sum()  # some views hid some points


def test_occlusion_drops_the_view_only_for_the_hidden_point() -> None:
    """A point right behind another on the same ray of a kept view (and a patch of points around
    the front one, the occluder) loses that view; the front point keeps it; the occluders given
    apart count as the points' own."""
    store = EvictedFrameStore()
    ov = np.ones((12, 16, 4), np.float32)
    store.add(ov, np.array([60.0, 60.0, 40.0, 30.0]), np.eye(4), (80, 60), max_cells=48, budget_bytes=_BIG)
    gx, gy = np.meshgrid(np.linspace(-0.2, 0.2, 9), np.linspace(-0.2, 0.2, 9))
    front = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 2.0)], 1).astype(np.float32)
    behind = np.array([[0.0, 0.0, 3.0]], np.float32)
    pts = np.concatenate([front, behind])
    rows, _, _ = store.means(pts, occlusion_footprint_m=0.1)
    assert pts.shape[0] - 1 not in rows and 40 in rows  # the hidden point lost its view, the centre kept it
    rows_alone, _, _ = store.means(behind, occlusion_footprint_m=0.1)
    assert rows_alone.tolist() == [0]  # nothing in front of it: the view counts
    rows_given, _, _ = store.means(behind, occlusion_footprint_m=0.1, occluders=pts)
    assert rows_given.size == 0


def test_budget_drops_the_oldest_and_counts_them() -> None:
    rng = np.random.default_rng(2)
    store = EvictedFrameStore()
    views = _random_views(rng, 5, 4)
    one = 48 * 4 * 4  # the table rows of one view; the per-view constants are a few hundred bytes more
    dropped = [store.add(*v, max_cells=48, budget_bytes=3 * one + 1024) for v in views]
    assert [len(d) for d in dropped] == [0, 0, 0, 1, 1]
    np.testing.assert_array_equal(dropped[3][0].world_from_cam, views[0][2])  # the oldest first
    assert dropped[3][0].ov.shape == (6, 8, 4) and dropped[3][0].depth_m is None
    stats = store.stats()
    assert stats["frames"] == len(store) == 3 and stats["frames_dropped"] == 2 and stats["frames_added"] == 5
    assert stats["frames_bytes"] == store.nbytes <= 3 * one + 1024
    # a budget that holds no view: the view comes back at once
    back = store.add(*views[0], max_cells=48, budget_bytes=10)
    assert len(back) == 4 and len(store) == 0 and store.stats()["frames_dropped"] == 6


def test_bad_input_changes_nothing_and_the_store_round_trips() -> None:
    rng = np.random.default_rng(3)
    store = EvictedFrameStore()
    for v in _random_views(rng, 3, 4):
        store.add(*v, max_cells=48, budget_bytes=_BIG)
    ov, k, pose, wh = _random_views(rng, 1, 4)[0]
    for bad in ((ov[..., :3], k, pose, wh), (ov, k[:3], pose, wh), (ov, k, pose * np.nan, wh),
                (ov, k, pose, (0, 5))):
        with pytest.raises(ValueError):
            store.add(*bad, max_cells=48, budget_bytes=_BIG)
    assert len(store) == 3
    pts = rng.uniform(-3, 3, (500, 3)).astype(np.float32)
    before = store.means(pts)
    arrays, manifest = store.to_arrays("f")
    fresh = EvictedFrameStore()
    fresh.restore(arrays, manifest, "f")
    for a, b in zip(fresh.means(pts), before, strict=True):
        np.testing.assert_array_equal(a, b)
    for field in ("ov", "K", "image_wh"):
        broken = dict(arrays)
        broken[f"f.{field}"] = broken[f"f.{field}"][:1]
        with pytest.raises(ValueError, match=field):
            fresh.restore(broken, manifest, "f")
    assert len(fresh) == 3
    # merged with a voxel prior: the views-weighted mean of both
    p_tab = np.ones((1, 4), np.float32)
    merged = merged_prior(2, (p_tab, np.array([0, -1]), np.array([3.0, 0.0], np.float32)), np.array([0]),
                          np.zeros((1, 4), np.float32), np.array([1.0], np.float32), 4)
    assert merged is not None
    np.testing.assert_allclose(merged[0][0], 0.75)
    assert merged[1].tolist() == [0, -1] and merged[2].tolist() == [4.0, 0.0]


def _node(tmp_path: Path, max_keyframes: int, **queries: Any) -> MapperNode:
    config = config_from_dict(
        {"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
         "window": {"max_keyframes": max_keyframes, "min_translation_m": 0.01},
         "global_map": {"pixel_stride": 1}, "queries": {"evicted_views": "both", **queries}}
    )  # fmt: skip
    return MapperNode(config)


def _wall(n: int = 400) -> np.ndarray:
    xs, ys = np.meshgrid(np.linspace(-1.4, 1.4, 40), np.linspace(-0.5, 0.5, n // 40))
    return np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], axis=1).astype(np.float32)


def test_rgb_only_window_answers_what_evicted_keyframes_saw(tmp_path: Path) -> None:
    frames = _frames(depth=False)
    unbounded = _node(tmp_path, 100)
    kept = _node(tmp_path, 2, evicted_frames_mb=16.0)
    plain = _node(tmp_path, 2, evicted_frames_mb=0.0)
    for node in (unbounded, kept, plain):
        _stream(node, frames)
    assert len(kept.state.global_map.snapshot()) == 0  # no depth, no map voxels: nothing to keep per voxel
    stats = kept.ctx.status_providers["evicted_views"]()
    assert stats["frames"] == 4 and stats["frames_dropped"] == 0 and stats["frames_bytes"] > 0
    xyz = _wall()
    want, got, without = (_segment(n, "average", xyz) for n in (unbounded, kept, plain))
    seen = want.label >= 0
    only_evicted = seen & (without.source == SOURCE_NONE)
    assert only_evicted.sum() > 20  # points only keyframes that left saw
    assert (got.source[only_evicted] == SOURCE_MAP).all()
    assert np.array_equal(got.label, want.label)
    np.testing.assert_allclose(got.score, want.score, atol=1e-5)  # constant OV maps: reduced exactly
    assert got.timing_ms["from_evicted"] >= only_evicted.sum()
    # saved and loaded with the map
    assert isinstance(decode(kept.handle_query(encode(Save(name="evf"))), direction="reply"), Ok)
    fresh = _node(tmp_path, 2, evicted_frames_mb=16.0)
    assert isinstance(decode(fresh.handle_query(encode(Load(name="evf"))), direction="reply"), Ok)
    assert len(fresh.state.global_map.evicted.frames) == 4
    # the loaded window keeps its two keyframes: the same answer
    again = _segment(fresh, "average", xyz)
    np.testing.assert_allclose(again.score, got.score, atol=1e-6)


def test_a_tight_budget_hands_dropped_views_to_the_voxel_means(tmp_path: Path) -> None:
    node = _node(tmp_path, 2, evicted_frames_mb=0.0001, evicted_frames_cells=48)  # 105 bytes: no view fits
    _stream(node, _frames(depth=False))
    stats = node.ctx.status_providers["evicted_views"]()
    assert stats["frames"] == 0 and stats["frames_dropped"] == 4
    assert stats["done"] == 4 and stats["keyframes"] == 4


@pytest.mark.parametrize("key,value", [("evicted_frames_mb", -1.0), ("evicted_frames_mb", 1e9),
                                       ("evicted_frames_cells", 0)])
def test_bad_config_is_refused(tmp_path: Path, key: str, value: Any) -> None:
    with pytest.raises(ConfigError, match=key):
        _node(tmp_path, 2, **{key: value})


def test_the_learned_answer_takes_the_kept_views_where_nothing_else_answers(tmp_path: Path) -> None:
    """``govnesf``'s map answer (``answer_from_map`` with ``learned``): a point neither its window
    nor a map voxel answers takes the kept views' mean, the averaging's answer there."""
    from mapper.node.answers.segment import answer_from_map

    frames = _frames(depth=False)
    unbounded, kept = _node(tmp_path, 100), _node(tmp_path, 2, evicted_frames_mb=16.0)
    for node in (unbounded, kept):
        _stream(node, frames)
    xyz = _wall()
    want = _segment(unbounded, "average", xyz)
    emb = kept.ctx.text_encoder("test").encode(["c0", "c1", "c2", "c3"])
    n = xyz.shape[0]
    label, _, source = answer_from_map(kept.ctx, xyz, emb, np.full(n, -1, np.int32), np.zeros(n, np.float32),
                                       np.zeros(n, bool), learned=True)
    old = kept.state.window.keyframes[0].world_from_cam[0, 3]  # points left of the window's views
    only_left = (want.label >= 0) & (xyz[:, 0] < old - 0.9)
    assert only_left.sum() > 20
    assert (source[only_left] == SOURCE_MAP).all()
    assert np.array_equal(label[only_left], want.label[only_left])
    # without the kept views: nothing answers them
    plain = _node(tmp_path, 2, evicted_frames_mb=0.0)
    _stream(plain, frames)
    _, _, none = answer_from_map(plain.ctx, xyz, emb, np.full(n, -1, np.int32), np.zeros(n, np.float32),
                                 np.zeros(n, bool), learned=True)
    assert (none[only_left] == SOURCE_NONE).all()


def test_depth_tested_answers_take_the_kept_views_only_where_nothing_answers(tmp_path: Path) -> None:
    """``average_depth`` (a depth test) never mixes the kept views in, but a point only keyframes
    that left saw, which nothing else answers, takes their answer rather than none."""
    frames = _frames(depth=False)
    kept, plain = _node(tmp_path, 2, evicted_frames_mb=16.0), _node(tmp_path, 2, evicted_frames_mb=0.0)
    for node in (kept, plain):
        _stream(node, frames)
    xyz = _wall()
    got, without = _segment(kept, "average_depth", xyz), _segment(plain, "average_depth", xyz)
    filled = (without.source == SOURCE_NONE) & (got.source != SOURCE_NONE)
    assert filled.sum() > 20
    assert (got.source[filled] == SOURCE_MAP).all() and (got.label[filled] >= 0).all()
    answered = without.source != SOURCE_NONE  # what the depth-tested answer gave stays as it was
    assert np.array_equal(got.label[answered], without.label[answered])
    np.testing.assert_allclose(got.score[answered], without.score[answered], atol=1e-6)


class _ConstantLearned:
    """A stand-in learned backend (falls back to averaging like ``govnesf``): text ``c3`` at every
    point, cosine 1, the others 0."""

    ready = True
    fallback_to_averaging = True

    def depth_tested(self, msg: Any) -> bool:
        return bool(msg.use_depth)

    def segment(self, msg: Any, want_cos: bool) -> Any:
        from mapper.node.backends import PointAnswer

        n = len(msg.xyz)
        cos = np.zeros((n, len(msg.texts)), np.float32)
        cos[:, 3] = 1.0
        return PointAnswer(label=np.full(n, 3, np.int32), score=np.ones(n, np.float32), seen=np.ones(n, bool),
                           cos=cos)


@pytest.mark.parametrize("share", [0.0, 1.0])
def test_learned_answers_mix_the_evicted_views_by_their_share(tmp_path: Path, share: float) -> None:
    """``queries.learned_evicted_views``: where only views that left the window count for a point
    (share 1) the learned answer mixed at weight 1 is theirs (the averaging's there); where none
    left, or with the setting at 0, the model's answer stays."""
    from mapper.node.answers.segment import SegmentAnswers

    node = _node(tmp_path, 2, evicted_frames_mb=16.0, learned_evicted_views=share,
                 map_when_more_confident=False)
    _stream(node, _frames(depth=False))
    assert isinstance(node.segment, SegmentAnswers)
    node.segment.register("govnesf", _ConstantLearned())  # type: ignore[arg-type]
    xyz = _wall()
    got, average = _segment(node, "govnesf", xyz), _segment(node, "average", xyz)
    only_evicted = average.source == SOURCE_MAP  # no window view counts there
    window = average.source == 1
    assert only_evicted.sum() > 20 and window.sum() > 20
    assert (got.label[window] == 3).mean() > 0.5  # window views and kept ones: a mix that leans on the model
    if share == 0.0:
        assert (got.label[got.label >= 0] == 3).all()
    else:
        assert np.array_equal(got.label[only_evicted], average.label[only_evicted])
        assert (average.label[only_evicted] != 3).any()  # the test can tell the two apart


def test_learned_maps_are_read_only_by_learned_means_and_round_trip() -> None:
    """A view kept with the learned model's features (:meth:`EvictedFrameStore.add` ``learned`` or
    later :meth:`~EvictedFrameStore.set_learned` by key) answers ``means(learned=True)`` from them
    (invalid cells from its reduced map); ``means()`` reads the OV maps as before."""
    rng = np.random.default_rng(5)
    views = _random_views(rng, 4, 4)
    plain, store = EvictedFrameStore(), EvictedFrameStore()
    learned_maps = [rng.standard_normal((6, 8, 4)).astype(np.float32) for _ in views]
    valid = np.ones((6, 8), bool)
    valid[:, :2] = False
    for i, v in enumerate(views):
        plain.add(*v, max_cells=48, budget_bytes=_BIG)
        store.add(*v, max_cells=48, budget_bytes=_BIG, key=("r", i),
                  learned=(learned_maps[i], valid) if i == 0 else None)
    assert store.set_learned(("r", 1), (learned_maps[1], valid))
    assert not store.set_learned(("r", 9), (learned_maps[1], valid))  # no such view: nothing changes
    with pytest.raises(ValueError, match="learned"):
        store.set_learned(("r", 2), (learned_maps[2][:3], valid))
    assert store.stats()["frames_learned"] == 2 and store.nbytes > plain.nbytes
    pts = rng.uniform(-4, 4, (3000, 3)).astype(np.float32)
    for a, b in zip(store.means(pts), plain.means(pts), strict=True):  # the averaging: unchanged
        np.testing.assert_array_equal(a, b)
    rows, mean, count = store.means(pts, learned=True)
    # the same as a store whose views 0 and 1 carry the learned maps (the invalid cells their own)
    swapped = EvictedFrameStore()
    for i, (ov, k, pose, wh) in enumerate(views):
        small = reduce_ov(ov, 48)
        if i < 2:
            small = np.where(valid[..., None], learned_maps[i], small)
        swapped.add(small, k, pose, wh, max_cells=48, budget_bytes=_BIG)
    want = swapped.means(pts)
    assert np.array_equal(rows, want[0]) and np.array_equal(count, want[2])
    np.testing.assert_allclose(mean, want[1], atol=1e-6)
    arrays, manifest = store.to_arrays("f")
    fresh = EvictedFrameStore()
    fresh.restore(arrays, manifest, "f")
    for a, b in zip(fresh.means(pts, learned=True), (rows, mean, count), strict=True):
        np.testing.assert_array_equal(a, b)
    broken = dict(arrays)
    broken["f.learned"] = broken["f.learned"][:1]
    with pytest.raises(ValueError, match="learned"):
        EvictedFrameStore().restore(broken, manifest, "f")
    legacy = {k: v for k, v in arrays.items() if "learned" not in k}  # a map saved before learned maps
    old = EvictedFrameStore()
    old.restore(legacy, {**manifest, "learned": False}, "f")
    for a, b in zip(old.means(pts, learned=True), plain.means(pts), strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_learned_answer_reads_the_learned_maps_offered_before_or_after_a_view_is_kept(
    tmp_path: Path,
) -> None:
    """The pre-eviction worker's learned map of a keyframe (``EvictedViews.offer_learned``) reaches
    its kept view whether it comes before the keyframe is kept or after; ``govnesf``'s map answer
    then takes it where only the kept views answer, ``average`` keeps the OV maps."""
    from mapper.map.evicted_frames import reduced_shape
    from mapper.node.answers.segment import answer_from_map

    frames = _frames(depth=False)
    node = _node(tmp_path, 2, evicted_frames_mb=16.0)
    worker = node.ctx.evicted_views
    assert worker is not None
    _stream(node, frames[:2])
    k0, k1 = node.state.window.keyframes
    _stream(node, frames[2:3])  # k0 leaves and is kept; k1 stays in the window
    gmap = node.state.global_map
    emb = node.ctx.text_encoder("test").encode(["c0", "c1", "c2", "c3"])
    grid = reduced_shape(6, 8, node.ctx.config.queries.evicted_frames_cells)
    cells = np.broadcast_to(emb[3] * 5.0, (*grid, emb.shape[1])).astype(np.float32)  # every cell "c3"
    learned = (cells, np.ones(grid, bool))
    assert gmap.evicted.frames.stats()["frames_learned"] == 0
    worker.offer_learned(k0, gmap, learned)  # after it was kept: given at once
    assert gmap.evicted.frames.stats()["frames_learned"] == 1
    worker.offer_learned(k1, gmap, learned)  # before: it waits for the keyframe
    assert gmap.evicted.frames.stats()["frames_learned"] == 1
    _stream(node, frames[3:])
    assert gmap.evicted.frames.stats()["frames_learned"] == 2 and worker.learned_late == 0
    assert worker.stats()["frames_learned"] == 2
    xyz = _wall()
    n = xyz.shape[0]
    args = (xyz, emb, np.full(n, -1, np.int32), np.zeros(n, np.float32), np.zeros(n, bool))
    label_l, _, source = answer_from_map(node.ctx, *args, learned=True)
    plain = _node(tmp_path, 2, evicted_frames_mb=16.0)
    _stream(plain, frames)
    label_p, _, source_p = answer_from_map(plain.ctx, *args, learned=True)
    answered = source == SOURCE_MAP
    assert answered.sum() > 20 and np.array_equal(source, source_p)
    changed = answered & (label_l != label_p)
    assert changed.sum() > 0 and (label_l[changed] == 3).all()  # only ever toward the learned maps' text


@pytest.mark.parametrize("share", [0.0, 1.0])
def test_learned_answers_with_depth_mix_the_evicted_views_before_the_maps_blend(
    tmp_path: Path, share: float
) -> None:
    """``queries.learned_evicted_views_blended``: in a window with depth, where ``map_blend`` applies
    (``govnesf`` without a depth test), the model's cosines are mixed with the voxels' evicted views
    by their share before the map's blend; at 0 the answer is as before (the map's blend alone)."""
    from mapper.node.answers.segment import SegmentAnswers

    def answers(weight: float) -> Any:
        node = _node(tmp_path, 2, learned_evicted_views_blended=weight)
        _stream(node, _frames(depth=True))
        assert isinstance(node.segment, SegmentAnswers)
        node.segment.register("govnesf", _ConstantLearned())  # type: ignore[arg-type]
        return node, _segment(node, "govnesf", _wall())

    node, got = answers(share)
    _, off = answers(0.0)
    assert node.ctx.map_blend(depth_tested=False) > 0  # the window has depth: the blend applies
    mixed = got.timing_ms.get("mixed", 0.0)
    if share == 0.0:
        assert mixed == 0.0
    else:
        assert mixed > 20  # points the evicted views count for took their share
        assert not np.array_equal(got.score, off.score)


@pytest.mark.parametrize("order", ["fill", "first"])
def test_depth_tested_answers_in_an_rgb_only_window_can_take_the_kept_views_before_the_map(
    tmp_path: Path, order: str
) -> None:
    """``queries.evicted_frames_depth_tested``: a map voxel that says "c0" lies at the points only
    evicted keyframes saw; "fill" answers them from the voxel, "first" from the kept views (as the
    node holding every keyframe does)."""
    from mapper.map.window import Keyframe
    from tests.mapper.map.test_evicted_views import SPACE, H, K, W

    frames = _frames(depth=False)
    unbounded = _node(tmp_path, 100)
    kept = _node(tmp_path, 2, evicted_frames_mb=16.0, evicted_frames_depth_tested=order)
    for node in (unbounded, kept):
        _stream(node, frames)
    pose = np.eye(4)
    pose[0, 3] = -0.6
    ov = np.zeros((6, 8, 4), np.float16)
    ov[..., 0] = 1.0  # "c0" everywhere it sees
    voxels = Keyframe(seq=99, stamp_ns=99, camera="other", K=K, world_from_cam=pose,
                      rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.full((H, W), 2.0, np.float32), ov=ov,
                      ov_space=SPACE)
    kept.state.global_map.integrate(voxels)  # a map voxel layer on the wall, not in the window
    assert not kept.ctx.window_has_depth()
    xyz = _wall()
    want = _segment(unbounded, "average", xyz)
    got = _segment(kept, "average_depth", xyz)
    old = kept.state.window.keyframes[0].world_from_cam[0, 3]
    only_left = (want.label >= 0) & (xyz[:, 0] < old - 0.9) & (want.label != 0)
    assert only_left.sum() > 10 and (got.source[only_left] == SOURCE_MAP).all()
    if order == "fill":
        assert (got.label[only_left] == 0).all()  # the voxel's "c0"
    else:
        assert np.array_equal(got.label[only_left], want.label[only_left])  # the kept views'
