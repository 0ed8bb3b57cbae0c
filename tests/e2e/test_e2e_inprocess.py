"""The node in-process with real sockets: extension points, internal errors, non-blocking ingest."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from clients.client import MapperClient
from clients.harness import free_endpoints, synthetic_frame
from mapper.map.window import Keyframe
from mapper.node.config import NodeConfig, config_from_dict
from mapper.node.service import MapperNode
from protocol.errors import RemoteError
from protocol.messages import Message, Ok, QueryPoints, Save, encode
from tests.node_helpers import in_process_node

W, H = 32, 24


@pytest.fixture()
def node(tmp_path: Path) -> Iterator[MapperNode]:
    mapper = in_process_node(tmp_path, window={"max_keyframes": 3})
    mapper.start()
    try:
        yield mapper
    finally:
        mapper.stop()


def _client(node: MapperNode) -> MapperClient:
    return MapperClient(node.config.ingest_endpoint, node.config.query_endpoint, timeout_s=5.0, retries=0)


def test_handler_bug_becomes_internal_error_and_node_keeps_serving(node: MapperNode) -> None:
    def buggy(msg: Message) -> Message:
        raise ZeroDivisionError("boom")

    node.register_query_handler(QueryPoints, buggy)
    with _client(node) as client:
        with pytest.raises(RemoteError) as info:
            client.query_points(["chair"])
        assert info.value.code == "internal" and "ZeroDivisionError" in info.value.message
        status = client.status()
        assert status.extra["errors"] == {"internal": 1}
        assert "query_points" in status.extra["serving"]


def test_registered_handler_replaces_not_ready(node: MapperNode) -> None:
    node.register_query_handler(QueryPoints, lambda msg: Ok(message=f"{len(msg.texts)} texts"))  # type: ignore[attr-defined]
    with _client(node) as client:
        reply = client.request(QueryPoints(texts=["a", "b"], id="q1"))
        assert isinstance(reply, Ok) and reply.message == "2 texts" and reply.id == "q1"  # id filled in


def test_slow_query_does_not_block_ingest(node: MapperNode) -> None:
    entered, release = threading.Event(), threading.Event()

    def slow(msg: Message) -> Message:
        entered.set()
        release.wait(timeout=30)
        return Ok()

    node.register_query_handler(QueryPoints, slow)
    results: list[Message] = []
    with _client(node) as query_client, _client(node) as ingest_client:
        waiter = threading.Thread(
            target=lambda: results.append(query_client.request(QueryPoints(texts=["x"])))
        )
        waiter.start()
        try:
            assert entered.wait(timeout=10)
            # the query thread is busy inside the handler; frames are still acknowledged
            acks = [ingest_client.send_frame(synthetic_frame(i, 8, W, H)) for i in range(4)]
            assert [a.seq for a in acks] == [0, 1, 2, 3]
        finally:
            release.set()
            waiter.join(timeout=10)
        assert len(results) == 1 and isinstance(results[0], Ok)


def test_window_callbacks_and_map_version(node: MapperNode) -> None:
    added: list[int] = []
    evicted: list[int] = []

    def on_add(k: Keyframe) -> None:
        added.append(k.seq)

    def on_evict(k: Keyframe) -> None:
        evicted.append(k.seq)

    node.state.window.on_add.append(on_add)
    node.state.window.on_evict.append(on_evict)
    with _client(node) as client:
        acks = [client.send_frame(synthetic_frame(i, 8, W, H)) for i in range(8)]
        keyframe_seqs = [a.seq for a in acks if a.status == "keyframe"]
        assert added == keyframe_seqs and len(keyframe_seqs) > 3
        assert evicted == keyframe_seqs[:-3]  # max_keyframes = 3, oldest first
        assert client.status().map_version == len(keyframe_seqs)
        client.save("cb")
        added.clear()
        evicted.clear()
        client.load("cb")
        assert evicted == keyframe_seqs[-3:] and added == keyframe_seqs[-3:]


def test_handle_functions_never_raise(node: MapperNode) -> None:
    for data in (b"", b"\x00", b"\x81\xa1v\x01", encode(Save(name="ok")) + b"tail"):
        for handle in (node.handle_ingest, node.handle_query):
            reply = handle(data)
            assert isinstance(reply, bytes) and reply


def test_periodic_autosave_and_clean_run_exit(tmp_path: Path) -> None:
    mapper = in_process_node(
        tmp_path,
        poll_interval_s=NodeConfig.poll_interval_s,  # the default poll
        autosave_name="auto",
        autosave_interval_s=0.01,
        save_on_exit=False,
    )
    mapper.start()
    codes: list[int] = []
    runner = threading.Thread(target=lambda: codes.append(mapper.run()))
    runner.start()
    try:
        with _client(mapper) as client:
            client.send_frame(synthetic_frame(0, 8, W, H))
            deadline = threading.Event()
            for _ in range(200):  # up to 20 s on a loaded machine; normally well under a second
                status = client.status()
                if status.extra["last_save"] is not None:
                    break
                deadline.wait(0.1)
            assert status.extra["last_save"]["name"] == "auto"
            assert status.extra["last_save"]["map_version"] == 1
        assert (tmp_path / "maps" / "auto.govmap").is_file()
    finally:
        mapper.request_stop()
        runner.join(timeout=20)
    assert codes == [0]


def test_save_failure_on_the_node_is_internal_and_changes_nothing(tmp_path: Path) -> None:
    not_a_dir = tmp_path / "maps"
    not_a_dir.write_text("a file where the map directory should be")
    ingest, query = free_endpoints(2)
    config = config_from_dict(
        {"ingest_endpoint": ingest, "query_endpoint": query, "events_endpoint": "", "map_dir": str(not_a_dir)}
    )
    mapper = MapperNode(config)
    mapper.start()
    try:
        with _client(mapper) as client:
            client.send_frame(synthetic_frame(0, 8, W, H))
            with pytest.raises(RemoteError) as info:
                client.save("x")
            assert info.value.code == "internal" and "cannot write to map directory" in info.value.message
            status = client.status()
            assert status.keyframes == 1 and status.extra["last_save"] is None
    finally:
        mapper.stop()
    assert not_a_dir.read_text().startswith("a file")


def test_without_depth_semantic_requests_are_not_ready(node: MapperNode) -> None:
    """Frames with ov but no depth count for the window, add no map points; semantic requests
    then answer not_ready, except the averaging methods (``average_depth`` tests a point against
    the request's other points in keyframes without depth, ``queries.point_occlusion``)."""
    from clients.harness import sim_stream
    from protocol.errors import RemoteError

    stream = sim_stream(3, 30, 40, 30, depth=False)
    with _client(node) as client:
        for k in (0, 10, 20):
            assert client.send_frame(stream.frame(k, stream.render(k))).status == "keyframe"
        with pytest.raises(RemoteError, match="none carries an open-vocabulary feature") as info:
            client.query_points(["chair"])
        assert info.value.code == "not_ready"
        far = np.array([[0.0, 0.0, -50.0], [1.0, 1.0, 1.0]], np.float32)
        seg = client.segment_points(far, ["chair"], method="average", timeout_s=60.0)
        assert seg.label.shape == (2,) and seg.label[0] == -1
        tested = client.segment_points(far, ["chair"], method="average_depth", timeout_s=60.0)
        np.testing.assert_array_equal(tested.label, seg.label)  # two points hide nothing of each other
        status = client.status()
        assert status.extra["global_points"] == 0 and status.keyframes == 3


def test_unreadable_autosave_is_moved_aside_and_the_node_starts_empty(tmp_path: Path) -> None:
    maps = tmp_path / "maps"
    maps.mkdir()
    (maps / "auto.govmap").write_bytes(b"not a map")
    mapper = in_process_node(tmp_path, autosave_name="auto", save_on_exit=False)
    mapper.start()
    try:
        with _client(mapper) as client:
            assert client.status().keyframes == 0
    finally:
        mapper.stop()
    assert (maps / "auto.govmap.unreadable").read_bytes() == b"not a map"
    assert not (maps / "auto.govmap").exists()


def test_map_without_a_global_section_gets_it_rebuilt_from_its_keyframes(tmp_path: Path) -> None:
    """Maps saved before the global map existed load with their points rebuilt from keyframes."""
    from mapper.map.window import keyframes_to_arrays
    from mapper.node.store import MapStore

    frames = [synthetic_frame(seq, 20, W, H) for seq in (0, 5, 10)]
    keyframes = [
        Keyframe(seq=f.seq, stamp_ns=f.stamp_ns, camera=f.camera, K=f.K, world_from_cam=f.world_from_cam,
                 rgb=f.rgb, depth_m=f.depth_m, ov=f.ov, ov_space=f.ov_space)
        for f in frames
    ]  # fmt: skip
    arrays, entries = keyframes_to_arrays(keyframes)
    MapStore(tmp_path / "maps").save("old", arrays, {"map_version": 3, "ov_space": frames[0].ov_space,
                                                    "ov_dim": 8, "keyframes": entries})  # fmt: skip
    mapper = in_process_node(tmp_path)
    mapper.start()
    try:
        with _client(mapper) as client:
            assert "3 keyframes" in (client.load("old").message or "")
            status = client.status()
            assert status.keyframes == 3 and status.map_version == 3
            assert status.extra["global_points"] > 0 and status.extra["global_points_with_features"] > 0
    finally:
        mapper.stop()
