"""The in-process OV backend in the node (mapper.node.workers.ov_features): config, text encoder registration,
features for keyframes without ov (window swap seen by the learned runtime, global map features
without extra geometry), missing weights, frames with ov, queue bound, stale keyframes after a load.

Uses the tiny random CLIP that tests/mapper/ov/test_clip_backend.py builds, saved to tmp_path."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from mapper.map.global_map import GlobalSemanticMap
from mapper.model.field import GovNeSF
from mapper.node.backends.learned import install_learned_backend
from mapper.node.config import ConfigError, OvBackendConfig, apply_overrides, config_from_dict
from mapper.node.service import MapperNode
from mapper.node.workers.ov_features import OvFeatureWorker, install_ov_backend
from mapper.ov.clip_tokenizer import ClipTokenizer
from mapper.ov.encoders import available_spaces, get_text_encoder, unregister_text_encoder
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from protocol.messages import (
    Ack,
    Error,
    Frame,
    Load,
    Message,
    Ok,
    Points,
    QueryPoints,
    Save,
    Segmentation,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    encode,
)
from tests.mapper.ov.test_clip_backend import EMBED, T_HEADS, tiny_clip_state_dict, write_bpe
from tests.mapper.runtime.test_model_runtime import keyframe, orbit
from tests.model_helpers import tiny_model_config

SPACE = "openclip:tiny-test"
MakeNode = Callable[..., MapperNode]


@pytest.fixture(scope="module")
def clip_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ov_backend")
    bpe = write_bpe(root / "bpe_simple_vocab_16e6.txt.gz")
    torch.save(tiny_clip_state_dict(ClipTokenizer(bpe).vocab_size), root / "tiny.pt")
    return {"weights": root / "tiny.pt", "bpe": bpe}


def _config(tmp_path: Path, files: dict[str, Path], max_keyframes: int = 6, **ov: Any) -> Any:
    ov_table = {"kind": "clip", "weights_path": str(files["weights"]), "bpe_path": str(files["bpe"]),
                "model_name": "tiny-test", "device": "cpu", "text_heads": T_HEADS, **ov}
    return config_from_dict({
        "map_dir": str(tmp_path / "maps"), "autosave_name": "", "save_on_exit": False, "serve_model": False,
        "ingest_endpoint": f"inproc://ingest-{tmp_path.name}", "query_endpoint": f"inproc://query-{tmp_path.name}",
        "events_endpoint": "",
        "window": {"max_keyframes": max_keyframes, "min_translation_m": 0.05},
        "global_map": {"min_weight": 0.0, "rendered_depth": False},
        "ov_backend": ov_table,
    })


@pytest.fixture()
def make_node(tmp_path: Path, clip_files: dict[str, Path]) -> Iterator[MakeNode]:
    nodes: list[MapperNode] = []

    def make(**kw: Any) -> MapperNode:
        node = MapperNode(_config(tmp_path, clip_files, **kw))
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.stop()
    unregister_text_encoder(SPACE)


def _frame(seq: int, *, depth: bool = True, ov: np.ndarray | None = None, space: str | None = None) -> Frame:
    kf = keyframe(seq, orbit(seq), ov=None, depth_m=2.0 if depth else None)
    return Frame(seq=seq, stamp_ns=seq, width=kf.width, height=kf.height, K=kf.K,
                 world_from_cam=kf.world_from_cam, rgb=kf.rgb, depth_m=kf.depth_m, ov=ov,
                 ov_space=space if ov is not None else None)


def _ingest(node: MapperNode, frame: Frame) -> Message:
    return decode(node.handle_ingest(encode(frame)), direction="reply")


def _query(node: MapperNode, msg: Message) -> Message:
    return decode(node.handle_query(encode(msg)), direction="reply")


def _status(node: MapperNode) -> dict[str, Any]:
    status = _query(node, StatusRequest())
    assert isinstance(status, Status)
    return status.extra


def _segment(method: str = "average") -> SegmentPoints:
    return SegmentPoints(xyz=np.zeros((3, 3), np.float32), texts=["chair", "table"], method=method)


# ---- config ------------------------------------------------------------------------------------
def test_config_defaults_parse_and_errors(tmp_path: Path, clip_files: dict[str, Path]) -> None:
    default = config_from_dict({})
    assert default.ov_backend == OvBackendConfig() and default.ov_backend.kind == ""
    cfg = _config(tmp_path, clip_files, input_size=32).ov_backend
    clip = cfg.clip_config()
    assert cfg.space == SPACE and clip.model_name == "tiny-test" and clip.input_size == 32
    assert clip.text_heads == T_HEADS and clip.vision_heads is None  # 0 = width // 64
    assert _config(tmp_path, clip_files).ov_backend.clip_config().input_size is None  # 0 = native
    assert apply_overrides(default, {"ov_backend.dtype": "bfloat16"}).ov_backend.dtype == "bfloat16"
    bad: list[tuple[dict[str, Any], str]] = [
        ({"kind": "lseg"}, "ov_backend.kind 'lseg'"),
        ({"kind": "clip", "bpe_path": "b.gz"}, "ov_backend.weights_path must name a local file"),
        ({"kind": "clip", "weights_path": "w.pt"}, "ov_backend.bpe_path must name a local file"),
        ({"dtype": "float8"}, "ov_backend: dtype 'float8' not supported"),
        ({"activation": "relu"}, "ov_backend: activation 'relu'"),
        ({"device": "tpu"}, "ov_backend: device 'tpu'"),
        ({"model_name": "has space"}, "ov_backend: model_name"),
        ({"input_size": 8}, "ov_backend.input_size = 8 out of range"),
        ({"max_pending": 0}, "ov_backend.max_pending = 0 out of range"),
        ({"text_heads": -1}, "ov_backend.text_heads"),
        ({"weights": "w.pt"}, "unknown config key 'ov_backend.weights'"),
        ({"input_size": "224"}, "ov_backend.input_size must be an int"),
    ]
    for table, message in bad:
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(".", r"\.")):
            config_from_dict({"ov_backend": table})
    on = {"kind": "clip", "weights_path": "w.pt", "bpe_path": "b.gz"}
    with pytest.raises(ConfigError, match="ov_space = 'minilm-l6-v2' is pinned.*'openclip:ViT-B-16'"):
        config_from_dict({"ov_space": "minilm-l6-v2", "ov_backend": on})
    pinned = config_from_dict({"ov_space": "openclip:ViT-B-16", "ov_backend": on})
    assert pinned.ov_space == "openclip:ViT-B-16"
    assert config_from_dict({"ov_space": "minilm-l6-v2"}).ov_backend.kind == ""  # backend off: no conflict


def test_install_refuses_a_node_pinned_to_another_space(tmp_path: Path, clip_files: dict[str, Path]) -> None:
    config = apply_overrides(_config(tmp_path, clip_files), {"ov_space": SPACE})
    node = MapperNode(config)
    workers = list(node.ctx.workers)  # the node's own (evicted views)
    try:
        other = OvBackendConfig(**{**config.ov_backend.__dict__, "model_name": "other"})
        with pytest.raises(ConfigError, match="'openclip:tiny-test' is pinned.*'openclip:other'"):
            install_ov_backend(node, other)
        assert not node.ctx.keyframe_listeners and node.ctx.workers == workers
        assert "ov_backend" not in node.ctx.status_providers
    finally:
        node.stop()
        unregister_text_encoder(SPACE)


# ---- the node with the backend -----------------------------------------------------------------
def test_frames_without_ov_become_queryable_in_the_backend_space(make_node: MakeNode) -> None:
    node = make_node()
    worker = install_ov_backend(node)
    assert isinstance(worker, OvFeatureWorker) and worker.load_error is None and worker.backend is not None
    assert SPACE in available_spaces() and get_text_encoder(SPACE) is worker.backend
    assert ("ov-backend", worker.run) in node.ctx.workers
    assert worker.on_keyframe in node.ctx.keyframe_listeners
    for seq in range(3):
        ack = _ingest(node, _frame(seq))
        assert isinstance(ack, Ack) and ack.status == "keyframe"
    # nothing computed on the ingest thread: the keyframes wait, queries say why
    assert worker.pending == 3 and all(k.ov is None for k in node.state.window.keyframes)
    before = node.state.global_map.snapshot()
    assert len(before) > 0 and before.n_with_features == 0
    reply = _query(node, QueryPoints(texts=["chair"]))
    assert isinstance(reply, Error) and reply.code == "not_ready"
    assert "computing features for 3 keyframe(s)" in reply.message
    version = node.state.map_version

    assert worker.process_pending() == 3 and worker.pending == 0
    state = node.state
    assert state.ov_space == SPACE and state.ov_dim == EMBED and state.map_version == version + 3
    backend = worker.backend
    for kf in state.window.keyframes:
        assert kf.ov_space == SPACE and kf.ov is not None and kf.ov.shape[2] == EMBED
        np.testing.assert_array_equal(kf.ov, backend.dense_features(np.array(kf.rgb)))
    # the global map: features added, geometry untouched, the same features as a combined integrate
    after = state.global_map.snapshot()
    np.testing.assert_array_equal(after.xyz, before.xyz)
    np.testing.assert_array_equal(after.weight, before.weight)
    np.testing.assert_array_equal(after.hits, before.hits)
    np.testing.assert_array_equal(after.last_seen_ns, before.last_seen_ns)
    assert after.has_feature.all()
    combined = GlobalSemanticMap(node.config.global_map)
    for kf in state.window.keyframes:
        combined.integrate(kf)
    ref = combined.snapshot()
    np.testing.assert_array_equal(after.feat, ref.feat)
    np.testing.assert_array_equal(after.feat_weight, ref.feat_weight)
    np.testing.assert_array_equal(after.weight, ref.weight)

    points = _query(node, QueryPoints(texts=["chair"], negatives=[], objects=False))
    assert isinstance(points, Points) and points.xyz.shape[0] > 0
    assert isinstance(_query(node, _segment("average")), Segmentation)
    assert isinstance(_query(node, _segment("average_depth")), Segmentation)
    stats = _status(node)["ov_backend"]
    assert stats["loaded"] is True and stats["error"] is None and stats["space"] == SPACE
    assert stats["encoded"] == 3 and stats["window_updates"] == 3 and stats["queued"] == 3
    assert stats["map_points"] > 0 and stats["pending"] == 0 and stats["failed"] == 0
    assert stats["dim"] == EMBED


def test_the_learned_runtime_sees_the_new_features(make_node: MakeNode) -> None:
    node = make_node()
    torch.manual_seed(0)
    runtime = ModelRuntime(ModelRuntimeConfig(device="cpu", chunk_rays=512),
                           model=GovNeSF(tiny_model_config(ov_dim=EMBED)))
    install_learned_backend(node, runtime)
    worker = install_ov_backend(node)
    assert worker is not None
    for seq in range(3):
        _ingest(node, _frame(seq))
    xyz = np.array([[0.0, 0.0, 0.5], [0.2, 0.1, 0.4]], np.float32)
    msg = SegmentPoints(xyz=xyz, texts=["chair", "table"], method="govnesf")
    reply = _query(node, msg)
    assert isinstance(reply, Error) and reply.code == "not_ready" and "no keyframe in the window carries" in (
        reply.message) and "computing features" in reply.message
    assert runtime.views_added == 3 and runtime.views_removed == 0  # synced without ov
    assert worker.process_pending() == 3
    segmentation = _query(node, msg)
    assert isinstance(segmentation, Segmentation) and segmentation.label.shape == (2,)
    # applied incrementally: the three old views out, the three with features in
    assert runtime.views_removed == 3 and runtime.views_added == 6 and len(runtime) == 3


def test_missing_weights_node_starts_and_semantic_requests_name_the_path(
    make_node: MakeNode, tmp_path: Path
) -> None:
    missing = tmp_path / "no-such-clip.pt"
    node = make_node(weights_path=str(missing))
    worker = install_ov_backend(node)
    assert worker is not None and worker.backend is None
    assert worker.load_error is not None and str(missing) in worker.load_error
    assert SPACE not in available_spaces()
    node.start()  # serves everything else (inproc endpoints); the worker thread runs idle
    assert any(t.name == "mapper-ov-backend" and t.is_alive() for t in node._threads)
    ack = _ingest(node, _frame(0))
    node.ctx.drain_integrations()  # a started node integrates just after the ack
    assert isinstance(ack, Ack) and ack.status == "keyframe" and len(node.state.global_map) > 0
    assert worker.pending == 0 and worker.queued == 0  # nothing to compute with
    for request in (QueryPoints(texts=["chair"]), _segment("average")):
        reply = _query(node, request)
        assert isinstance(reply, Error) and reply.code == "not_ready"
        assert str(missing) in reply.message and "not found" in reply.message, reply.message
    stats = _status(node)["ov_backend"]
    assert stats["loaded"] is False and str(missing) in stats["error"] and stats["dim"] is None
    assert isinstance(_query(node, Save(name="still-works")), Ok)


def test_unreadable_weights_are_reported_with_the_path(make_node: MakeNode, tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    worker = install_ov_backend(make_node(weights_path=str(garbage)))
    assert worker is not None and worker.backend is None and worker.load_error is not None
    assert str(garbage) in worker.load_error and "ClipWeightsError" in worker.load_error


def test_frames_with_ov_are_never_re_encoded(make_node: MakeNode) -> None:
    node = make_node()
    worker = install_ov_backend(node)
    assert worker is not None
    sent = np.random.default_rng(0).standard_normal((2, 3, EMBED)).astype(np.float16)
    _ingest(node, _frame(0, ov=sent, space=SPACE))
    first = node.state.window.keyframes[0]
    assert worker.pending == 0 and worker.with_ov == 1
    _ingest(node, _frame(1))
    assert worker.process_pending() == 1
    assert node.state.window.keyframes[0] is first  # untouched: not re-encoded, not swapped
    np.testing.assert_array_equal(first.ov, sent)
    assert node.state.window.keyframes[1].ov_space == SPACE
    assert _status(node)["ov_backend"]["encoded"] == 1


def test_a_map_of_another_space_is_not_filled(make_node: MakeNode) -> None:
    node = make_node()
    worker = install_ov_backend(node)
    assert worker is not None
    other = np.ones((2, 3, 6), np.float16)
    _ingest(node, _frame(0, ov=other, space="test-space"))  # this frame sets the map's space
    _ingest(node, _frame(1))
    assert worker.pending == 1
    assert worker.process_pending() == 0 and worker.skipped_space == 1
    assert node.state.ov_space == "test-space" and node.state.window.keyframes[1].ov is None
    reply = _ingest(node, _frame(2, ov=np.ones((2, 3, EMBED), np.float16), space=SPACE))
    assert isinstance(reply, Error) and reply.code == "ov_space_mismatch"  # the node's rules hold
    reply = _query(node, QueryPoints(texts=["chair"]))
    assert isinstance(reply, Error) and "does not fill frames without ov" in reply.message


def test_queue_is_bounded_dropping_the_oldest(make_node: MakeNode) -> None:
    node = make_node(max_pending=2)
    worker = install_ov_backend(node)
    assert worker is not None
    for seq in range(5):
        _ingest(node, _frame(seq))
    assert worker.pending == 2 and worker.dropped == 3 and worker.queued == 5
    assert worker.process_pending() == 2
    assert [k.ov is not None for k in node.state.window.keyframes] == [False, False, False, True, True]
    stats = _status(node)["ov_backend"]
    assert stats["dropped"] == 3 and stats["encoded"] == 2 and stats["pending"] == 0


def test_keyframes_that_left_the_window(make_node: MakeNode) -> None:
    node = make_node(max_keyframes=2)
    worker = install_ov_backend(node)
    assert worker is not None
    _ingest(node, _frame(0))  # with depth
    for seq in (1, 2, 3):
        _ingest(node, _frame(seq, depth=False))
    assert [k.seq for k in node.state.window.keyframes] == [2, 3] and worker.pending == 4
    assert worker.process_pending() == 3
    # 0 left the window but has depth: its features still reach the global map; 1 has neither
    assert worker.encoded == 3 and worker.window_updates == 2 and worker.skipped_evicted == 1
    assert worker.map_points > 0 and node.state.global_map.snapshot().n_with_features > 0
    assert all(k.ov is not None for k in node.state.window.keyframes)


def test_a_load_makes_queued_keyframes_stale(make_node: MakeNode) -> None:
    node = make_node()
    worker = install_ov_backend(node)
    assert worker is not None
    _ingest(node, _frame(0))
    assert isinstance(_query(node, Save(name="plain")), Ok)
    _ingest(node, _frame(1))
    assert isinstance(_query(node, Load(name="plain")), Ok)
    assert worker.process_pending() == 0 and worker.stale == 2 and worker.encoded == 0
    assert all(k.ov is None for k in node.state.window.keyframes) and node.state.ov_space is None
    _ingest(node, _frame(2))  # frames after the load are served as usual
    assert worker.process_pending() == 1 and node.state.ov_space == SPACE
    # a map with the features saves and loads them: those keyframes are not queued again
    assert isinstance(_query(node, Save(name="with-ov")), Ok)
    assert isinstance(_query(node, Load(name="with-ov")), Ok)
    assert node.state.window.keyframes[-1].ov_space == SPACE and worker.pending == 0


def test_failures_are_counted_and_the_worker_thread_keeps_running(make_node: MakeNode) -> None:
    node = make_node()
    worker = install_ov_backend(node)
    assert worker is not None and worker.backend is not None
    real = worker.backend.dense_features
    calls = {"n": 0}

    def flaky(rgb: np.ndarray) -> np.ndarray:
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("simulated backend failure")
        return real(rgb)

    worker.backend.dense_features = flaky  # type: ignore[method-assign]
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop,), daemon=True)
    thread.start()
    for seq in range(3):
        _ingest(node, _frame(seq))
    deadline = time.monotonic() + 20.0
    while worker.encoded + worker.failed < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    stop.set()
    thread.join(timeout=5.0)
    assert not thread.is_alive()
    assert worker.failed == 1 and worker.encoded == 2
    assert _status(node)["ov_backend"]["failed"] == 1
