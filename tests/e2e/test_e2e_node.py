"""End-to-end: a real ``govnesf serve`` process on free loopback ports, driven over ZeroMQ.

Every test checks behaviour through the wire only (acks, errors, status counters, files in the
map directory). The node process is always killed in teardown.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq

from clients.client import MapperClient
from clients.harness import REPO_ROOT, NodeProcess, synthetic_frame, write_synthetic_recording
from clients.replay import replay
from protocol.errors import RemoteError
from protocol.messages import (
    Ack,
    Error,
    MapUpdated,
    Ok,
    QueryPoints,
    Render,
    SegmentPoints,
    Status,
    StatusRequest,
    decode,
    encode,
)

pytestmark = pytest.mark.slow

MAX_MESSAGE_BYTES = 1 << 20  # small limit so that the oversize test stays cheap
W, H = 64, 48


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    root = tmp_path_factory.mktemp("e2e")
    proc = NodeProcess(
        root / "maps",
        log_path=root / "node.log",
        extra_args=[
            "--set",
            f"max_message_bytes={MAX_MESSAGE_BYTES}",
            "--set",
            "window.max_keyframes=10",
            "--set",
            "serve_model=false",  # the base node: no learned model (tests/e2e/test_e2e_semantic.py has it)
        ],
    )
    with proc:
        proc.wait_ready()
        yield proc


@pytest.fixture()
def client(node: NodeProcess) -> Iterator[MapperClient]:
    with node.client(timeout_s=5.0, retries=1) as c:
        yield c


def _status(client: MapperClient) -> Status:
    """The node's status once every acked keyframe is in the global map (the integrator fuses
    them shortly after their acks; ``global_map.integrate_queue``), so memory and map counts are
    settled."""
    deadline = time.monotonic() + 60.0
    status = client.status()
    while (status.extra.get("integration") or {}).get("backlog"):
        assert time.monotonic() < deadline, f"the integrator's backlog did not drain: {status.extra}"
        time.sleep(0.02)
        status = client.status()
    return status


def _raw_frame(changes: dict[str, Any]) -> bytes:
    """Wire bytes of a valid synthetic frame with top-level keys replaced (to craft bad input)."""
    wire = msgpack.unpackb(encode(synthetic_frame(1, 20, W, H)), raw=False)
    wire.update(changes)
    return msgpack.packb(wire, use_bin_type=True)


def _dealer(ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str) -> zmq.Socket[bytes]:
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, 5000)
    sock.connect(endpoint)
    return sock


def test_replay_acks_every_frame_and_status_counts_match(
    node: NodeProcess, client: MapperClient, tmp_path: Path
) -> None:
    n = 24
    recording = write_synthetic_recording(tmp_path / "r.govrec", n, W, H)
    before = _status(client)
    summary = replay(recording, client, window=4, progress=False)
    after = _status(client)
    assert summary.sent == n and not summary.truncated and summary.unreachable is None
    assert sum(summary.statuses.values()) == n and not summary.errors
    kf, acc = summary.statuses["keyframe"], summary.statuses["accepted"]
    assert kf > 0 and acc > 0  # the path is slow at both ends: some frames are not keyframes
    assert after.frames_received - before.frames_received == n
    assert after.frames_rejected == before.frames_rejected
    assert after.map_version - before.map_version == kf
    assert after.extra["frames_keyframe"] - before.extra["frames_keyframe"] == kf
    assert after.extra["frames_accepted"] - before.extra["frames_accepted"] == acc
    assert after.keyframes == min(10, before.keyframes + kf)  # bounded by window.max_keyframes
    assert after.ov_space == "demo-checker"
    assert after.memory_bytes > 0 and summary.map_version == after.map_version


def test_truncated_recording_replays_complete_frames(
    node: NodeProcess, client: MapperClient, tmp_path: Path
) -> None:
    recording = write_synthetic_recording(tmp_path / "r.govrec", 5, W, H)
    data = recording.read_bytes()
    recording.write_bytes(data[:-100])
    summary = replay(recording, client, progress=False)
    assert summary.sent == 4 and summary.truncated and "cut short" in (summary.truncation or "")


@pytest.mark.parametrize(
    "changes, fragment",
    [
        ({"T_world_cam": [float("nan")] + [0.0] * 15}, "T_world_cam"),
        ({"width": W + 1}, "rgb"),
        ({"K": [1.0, 2.0, 3.0]}, "K"),
        ({"seq": -1}, "seq"),
        ({"depth": {"dtype": "float32", "shape": [H, W], "data": b"\x00" * 7}}, "depth"),
    ],
)
def test_bad_frames_get_errors_and_change_nothing(
    node: NodeProcess, client: MapperClient, changes: dict[str, Any], fragment: str
) -> None:
    before = _status(client)
    with pytest.raises(RemoteError) as info:
        client.send_frame(_raw_frame(changes))
    assert info.value.code == "bad_request" and fragment in info.value.message
    after = _status(client)
    assert after.frames_received == before.frames_received + 1
    assert after.frames_rejected == before.frames_rejected + 1
    assert (after.map_version, after.keyframes, after.memory_bytes) == (
        before.map_version, before.keyframes, before.memory_bytes,
    )  # fmt: skip


def test_ov_space_mismatch_is_refused(node: NodeProcess, client: MapperClient) -> None:
    client.send_frame(synthetic_frame(0, 20, W, H))  # makes sure the map's space is demo-checker
    before = _status(client)
    frame = synthetic_frame(7, 20, W, H)
    frame.ov_space = "minilm-l6-v2"
    with pytest.raises(RemoteError) as info:
        client.send_frame(frame)
    assert info.value.code == "ov_space_mismatch" and "demo-checker" in info.value.message
    # same space, other feature dimension: a rejected ack
    frame = synthetic_frame(8, 20, W, H)
    frame.ov = np.zeros((3, 4, 5), np.float16)
    ack = client.send_frame(frame)
    assert ack.status == "rejected" and "dimension 5" in (ack.reason or "")
    after = _status(client)
    assert after.frames_rejected == before.frames_rejected + 2
    assert (after.map_version, after.keyframes, after.ov_space) == (
        before.map_version, before.keyframes, "demo-checker",
    )  # fmt: skip


def test_garbage_never_kills_the_node(node: NodeProcess, client: MapperClient) -> None:
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    try:
        before = _status(client)
        cases: list[tuple[str, bytes, str]] = [
            ("garbage", b"\xc1\xff\x00garbage", "bad_request"),
            ("empty", b"", "bad_request"),
            ("list", msgpack.packb([1, 2, 3]), "bad_request"),
            ("no type", msgpack.packb({"v": 1}), "bad_request"),
            ("unknown type", msgpack.packb({"v": 1, "type": "teleport", "id": 5}), "bad_request"),
            ("version 2", msgpack.packb({"v": 2, "type": "status"}), "unsupported_version"),
            ("oversize", b"\x00" * (MAX_MESSAGE_BYTES + 1), "too_large"),
            ("query on ingest", encode(StatusRequest(id=3)), "bad_request"),
        ]
        for endpoint in (node.ingest, node.query):
            sock = _dealer(ctx, endpoint)
            for name, data, code in cases:
                if endpoint == node.query and name == "query on ingest":
                    continue
                sock.send_multipart([b"", data])
                reply = decode(sock.recv_multipart()[-1], direction="reply")
                assert isinstance(reply, Error), name
                assert reply.code == code, (name, reply.message)
            sock.close()
        # the id of an undecodable request is still echoed
        sock = _dealer(ctx, node.query)
        sock.send_multipart([b"", msgpack.packb({"v": 1, "type": "teleport", "id": "abc"})])
        assert decode(sock.recv_multipart()[-1], direction="reply").id == "abc"  # type: ignore[attr-defined]
        # a frame sent to the query endpoint
        sock.send_multipart([b"", encode(synthetic_frame(0, 20, W, H))])
        reply = decode(sock.recv_multipart()[-1], direction="reply")
        assert isinstance(reply, Error) and "ingest endpoint" in reply.message
        sock.close()
        after = _status(client)
        assert (after.map_version, after.keyframes) == (before.map_version, before.keyframes)
        ingest_garbage = len(cases)
        assert after.frames_received - before.frames_received == ingest_garbage
        assert after.frames_rejected - before.frames_rejected == ingest_garbage
        assert node.process is not None and node.process.poll() is None
    finally:
        ctx.destroy(linger=0)


def test_message_beyond_the_hard_limit_drops_only_that_peer(node: NodeProcess, client: MapperClient) -> None:
    """Above 4x max_message_bytes ZeroMQ refuses the message at the transport (no reply, the
    peer is disconnected); the node and its other peers carry on."""
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    try:
        sock = _dealer(ctx, node.ingest)
        sock.setsockopt(zmq.RCVTIMEO, 500)
        sock.send_multipart([b"", b"\x00" * (4 * MAX_MESSAGE_BYTES + 1)])
        with pytest.raises(zmq.Again):
            sock.recv_multipart()
        sock.close()
        assert isinstance(client.send_frame(synthetic_frame(2, 20, W, H)), Ack)
        assert node.process is not None and node.process.poll() is None
    finally:
        ctx.destroy(linger=0)


def test_req_and_dealer_peers_are_answered(node: NodeProcess) -> None:
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    try:
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.RCVTIMEO, 5000)
        req.connect(node.query)
        req.send(encode(StatusRequest(id=11)))
        reply = decode(req.recv(), direction="reply")
        assert isinstance(reply, Status) and reply.id == 11
        req_ingest = ctx.socket(zmq.REQ)
        req_ingest.setsockopt(zmq.RCVTIMEO, 5000)
        req_ingest.connect(node.ingest)
        req_ingest.send(encode(synthetic_frame(3, 20, W, H)))
        ack = decode(req_ingest.recv(), direction="reply")
        assert isinstance(ack, Ack) and ack.seq == 3
        for delimiter in ([b""], []):
            dealer = _dealer(ctx, node.ingest)
            dealer.send_multipart([*delimiter, encode(synthetic_frame(4, 20, W, H))])
            parts = dealer.recv_multipart()
            assert parts[:-1] == delimiter  # the envelope comes back as sent
            ack = decode(parts[-1], direction="reply")
            assert isinstance(ack, Ack) and ack.seq == 4
            dealer.close()
        for sock in (req, req_ingest):
            sock.close(linger=0)
    finally:
        ctx.destroy(linger=0)


def test_queries_without_encoder_or_model_answer_not_ready(client: MapperClient) -> None:
    """This node's frames carry 'demo-checker' features: no text encoder embeds queries in that
    space, the learned model is not loaded and rendering is not served yet."""
    requests = [
        QueryPoints(texts=["chair"]),
        SegmentPoints(xyz=np.zeros((2, 3), np.float32), texts=["chair", "table"]),
        Render(
            width=8, height=6, K=np.array([8.0, 8.0, 4.0, 3.0]), world_from_cam=np.eye(4), outputs=["rgb"]
        ),
    ]
    for request in requests:
        reply = client.request(request)
        assert isinstance(reply, Error) and reply.code == "not_ready", reply
        assert request.TYPE in reply.message
    with pytest.raises(RemoteError, match="not_ready") as info:
        client.query_points(["chair"])
    assert "no text encoder for ov_space 'demo-checker'" in info.value.message
    with pytest.raises(RemoteError, match="learned model is not loaded"):
        client.segment_points(np.zeros((1, 3), np.float32), ["chair"])


def test_save_load_roundtrip_and_traversal_refused(node: NodeProcess, client: MapperClient) -> None:
    for seq in range(0, 20, 4):
        client.send_frame(synthetic_frame(seq, 20, W, H))
    assert isinstance(client.save("e2e_map"), Ok)
    assert (node.map_dir / "e2e_map.govmap").is_file()
    # the status of the map as saved: the integrator may still be fusing the last acked keyframes into
    # the global map before the save, which waits for them (global_map.integrate_queue)
    saved = _status(client)
    assert saved.keyframes > 0
    # change the map, then load it back
    far = synthetic_frame(10, 20, W, H)
    far.world_from_cam = far.world_from_cam.copy()
    far.world_from_cam[2, 3] += 5.0
    assert client.send_frame(far).status == "keyframe"
    changed = _status(client)
    assert changed.map_version > saved.map_version
    ok = client.load("e2e_map")
    assert "e2e_map" in (ok.message or "")
    loaded = _status(client)
    assert loaded.keyframes == saved.keyframes and loaded.map_version == changed.map_version + 1
    assert loaded.memory_bytes == saved.memory_bytes and loaded.ov_space == saved.ov_space
    # traversal and bad names never touch the file system
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    try:
        sock = _dealer(ctx, node.query)
        for kind in ("save", "load"):
            for name in ("../evil", "..", "/tmp/evil", "a/b", "x" * 65):
                sock.send_multipart([b"", msgpack.packb({"v": 1, "type": kind, "name": name, "id": 1})])
                reply = decode(sock.recv_multipart()[-1], direction="reply")
                assert isinstance(reply, Error) and reply.code == "bad_request", (kind, name)
        sock.close()
    finally:
        ctx.destroy(linger=0)
    assert sorted(p.name for p in node.map_dir.iterdir()) == ["e2e_map.govmap"]
    assert not (node.map_dir.parent / "evil.govmap").exists()
    with pytest.raises(RemoteError, match="no saved map named 'missing'"):
        client.load("missing")
    assert _status(client).map_version == loaded.map_version  # failed load changed nothing


def test_events_publish_map_updates(node: NodeProcess, client: MapperClient) -> None:
    assert node.events is not None
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    try:
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.setsockopt(zmq.RCVTIMEO, 200)
        sub.connect(node.events)
        event, sent = None, None
        for attempt in range(25):  # a SUB misses what is published before it has joined
            frame = synthetic_frame(attempt, 20, W, H)
            frame.world_from_cam = frame.world_from_cam.copy()
            frame.world_from_cam[2, 3] += 10.0 + attempt  # far from everything: always a keyframe
            ack = client.send_frame(frame)
            assert ack.status == "keyframe"
            try:
                event, sent = decode(sub.recv(), direction="reply"), frame
                break
            except zmq.Again:
                continue
        assert isinstance(event, MapUpdated) and 0 < event.map_version <= _status(client).map_version
        # the notice names the box the new keyframe can change: its depth points
        assert sent is not None and sent.depth_m is not None
        assert event.region_min is not None and event.region_max is not None
        v, u = H // 2, W // 2
        z = float(sent.depth_m[v, u])
        fx, fy, cx, cy = sent.K
        centre = sent.world_from_cam[:3, :3] @ [(u + 0.5 - cx) / fx * z, (v + 0.5 - cy) / fy * z, z]
        centre = centre + sent.world_from_cam[:3, 3]
        assert np.all(event.region_min - 0.05 <= centre) and np.all(centre <= event.region_max + 0.05)
        sub.close()
    finally:
        ctx.destroy(linger=0)


def test_cli_status_and_unreachable_replay(node: NodeProcess, tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    out = subprocess.run(
        [sys.executable, "-m", "clients.cli", "status", "--query", node.query],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "map_version" in out.stdout and "frames_received" in out.stdout
    recording = write_synthetic_recording(tmp_path / "r.govrec", 2, W, H)
    from clients.harness import free_endpoints

    (nobody,) = free_endpoints(1)
    out = subprocess.run(
        [sys.executable, "-m", "clients.cli", "replay", str(recording), "--ingest", nobody,
         "--timeout", "0.3", "--retries", "1", "--no-progress"],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 1 and "unreachable" in out.stderr


def test_sigterm_exits_cleanly_with_final_save(tmp_path: Path) -> None:
    proc = NodeProcess(
        tmp_path / "maps",
        log_path=tmp_path / "node.log",
        extra_args=["--set", "autosave_name=final", "--events", ""],
        events=False,
    )
    with proc:
        proc.wait_ready()
        with proc.client(timeout_s=5.0) as client:
            assert client.send_frame(synthetic_frame(0, 20, W, H)).status == "keyframe"
        assert proc.signal(signal.SIGTERM) == 0
    assert (tmp_path / "maps" / "final.govmap").is_file()
    log = (tmp_path / "node.log").read_text()
    assert "SIGTERM" in log and "final save" in log


def test_second_node_on_same_port_fails_clearly(node: NodeProcess, tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    out = subprocess.run(
        [sys.executable, "-m", "clients.cli", "serve", "--ingest", node.ingest, "--query", node.query,
         "--events", "", "--map-dir", str(tmp_path)],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 3 and "cannot bind" in out.stderr


def test_frames_roundtrip_through_jpeg_ingest(client: MapperClient) -> None:
    frame = synthetic_frame(5, 20, W, H, rgb_encoding="jpeg")
    assert isinstance(client.send_frame(frame), Ack)
