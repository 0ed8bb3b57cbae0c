"""``save`` / ``load`` across a restart: a map saved by one node, loaded by a new node and streamed
into further continues as if the stream had not stopped (the window holds the keyframes it held,
the map grows from what it had, answers equal those of the same frames streamed in one go); a
damaged map file is refused and changes nothing."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.harness import DEMO_OV_SPACE, synthetic_frame
from mapper.node.service import MapperNode
from mapper.node.store import MapStore
from mapper.ov.encoders import register_text_encoder, unregister_text_encoder
from protocol.messages import Error, Load, Ok, Save, Segmentation, SegmentPoints, decode, encode
from tests.node_helpers import DemoOneHotEncoder, in_process_node

N_FRAMES = 40
TEXTS = ["sky", "dark", "light"]


@pytest.fixture(autouse=True)
def _encoder() -> Iterator[None]:
    register_text_encoder(DEMO_OV_SPACE, DemoOneHotEncoder)
    yield
    unregister_text_encoder(DEMO_OV_SPACE)


def _node(tmp_path: Path) -> MapperNode:
    # inline integration: after an ack the frame is in the global map (no background timing)
    return in_process_node(tmp_path, window={"max_keyframes": 6}, global_map={"integrate_queue": 0})


def _ask(node: MapperNode, msg: Any) -> Any:
    return decode(node.handle_query(encode(msg)), direction="reply")


def _stream(node: MapperNode, seqs: range) -> None:
    for seq in seqs:
        node.handle_ingest(encode(synthetic_frame(seq, N_FRAMES, 64, 48)))
        if node.ctx.evicted_views is not None:  # as its worker would, soon after each eviction
            node.ctx.evicted_views.process_pending()


def _answers(node: MapperNode, xyz: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    if node.ctx.evicted_views is not None:  # settled: the node is not started, no worker thread runs
        node.ctx.evicted_views.process_pending()
    out = {}
    for method in ("average", "average_depth"):
        reply = _ask(node, SegmentPoints(xyz=xyz, texts=TEXTS, method=method))
        assert isinstance(reply, Segmentation), reply
        out[method] = (reply.label.copy(), reply.score.copy())
    return out


def _window(node: MapperNode) -> list[tuple[int, int, str]]:
    return [(k.seq, k.stamp_ns, k.camera) for k in node.state.window.keyframes]


def _map(node: MapperNode) -> tuple[np.ndarray, np.ndarray]:
    """The global map's points and features, in an order that does not depend on row order."""
    snap = node.state.global_map.snapshot()
    xyz, feat = np.asarray(snap.xyz), np.asarray(snap.unit_features_f32())
    order = np.lexsort(xyz.T)
    return xyz[order], feat[order]


def test_a_loaded_map_continues_as_if_the_stream_had_not_stopped(tmp_path: Path) -> None:
    half = N_FRAMES // 2
    first = _node(tmp_path / "first")
    _stream(first, range(half))
    assert first.ctx.state.keyframes_evicted > 0  # the window turned over before the save
    # points the first half saw
    asked = np.asarray(first.state.global_map.snapshot().xyz)[::7].astype(np.float32)
    before = _answers(first, asked)
    window, points = _window(first), len(first.state.global_map)
    assert isinstance(_ask(first, Save(name="half")), Ok)
    first.stop()
    maps = tmp_path / "first" / "maps"

    restarted = _node(tmp_path / "restarted")  # a new node, reading the first node's map directory
    restarted.ctx.store = MapStore(maps)
    assert isinstance(_ask(restarted, Load(name="half")), Ok)
    assert _window(restarted) == window and len(restarted.state.global_map) == points
    after_load = _answers(restarted, asked)
    for method, (label, score) in before.items():
        np.testing.assert_array_equal(after_load[method][0], label)
        np.testing.assert_allclose(after_load[method][1], score, atol=1e-6)
    _stream(restarted, range(half, N_FRAMES))

    one_go = _node(tmp_path / "one_go")
    _stream(one_go, range(N_FRAMES))
    assert _window(restarted) == _window(one_go)  # the same keyframes chosen after the restart
    assert len(restarted.state.global_map) == len(one_go.state.global_map) > points  # grown, not reset
    (xyz, feat), (xyz_one, feat_one) = _map(restarted), _map(one_go)
    np.testing.assert_allclose(xyz, xyz_one, atol=1e-5)
    np.testing.assert_allclose(feat, feat_one, atol=2e-3)  # features are kept as fp16 unit vectors
    continued, streamed = _answers(restarted, asked), _answers(one_go, asked)
    for method, (label, score) in streamed.items():
        np.testing.assert_array_equal(continued[method][0], label)
        np.testing.assert_allclose(continued[method][1], score, atol=2e-3)
    restarted.stop()
    one_go.stop()


def test_a_damaged_map_is_refused_and_changes_nothing(tmp_path: Path) -> None:
    node = _node(tmp_path)
    _stream(node, range(10))
    assert isinstance(_ask(node, Save(name="good")), Ok)
    store = MapStore(tmp_path / "maps")
    arrays, manifest = store.load("good")
    arrays["global.xyz"] = arrays["global.xyz"][:-1]  # one row short
    store.save("damaged", arrays, {k: v for k, v in manifest.items() if not k.startswith("format")})
    window, points, version = _window(node), len(node.state.global_map), node.state.map_version
    reply = _ask(node, Load(name="damaged"))
    assert isinstance(reply, Error) and reply.code == "bad_request" and "damaged" in reply.message
    assert _window(node) == window and len(node.state.global_map) == points
    assert node.state.map_version == version
    node.stop()
