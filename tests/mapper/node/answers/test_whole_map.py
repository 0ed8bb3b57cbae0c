"""Answers from the whole map: points and pixels the window does not see are answered from the
global map's fused features (every segment method and render labels), each answer names its source,
and the learned features reach the map before a keyframe leaves the window.

A node in-process (no sockets) with a window of ONE keyframe and a fake 4-d embedding space whose
text encoder maps "c0".."c3" to one-hot vectors. Keyframe A looks along +z at the wall z = 2 and
sees class c0 everywhere; keyframe B looks along +x at the wall x = 2 and sees c1. After B, A has
left the window, but its wall is in the global map."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapper.map.global_map import GlobalMapSnapshot, GlobalSemanticMap
from mapper.node.backends.learned import LearnedBackend
from mapper.node.config import GlobalMapConfig, config_from_dict
from mapper.node.queries import (
    SOURCE_MAP,
    SOURCE_NONE,
    SOURCE_WINDOW,
    blend_with_map,
    fill_from_map,
    render_from_map,
)
from mapper.node.service import MapperNode
from mapper.node.workers.map_features import PreEvictionFeatures
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from mapper.runtime.model_runtime import ModelRuntimeConfig, RenderFrame
from protocol.messages import (
    ANSWER_SOURCES,
    Error,
    Frame,
    Render,
    RenderResult,
    Segmentation,
    SegmentPoints,
    decode,
    encode,
)

SPACE = "test-onehot-4"
D = 4
W, H = 32, 24
K = np.array([30.0, 30.0, 16.0, 12.0])
LOOK_X = np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]], float)  # camera +z = world +x
ON_A = [0.0, 0.0, 2.0]  # on A's wall (z = 2), which B does not see
ON_B = [2.0, 0.0, 0.0]  # on B's wall (x = 2), in the window
FAR = [0.0, 9.0, 9.0]  # nowhere


class OneHotEncoder:
    space = SPACE
    dim = D

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        out = np.zeros((len(texts), D), np.float32)
        for i, t in enumerate(texts):
            last = t.strip()[-1:]
            out[i, int(last) % D if last.isdigit() else 0] = 1.0
        return out


@pytest.fixture(autouse=True)
def onehot_space() -> Iterator[None]:
    register_text_encoder(SPACE, OneHotEncoder)
    yield
    unregister_text_encoder(SPACE)


def _frame(seq: int, pose: np.ndarray, cls: int) -> Frame:
    ov = np.zeros((6, 8, D), np.float16)
    ov[..., cls] = 1.0
    return Frame(seq=seq, stamp_ns=seq, width=W, height=H, K=K, world_from_cam=pose,
                 rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.full((H, W), 2.0, np.float32), ov=ov,
                 ov_space=SPACE)  # fmt: skip


def _node(tmp_path: Path, **queries: Any) -> MapperNode:
    config = config_from_dict(
        {"map_dir": str(tmp_path), "events_endpoint": "", "serve_model": False,
         "window": {"max_keyframes": 1}, "global_map": {"pixel_stride": 1}, "queries": queries}
    )  # fmt: skip
    return MapperNode(config)


def _stream(node: MapperNode, frames: Sequence[Frame]) -> None:
    for f in frames:
        reply = decode(node.handle_ingest(encode(f)), direction="reply")
        assert getattr(reply, "status", None) == "keyframe", reply


def _segment(node: MapperNode, method: Any, points: list[list[float]]) -> Segmentation:
    msg = SegmentPoints(xyz=np.array(points, np.float32), texts=["c0", "c1", "c2", "c3"], method=method, id=7)
    reply = decode(node.handle_query(encode(msg)), direction="reply")
    assert isinstance(reply, Segmentation), reply
    return reply


@pytest.mark.parametrize("method", ["average", "average_depth"])
def test_averaging_answers_from_window_and_map_and_names_the_source(tmp_path: Path, method: Any) -> None:
    node = _node(tmp_path)
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    assert len(node.state.window) == 1  # A left the window
    reply = _segment(node, method, [ON_A, ON_B, FAR])
    assert reply.label.tolist() == [0, 1, -1]
    assert reply.source is not None and reply.source.tolist() == [SOURCE_MAP, SOURCE_WINDOW, SOURCE_NONE]
    assert [ANSWER_SOURCES[s] for s in reply.source] == ["map", "window", "none"]
    assert reply.score[0] > 0.99 and reply.score[2] == 0.0
    assert reply.timing_ms["from_map"] == 1.0
    # the source survives the wire (an optional field) and old-style replies still decode
    old_style = decode(encode(Segmentation(label=reply.label, score=reply.score)), direction="reply")
    assert isinstance(old_style, Segmentation) and old_style.source is None


def test_map_radius_follows_the_voxel_size_and_zero_means_window_only(tmp_path: Path) -> None:
    node = _node(tmp_path, map_radius_voxels=0.0)
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    assert _segment(node, "average", [ON_A, ON_B]).label.tolist() == [-1, 1]
    node = _node(tmp_path, map_radius_voxels=2.0)  # 10 cm at 5 cm voxels
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    near, off = [0.0, 0.0, 2.07], [0.0, 0.0, 2.2]  # 7 cm and 20 cm behind A's wall
    assert _segment(node, "average", [near, off]).label.tolist() == [0, -1]


def test_map_alone_answers_after_the_window_lost_its_features(tmp_path: Path) -> None:
    node = _node(tmp_path)
    no_ov = _frame(1, LOOK_X, 1)
    no_ov.ov = None
    no_ov.ov_space = None
    _stream(node, [_frame(0, np.eye(4), 0), no_ov])  # the window holds a keyframe without ov
    reply = _segment(node, "average", [ON_A, ON_B])
    assert reply.source is not None and reply.source.tolist() == [SOURCE_MAP, SOURCE_NONE]
    assert reply.label.tolist() == [0, -1]


def test_empty_map_and_window_still_answer_not_ready(tmp_path: Path) -> None:
    node = _node(tmp_path)
    msg = SegmentPoints(xyz=np.zeros((1, 3), np.float32), texts=["c0"], method="average")
    reply = decode(node.handle_query(encode(msg)), direction="reply")
    assert isinstance(reply, Error) and reply.code == "not_ready"


def _learned(node: MapperNode, runtime: Any) -> MapperNode:
    """``node`` with ``runtime`` as its learned backend (``govnesf`` and ``render``)."""
    backend = LearnedBackend(runtime)
    node.segment.register("govnesf", backend)
    node.render.backend = backend
    return node


class StubRuntime:
    """Stands in for ModelRuntime: the window "sees" only points with x > 1 (B's wall) and renders
    a surface 2 m ahead whose pixels it leaves unlabelled (or no surface with ``depth=0``)."""

    config = ModelRuntimeConfig(surface_from_map="off")  # these tests are about the map's labels

    def __init__(self, depth: float = 2.0) -> None:
        self.depth = depth
        self.outputs: list[str] = []

    def segment(self, xyz: np.ndarray, texts: Sequence[str], *, use_depth: bool) -> tuple[Any, Any, dict]:
        seen = np.asarray(xyz)[:, 0] > 1.0
        return np.where(seen, 1, -1).astype(np.int32), np.where(seen, 0.9, 0.0).astype(np.float32), {"n": 1.0}

    def segment_cosines(
        self, xyz: np.ndarray, texts: Sequence[str], *, use_depth: bool
    ) -> tuple[Any, Any, Any, dict]:
        label, score, timing = self.segment(xyz, texts, use_depth=use_depth)
        cos = np.zeros((label.shape[0], len(texts)), np.float32)
        seen = label >= 0
        cos[seen, label[seen]] = score[seen]
        return label, score, cos, timing

    def render(
        self, K: Any, pose: Any, width: int, height: int, outputs: Sequence[str], texts: Any,
        surface_depth_m: np.ndarray | None = None,
    ) -> RenderFrame:
        self.outputs = list(outputs)
        label = np.full((height, width), -1, np.int32)
        label[:, : width // 4] = 2  # the window labels the left quarter
        score = np.zeros((height, width, len(texts)), np.float32)
        score[:, : width // 4, 2] = 0.8
        depth = np.full((height, width), self.depth, np.float32)
        return RenderFrame(depth_m=depth if "depth" in outputs else None, label=label,
                           score=score if "score" in outputs else None)  # fmt: skip


def test_govnesf_segment_falls_back_to_the_map(tmp_path: Path) -> None:
    node = _node(tmp_path)
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    handler = _learned(node, StubRuntime()).segment.handle
    msg = SegmentPoints(xyz=np.array([ON_A, ON_B, FAR], np.float32), texts=["c0", "c1", "c2", "c3"])
    reply = handler(msg)
    assert isinstance(reply, Segmentation)
    assert reply.source is not None and reply.source.tolist() == [2, 1, 0]
    assert reply.label.tolist() == [0, 1, -1]


@pytest.mark.parametrize("depth", [2.0, 0.0], ids=["surface", "splat"])
def test_render_labels_the_pixels_the_window_leaves_from_the_map(tmp_path: Path, depth: float) -> None:
    node = _node(tmp_path, map_when_more_confident=False, map_blend=0.0)  # window first
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    runtime = StubRuntime(depth)
    handler = _learned(node, runtime).render.handle
    msg = Render(width=W, height=H, K=K, world_from_cam=np.eye(4), outputs=["label", "score"],
                 texts=["c0", "c1", "c2", "c3"], id=3)  # fmt: skip
    reply = handler(msg)
    assert isinstance(reply, RenderResult) and reply.depth_m is None  # depth was not asked for
    assert "depth" in runtime.outputs  # ... but used for the surface points
    assert reply.label is not None and reply.source is not None and reply.score is not None
    left = reply.label[:, : W // 4]
    assert (left == 2).all() and (reply.source[:, : W // 4] == SOURCE_WINDOW).all()
    right = reply.source[:, W // 4:]
    assert (right == SOURCE_MAP).mean() > 0.95  # A's wall fills the view, from the map
    assert (reply.label[:, W // 4:][right == SOURCE_MAP] == 0).all()
    assert np.allclose(reply.score[:, W // 4:, 0][right == SOURCE_MAP], 1.0, atol=2e-3)
    assert decode(encode(reply), direction="reply").source.shape == (H, W)  # type: ignore[attr-defined]


@pytest.mark.parametrize("depth", [2.0, 0.0], ids=["surface", "splat"])
def test_render_takes_the_more_confident_map_where_the_surface_is_known(tmp_path: Path, depth: float) -> None:
    """Default rule: the window's left quarter says class 2 at cosine 0.8; the map point at the
    rendered surface (A's wall) says class 0 at cosine 1: the map answers there. Without a rendered
    surface (depth 0) nothing is compared (no splat), so the window's answer stays. The reply
    carries only the outputs asked for. (``queries.map_blend`` is for ``segment_points`` only.)"""
    node = _node(tmp_path)
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    runtime = StubRuntime(depth)
    handler = _learned(node, runtime).render.handle
    msg = Render(width=W, height=H, K=K, world_from_cam=np.eye(4), outputs=["label"],
                 texts=["c0", "c1", "c2", "c3"], id=3)  # fmt: skip
    reply = handler(msg)
    assert isinstance(reply, RenderResult) and reply.score is None and reply.depth_m is None
    assert "score" in runtime.outputs  # asked of the model for the comparison
    assert reply.label is not None and reply.source is not None
    left, left_source = reply.label[:, : W // 4], reply.source[:, : W // 4]
    if depth > 0:
        assert (left_source == SOURCE_MAP).mean() > 0.95 and (left[left_source == SOURCE_MAP] == 0).all()
    else:
        assert (left == 2).all() and (left_source == SOURCE_WINDOW).all()
    assert (reply.source[:, W // 4:] == SOURCE_MAP).mean() > 0.95  # the rest as before


def test_render_with_map_radius_zero_is_window_only(tmp_path: Path) -> None:
    node = _node(tmp_path, map_radius_voxels=0.0)
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    handler = _learned(node, StubRuntime(0.0)).render.handle
    reply = handler(Render(width=W, height=H, K=K, world_from_cam=np.eye(4), outputs=["label"],
                           texts=["c0", "c1", "c2", "c3"]))  # fmt: skip
    assert isinstance(reply, RenderResult) and reply.source is not None and reply.label is not None
    assert not (reply.source == SOURCE_MAP).any() and (reply.label[:, W // 4:] == -1).all()


def _one_point_snapshot() -> GlobalMapSnapshot:
    """A map of one point 2 m ahead of the origin (z = 2) whose feature is class 0."""
    n = 1
    return GlobalMapSnapshot(
        version=1, map_version=1, voxel_size_m=0.05, xyz=np.array([[0.0, 0.0, 2.0]], np.float32),
        feat=np.eye(D, dtype=np.float16)[:1], weight=np.ones(n, np.float32),
        feat_weight=np.ones(n, np.float32), hits=np.ones(n, np.int32), last_seen_ns=np.zeros(n, np.int64),
    )  # fmt: skip


def test_render_from_map_leaves_pixels_without_map_points_alone() -> None:
    snap = _one_point_snapshot()
    need = np.ones((H, W), bool)
    emb = np.eye(D, dtype=np.float32)
    label, cos, answered = render_from_map(snap, K, np.eye(4), W, H, None, need, emb, 0.075)
    # one point 2 m ahead covers about its voxel: 0.5 * 30 * 0.05 / 2 < 1 pixel, so just its pixel
    assert answered.sum() == 1 and answered[12, 16] and label[12, 16] == 0 and cos[12, 16, 0] > 0.99
    assert (label[~answered] == -1).all() and (cos[~answered] == 0).all()
    # a point behind the camera is not splatted
    look_back = np.diag([-1.0, 1.0, -1.0, 1.0])  # camera +z = world -z
    behind = render_from_map(snap, K, look_back, W, H, None, need, emb, 0.075)[2]
    assert not behind.any()


def test_fill_from_map_keeps_window_answers_and_ignores_other_dimensions() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig(voxel_size_m=0.1))
    snap = gmap.snapshot()  # empty: nothing from the map
    label, score, source = fill_from_map(snap, np.zeros((2, 3), np.float32), np.eye(2, dtype=np.float32),
                                         np.array([1, 0], np.int32), np.array([0.5, 0.0], np.float32),
                                         np.array([True, False]), 0.15)  # fmt: skip
    assert label.tolist() == [1, -1] and source.tolist() == [SOURCE_WINDOW, SOURCE_NONE] and score[1] == 0.0


def test_nearest_with_feature_skips_points_without_features(tmp_path: Path) -> None:
    node = _node(tmp_path)
    plain = _frame(0, np.eye(4), 0)
    plain.ov = None
    plain.ov_space = None
    _stream(node, [plain, _frame(1, LOOK_X, 1)])  # A's wall: geometry only
    snap = node.state.global_map.snapshot()
    rows = snap.nearest_with_feature(np.array([ON_A, ON_B], np.float32), 0.075)
    assert rows[0] == -1 and rows[1] >= 0 and snap.has_feature[rows[1]]


def test_learned_features_reach_the_map_before_the_keyframe_leaves(tmp_path: Path) -> None:
    node = _node(tmp_path)
    calls: list[int] = []
    pending_during: list[int] = []

    def learned(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        calls.append(len(xyz))
        pending_during.append(worker.stats()["pending"])  # the batch in progress still counts
        feats = np.zeros((len(xyz), D), np.float32)
        feats[:, 3] = 2.0  # the "model" says c3 (any norm), against the fused c0:
        feats[:, 0] = -1.0  # mixed with the fused direction it still points to c3
        valid = np.ones(len(xyz), bool)
        valid[0] = False  # one voxel the model cannot answer keeps its fused feature
        return feats, valid

    worker = PreEvictionFeatures(node.ctx, learned)
    worker.install()
    _stream(node, [_frame(0, np.eye(4), 0)])  # the window (1) is full: A leaves next, queued now
    assert worker.stats()["pending"] == 1 and not worker.idle()
    weight_before = node.state.global_map.snapshot().feat_weight.copy()
    assert worker.process_pending() == 1 and worker.idle()
    assert pending_during == [1] and worker.stats()["pending"] == 0  # a settled node reads 0 only when done
    stats = worker.stats()
    assert stats["done"] == 1 and stats["late"] == 0 and stats["voxels_set"] == calls[0] - 1
    snap = node.state.global_map.snapshot()
    assert snap.feat is not None
    np.testing.assert_array_equal(snap.feat_weight, weight_before)  # weights kept: still a running mean
    learned = np.argmax(snap.feat.astype(np.float32), axis=1) == 3
    assert learned.sum() == calls[0] - 1
    assert (snap.feat[learned, 0] > 0.4).all()  # mixed with the fused c0, not replaced
    _stream(node, [_frame(1, LOOK_X, 1)])  # A leaves; B is queued (the window is full again)
    assert _segment(node, "average", [ON_A]).label.tolist() == [3]  # the map carries the model's answer
    assert node.state.global_map.stats()["global_points_learned"] == calls[0] - 1
    # B is processed after it left the window: still written, counted as late
    with node.state.lock:
        node.state.window.clear()
    assert worker.process_pending() == 1 and worker.stats()["late"] == 1


def test_set_features_refuses_a_wrong_shape_and_changes_nothing() -> None:
    gmap = GlobalSemanticMap(GlobalMapConfig())
    from mapper.map.window import Keyframe

    f = _frame(0, np.eye(4), 0)
    kf = Keyframe(seq=0, stamp_ns=0, camera="cam0", K=f.K, world_from_cam=f.world_from_cam, rgb=f.rgb,
                  depth_m=f.depth_m, ov=f.ov, ov_space=SPACE)  # fmt: skip
    gmap.integrate(kf)
    keys, xyz = gmap.seen_voxels(kf)
    assert keys.shape[0] == len(gmap) and xyz.shape == (len(gmap), 3)
    version = gmap.version
    with pytest.raises(ValueError, match="dimension 5"):
        gmap.set_features(keys, np.ones((keys.shape[0], 5), np.float32))
    with pytest.raises(ValueError, match=r"must be \(U="):
        gmap.set_features(keys, np.ones((keys.shape[0] + 1, D), np.float32))
    assert gmap.version == version and gmap.points_learned == 0


def _learned_map(once: bool) -> tuple[GlobalSemanticMap, np.ndarray]:
    from mapper.map.window import Keyframe

    gmap = GlobalSemanticMap(GlobalMapConfig(learned_features_once=once))
    f = _frame(0, np.eye(4), 0)  # fused c0 everywhere
    gmap.integrate(Keyframe(seq=0, stamp_ns=0, camera="cam0", K=f.K, world_from_cam=f.world_from_cam,
                            rgb=f.rgb, depth_m=f.depth_m, ov=f.ov, ov_space=SPACE))  # fmt: skip
    keys = gmap.to_arrays()[0]["global.keys"]
    return gmap, keys


def _unit_feat(gmap: GlobalSemanticMap) -> np.ndarray:
    feat = gmap.snapshot().feat
    assert feat is not None
    f = feat.astype(np.float64)
    return f / np.linalg.norm(f, axis=1, keepdims=True)


@pytest.mark.parametrize("once", [True, False])
def test_learned_features_enter_a_voxel_once_or_at_every_eviction(once: bool) -> None:
    gmap, keys = _learned_map(once)
    c2, c3 = np.zeros((len(keys), D), np.float32), np.zeros((len(keys), D), np.float32)
    c2[:, 2], c3[:, 3] = 1.0, 1.0
    half = len(keys) // 2
    assert gmap.set_features(keys[:half], c2[:half]) == half  # the first eviction: c0 + c2
    first = _unit_feat(gmap)
    np.testing.assert_allclose(first[:half, [0, 2]], np.sqrt(0.5), atol=2e-3)
    np.testing.assert_allclose(first[half:], np.eye(D)[[0] * (len(keys) - half)], atol=1e-6)  # not set yet
    set_again = gmap.set_features(keys, c3)  # a later eviction of keyframes that saw them all
    after = _unit_feat(gmap)
    if once:  # only the voxels without a learned feature take it
        assert set_again == len(keys) - half and gmap.points_learned == len(keys)
        np.testing.assert_allclose(after[:half], first[:half], atol=1e-6)
        np.testing.assert_allclose(after[half:, [0, 3]], np.sqrt(0.5), atol=2e-3)
    else:  # every time an equal mix with what the voxel has: c0 keeps about a quarter of the say
        assert set_again == len(keys) and gmap.points_learned == len(keys) + half
        expect = np.array([0.5, 0.0, 0.5, np.sqrt(0.5)]) / np.linalg.norm([0.5, 0.0, 0.5, np.sqrt(0.5)])
        np.testing.assert_allclose(after[:half], np.tile(expect, (half, 1)), atol=3e-3)
    # the worker asks the model only for the voxels still without a learned feature
    from mapper.map.window import Keyframe

    f = _frame(0, np.eye(4), 0)
    kf = Keyframe(seq=0, stamp_ns=0, camera="cam0", K=f.K, world_from_cam=f.world_from_cam, rgb=f.rgb,
                  depth_m=f.depth_m, ov=f.ov, ov_space=SPACE)  # fmt: skip
    assert gmap.seen_voxels(kf)[0].shape[0] == len(keys)
    assert gmap.seen_voxels(kf, unlearned=True)[0].shape[0] == 0


def test_learned_flags_survive_save_and_load_and_old_maps_load_without_them() -> None:
    gmap, keys = _learned_map(True)
    c3 = np.zeros((3, D), np.float32)
    c3[:, 3] = 1.0
    gmap.set_features(keys[:3], c3)
    arrays, manifest = gmap.to_arrays()
    assert int(arrays["global.learned"].sum()) == 3
    back = GlobalSemanticMap(GlobalMapConfig())
    back.restore(arrays, manifest, map_version=1)
    assert back.set_features(keys[:3], c3) == 0 and back.set_features(keys[3:5], c3[:2]) == 2  # flags kept
    old = {k: v for k, v in arrays.items() if k != "global.learned"}  # a map saved before the flag
    back.restore(old, manifest, map_version=1)
    assert back.set_features(keys[:3], c3) == 3
    bad = dict(arrays, **{"global.learned": arrays["global.learned"][:-1]})
    with pytest.raises(ValueError, match="learned must be uint8"):
        back.restore(bad, manifest, map_version=1)


def test_fill_from_map_takes_a_more_confident_map_answer_only_when_asked() -> None:
    snap = _one_point_snapshot()
    emb = np.eye(D, dtype=np.float32)
    xyz = np.array([[0.0, 0.0, 2.0]] * 4 + [[0.0, 5.0, 2.0]], np.float32)  # four at the map point, one far
    # the window says: 1 (weaker than the map's 0), 1 (as confident as the map: a tie keeps the window),
    # 0 (the map's own text, weaker: the window's answer stays), unseen, and 2 far from every map point
    label = np.array([1, 1, 0, -1, 2], np.int32)
    score = np.array([0.3, 1.0, 0.2, 0.0, 0.3], np.float32)
    seen = label >= 0
    lab, sc, src = fill_from_map(snap, xyz, emb, label, score, seen, 0.075, more_confident=True)
    assert lab.tolist() == [0, 1, 0, 0, 2]
    assert src.tolist() == [SOURCE_MAP, SOURCE_WINDOW, SOURCE_WINDOW, SOURCE_MAP, SOURCE_WINDOW]
    assert sc[0] == pytest.approx(1.0, abs=1e-3) and sc[1] == 1.0 and sc[2] == pytest.approx(0.2)
    lab, sc, src = fill_from_map(snap, xyz, emb, label, score, seen, 0.075)  # default: window first
    assert lab.tolist() == [1, 1, 0, 0, 2] and src.tolist() == [1, 1, 1, 2, 1]
    assert sc[0] == pytest.approx(0.3)


def _disagreeing_frames() -> list:
    """A strong view of text 3 at ON_B, a view of A's wall (so that the strong one leaves a window of
    one), then B's wall again, mostly 1 (0.6 against 0.55 for 3): the window and the map disagree at
    ON_B."""
    strong = _frame(0, LOOK_X, 3)
    weak = _frame(1, np.eye(4), 0)
    ov = np.zeros((6, 8, D), np.float16)
    ov[..., 1], ov[..., 3] = 0.6, 0.55
    again = _frame(2, LOOK_X, 1)
    again.ov = ov
    return [strong, weak, again]


@pytest.mark.parametrize("more_confident", [True, False])
def test_node_prefers_the_more_confident_map_as_configured(tmp_path: Path, more_confident: bool) -> None:
    """ON_B is in the window, seen as class 1 by a view with a weak feature; the map fused it as
    class 3 from a view that left (a strong feature): the map answers when configured to."""
    node = _node(tmp_path, map_when_more_confident=more_confident, map_blend=0.0)
    _stream(node, _disagreeing_frames())
    reply = _segment(node, "average", [ON_B])
    assert reply.source is not None
    if more_confident:
        assert reply.label.tolist() == [3] and reply.source.tolist() == [SOURCE_MAP]
    else:
        assert reply.label.tolist() == [1] and reply.source.tolist() == [SOURCE_WINDOW]


def test_map_similarities_equal_a_float64_reference_across_blocks() -> None:
    from mapper.map.global_map import UNIT_BLOCK_ROWS
    from mapper.node.queries import _map_similarities

    rng = np.random.default_rng(3)
    n = UNIT_BLOCK_ROWS + 500  # two blocks
    feat = rng.standard_normal((n, D)).astype(np.float16)
    snap = GlobalMapSnapshot(
        version=1, map_version=1, voxel_size_m=0.05, xyz=rng.uniform(0, 5, (n, 3)).astype(np.float32),
        feat=feat, weight=np.ones(n, np.float32), feat_weight=np.ones(n, np.float32),
        hits=np.ones(n, np.int32), last_seen_ns=np.zeros(n, np.int64),
    )  # fmt: skip
    emb = rng.standard_normal((3, D)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    rows = rng.integers(0, n, 2000)
    rows[:3] = [0, UNIT_BLOCK_ROWS - 1, UNIT_BLOCK_ROWS]  # block edges, and repeats below
    rows[3:6] = rows[:3]
    f = feat[rows].astype(np.float64)
    want = (f / np.linalg.norm(f, axis=1, keepdims=True)) @ emb.T.astype(np.float64)
    got = _map_similarities(snap, rows, emb)
    assert got.shape == (2000, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=2e-6)
    assert _map_similarities(snap, rows[:0], emb).shape == (0, 3)


def test_fill_from_map_blends_the_cosines_where_both_answer() -> None:
    """``queries.map_blend``: where the window and the map both answer, the best text of
    (1 - w) window + w map; ``source`` says map only where that changed the window's label."""
    snap = _one_point_snapshot()  # class 0 at cosine 1
    emb = np.eye(D, dtype=np.float32)
    xyz = np.array([[0.0, 0.0, 2.0]] * 3 + [[0.0, 5.0, 2.0]], np.float32)  # three at the map point, one far
    window_cos = np.zeros((4, D), np.float32)
    window_cos[0, 1] = 0.6  # the window says 1: the blend (0.75 x 1 for text 0) says 0
    window_cos[1, 0], window_cos[1, 1] = 0.2, 0.95  # a confident 1: 0.25 x 0.95 < 0.75 x 1 + 0.25 x 0.2
    window_cos[3, 2] = 0.4  # far from every map point: the window's answer stays
    label = np.array([1, 1, -1, 2], np.int32)
    score = np.array([0.6, 0.95, 0.0, 0.4], np.float32)
    seen = label >= 0
    lab, sc, src = fill_from_map(snap, xyz, emb, label, score, seen, 0.075, window_cos=window_cos, blend=0.75)
    assert lab.tolist() == [0, 0, 0, 2]
    assert src.tolist() == [SOURCE_MAP, SOURCE_MAP, SOURCE_MAP, SOURCE_WINDOW]
    # float64 reference of the blended score; the unseen point takes the map's own cosine
    want0 = 0.25 * 0.0 + 0.75 * 1.0
    want1 = 0.25 * 0.2 + 0.75 * 1.0
    assert sc[0] == pytest.approx(want0, abs=1e-3) and sc[1] == pytest.approx(want1, abs=1e-3)
    assert sc[2] == pytest.approx(1.0, abs=1e-3) and sc[3] == pytest.approx(0.4)
    # a light map weight keeps the confident window answer (and says so)
    lab, sc, src = fill_from_map(snap, xyz, emb, label, score, seen, 0.075, window_cos=window_cos, blend=0.1)
    assert lab.tolist() == [1, 1, 0, 2]
    assert src.tolist() == [SOURCE_WINDOW, SOURCE_WINDOW, SOURCE_MAP, SOURCE_WINDOW]
    assert sc[1] == pytest.approx(0.9 * 0.95, abs=1e-3)  # the blended cosine, not the window's
    # blend 0 (or no window cosines): the more-confident rule / window first, as before
    lab0, _, src0 = fill_from_map(snap, xyz, emb, label, score, seen, 0.075, window_cos=window_cos, blend=0.0)
    assert lab0.tolist() == [1, 1, 0, 2] and src0.tolist() == [1, 1, 2, 1]
    with pytest.raises(ValueError, match="window_cos has shape"):
        fill_from_map(snap, xyz, emb, label, score, seen, 0.075, window_cos=window_cos[:2], blend=0.5)


def test_blend_with_map_ends_and_bad_weights() -> None:
    rng = np.random.default_rng(0)
    w, m = rng.uniform(-1, 1, (5, 3)).astype(np.float32), rng.uniform(-1, 1, (5, 3)).astype(np.float32)
    assert np.array_equal(blend_with_map(w, m, 0.0), w) and np.array_equal(blend_with_map(w, m, 1.0), m)
    half = blend_with_map(w, m, 0.5)
    assert np.allclose(half, 0.5 * (w.astype(np.float64) + m.astype(np.float64)), atol=1e-7)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="must be in"):
            blend_with_map(w, m, bad)


@pytest.mark.parametrize("blend", [0.75, 0.05])
def test_node_blends_window_and_map_as_configured(tmp_path: Path, blend: float) -> None:
    """The stream of the test above: the window (one view, mostly 1) and the map (which also fused
    the strong view of 3 that left) disagree at ON_B; the shipped weight takes the map's text, a
    light one keeps the window's. ``govnesf`` (a stub runtime that reports its cosines) the same."""
    node = _node(tmp_path, map_blend=blend)
    frames = _disagreeing_frames()
    _stream(node, frames)
    reply = _segment(node, "average", [ON_B])
    assert reply.source is not None
    if blend > 0.5:
        assert reply.label.tolist() == [3] and reply.source.tolist() == [SOURCE_MAP]
    else:
        assert reply.label.tolist() == [1] and reply.source.tolist() == [SOURCE_WINDOW]
    handler = _learned(node, StubRuntime()).segment.handle
    got = handler(SegmentPoints(xyz=np.array([ON_B], np.float32), texts=["c0", "c1", "c2", "c3"]))
    assert isinstance(got, Segmentation) and got.source is not None
    # the stub's window says 1 at 0.9; the map point says mostly 3
    assert got.label.tolist() == ([3] if blend > 0.5 else [1])


def test_map_blend_follows_the_window_depth(tmp_path: Path) -> None:
    """``queries.map_blend`` while at least half of the window's keyframes carry input depth,
    ``map_blend_without_depth`` otherwise (an RGB-only robot's map holds estimated surfaces)."""
    node = _node(tmp_path, map_blend=0.6, map_blend_without_depth=0.2)
    assert node.ctx.map_blend() == 0.2  # empty window: nothing measured
    _stream(node, [_frame(0, np.eye(4), 0)])
    assert node.ctx.map_blend() == 0.6
    rgb_only = _frame(1, LOOK_X, 1)
    rgb_only.depth_m = None
    _stream(node, [rgb_only])  # the window (one keyframe) now has no depth
    assert node.ctx.map_blend() == 0.2
    assert node.ctx.map_blend(depth_tested=True) == 0.0  # a depth-tested answer: the more-confident rule


def test_depth_tested_answers_keep_the_more_confident_rule(tmp_path: Path) -> None:
    """``average_depth`` (and ``govnesf`` with ``use_depth``) already passed a depth test: the blend
    is not applied to them (measured: it cost them), the more-confident rule is."""
    node = _node(tmp_path, map_blend=0.75)
    frames = _disagreeing_frames()
    _stream(node, frames)
    plain, tested = _segment(node, "average", [ON_B]), _segment(node, "average_depth", [ON_B])
    more_confident = _node(tmp_path / "b", map_blend=0.0)
    _stream(more_confident, frames)
    want = _segment(more_confident, "average_depth", [ON_B])
    assert plain.label.tolist() == [3]  # blended
    assert tested.label.tolist() == want.label.tolist() and tested.score.tolist() == want.score.tolist()


def test_nearest_with_feature_grid_and_kd_tree_agree(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the snapshot's index is a voxel grid, or a k-d tree where the grid would be too large or the
    # radius beyond its reach: the same rows either way, on and off the map's surfaces
    from scipy.spatial import cKDTree

    from mapper.map import query_kernels

    node = _node(tmp_path)
    _stream(node, [_frame(0, np.eye(4), 0), _frame(1, LOOK_X, 1)])
    snap = node.state.global_map.snapshot()
    rng = np.random.default_rng(0)
    have = snap.xyz[snap.has_feature]
    queries = np.concatenate([have + rng.normal(0, 0.03, have.shape), rng.uniform(-3, 3, (500, 3))])
    grid_rows = snap.nearest_with_feature(queries.astype(np.float32), 0.075)
    assert isinstance(snap._cache["feature_grid"], query_kernels.NearestGrid)
    # a radius beyond the grid's reach (voxels of 5 cm here) takes the k-d tree
    far_rows = snap.nearest_with_feature(queries.astype(np.float32), 0.5)
    assert "feature_tree" in snap._cache and (far_rows >= 0).sum() > (grid_rows >= 0).sum()
    monkeypatch.setattr(query_kernels.NearestGrid, "build", classmethod(lambda cls, pts, cell: None))
    snap2 = node.state.global_map.snapshot()
    snap2._cache.clear()
    tree_rows = snap2.nearest_with_feature(queries.astype(np.float32), 0.075)
    assert isinstance(snap2._cache["feature_grid"], cKDTree)  # no grid: the tree in its place
    np.testing.assert_array_equal(grid_rows, tree_rows)
    assert (grid_rows >= 0).sum() > have.shape[0] // 2 and (grid_rows < 0).any()
    rows = np.flatnonzero(snap.has_feature)
    dist, idx = cKDTree(snap.xyz[rows].astype(np.float64)).query(queries, distance_upper_bound=0.5)
    np.testing.assert_array_equal(far_rows, np.where(np.isfinite(dist), rows[np.minimum(idx, rows.size - 1)],
                                                     -1))
