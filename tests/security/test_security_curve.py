"""CurveZMQ: `govnesf keys` file layout, an allowed client gets through, a plain client and an
unknown key get nothing, the loopback default is unchanged, non-loopback binds without CURVE are
refused at start-up unless insecure."""

from __future__ import annotations

import logging
import os
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zmq
import zmq.auth

from clients.cli import main as govnesf
from clients.client import MapperClient
from clients.harness import REPO_ROOT, free_endpoints, synthetic_frame
from mapper.node.config import NodeConfig, config_from_dict
from mapper.node.security import exposure_problem, is_loopback
from mapper.node.service import MapperNode
from protocol.curve import ClientCurveKeys, CurveKeyError, load_client_keys
from protocol.errors import RemoteError
from protocol.messages import MapUpdated, decode


def _make_keys(root: Path, *clients: str) -> None:
    assert govnesf(["keys", str(root)]) == 0
    for name in clients:
        assert govnesf(["keys", str(root), "--client", name]) == 0


def _config(tmp_path: Path, **extra: object) -> NodeConfig:
    ingest, query, events = free_endpoints(3)
    data: dict[str, object] = {
        "ingest_endpoint": ingest, "query_endpoint": query, "events_endpoint": events,
        "map_dir": str(tmp_path / "maps"), "poll_interval_s": 0.02, **extra,
    }  # fmt: skip
    return config_from_dict(data)


@pytest.fixture()
def curve_node(tmp_path: Path) -> Iterator[MapperNode]:
    keys = tmp_path / "keys"
    _make_keys(keys, "robot1")
    node = MapperNode(_config(tmp_path, curve_dir=str(keys), limits={"curve_reload_interval_s": 0.1}))
    node.start()
    runner = threading.Thread(target=node.run, daemon=True)  # the main loop reloads allowed/
    runner.start()
    try:
        yield node
    finally:
        node.request_stop()
        runner.join(timeout=15)


def _client(node: MapperNode, curve: ClientCurveKeys | None, timeout_s: float = 3.0) -> MapperClient:
    cfg = node.config
    return MapperClient(cfg.ingest_endpoint, cfg.query_endpoint, timeout_s=timeout_s, retries=0, curve=curve)


def test_keys_command_makes_the_zmq_auth_layout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "keys"
    assert govnesf(["keys", str(root)]) == 0
    assert sorted(p.name for p in root.iterdir()) == ["allowed", "server.key", "server.key_secret"]
    assert list((root / "allowed").iterdir()) == []
    assert govnesf(["keys", str(root), "--client", "robot1"]) == 0
    assert sorted(p.name for p in (root / "clients").iterdir()) == ["robot1.key", "robot1.key_secret"]
    assert sorted(p.name for p in (root / "allowed").iterdir()) == ["robot1.key"]
    assert (root / "allowed/robot1.key").read_bytes() == (root / "clients/robot1.key").read_bytes()
    for secret in (root / "server.key_secret", root / "clients/robot1.key_secret"):
        assert stat.S_IMODE(os.stat(secret).st_mode) == 0o600
    # zmq.auth's own format: its loader reads them, the public halves match
    server_pub, server_sec = zmq.auth.load_certificate(str(root / "server.key_secret"))
    assert server_sec and zmq.auth.load_certificate(str(root / "server.key"))[0] == server_pub
    client_pub, _ = zmq.auth.load_certificate(str(root / "allowed/robot1.key"))
    keys = load_client_keys(root, "robot1")
    assert keys.public == client_pub and keys.server_public == server_pub
    capsys.readouterr()
    # never overwritten; bad names refused
    assert govnesf(["keys", str(root)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert govnesf(["keys", str(root), "--client", "robot1"]) == 2
    assert govnesf(["keys", str(root), "--client", "../evil"]) == 2
    assert "invalid" in capsys.readouterr().err
    with pytest.raises(CurveKeyError, match="not found"):
        load_client_keys(root, "nobody")
    # --client before the server keys: refused, nothing written
    fresh = tmp_path / "fresh"
    assert govnesf(["keys", str(fresh), "--client", "robot1"]) == 2
    assert "run `govnesf keys" in capsys.readouterr().err
    assert not fresh.exists()


def test_allowed_client_streams_queries_and_gets_events(curve_node: MapperNode, tmp_path: Path) -> None:
    keys = load_client_keys(tmp_path / "keys", "robot1")
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    keys.apply(sub)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    assert curve_node.config.events_endpoint
    sub.connect(curve_node.config.events_endpoint)
    try:
        with _client(curve_node, keys) as client:
            status = client.status()
            assert status.extra["security"]["mode"] == "curve"
            assert status.extra["security"]["allowed_keys"] == 1
            ack = client.send_frame(synthetic_frame(0, width=32, height=24))
            assert ack.status == "keyframe"
            # a heavy request (worker pool, inproc hand-back) is answered through CURVE too
            with pytest.raises(RemoteError) as info:
                client.segment_points(np.zeros((2, 3), np.float32), ["chair"], method="average")
            assert info.value.code == "not_ready"
            # the SUB joined before the frame, but give its handshake time: send until a notice lands
            deadline = time.monotonic() + 5.0
            seq = 1
            while not sub.poll(100) and time.monotonic() < deadline:
                client.send_frame(synthetic_frame(seq * 7, width=32, height=24))
                seq += 1
            notice = decode(sub.recv(zmq.NOBLOCK), direction="reply")
            assert isinstance(notice, MapUpdated)
    finally:
        sub.close(linger=0)


def test_plain_client_and_unknown_key_get_no_reply(curve_node: MapperNode, tmp_path: Path) -> None:
    with _client(curve_node, None, timeout_s=0.5) as plain, pytest.raises(TimeoutError):
        plain.status()
    # a key pair made elsewhere (not in allowed/), with the right server key
    other = tmp_path / "other"
    _make_keys(other, "intruder")
    intruder = load_client_keys(other, "intruder")
    server_public = load_client_keys(tmp_path / "keys", "robot1").server_public
    unknown = ClientCurveKeys(intruder.public, intruder.secret, server_public)
    with _client(curve_node, unknown, timeout_s=0.5) as client:
        with pytest.raises(TimeoutError):
            client.status()
        with pytest.raises(TimeoutError):
            client.send_frame(synthetic_frame(0, width=32, height=24))
    # nothing reached the node
    with _client(curve_node, load_client_keys(tmp_path / "keys", "robot1")) as client:
        status = client.status()
    assert status.frames_received == 0 and status.extra["requests"] == {"status": 1}


def test_keys_added_to_allowed_are_picked_up_and_removed_ones_refused(
    curve_node: MapperNode, tmp_path: Path
) -> None:
    keys = tmp_path / "keys"
    assert govnesf(["keys", str(keys), "--client", "planner"]) == 0  # also copies it into allowed/
    planner = load_client_keys(keys, "planner")
    deadline = time.monotonic() + 5.0
    while True:
        with _client(curve_node, planner, timeout_s=0.3) as client:
            try:
                assert client.status().extra["security"]["allowed_keys"] == 2
                break
            except TimeoutError:
                assert time.monotonic() < deadline, "the new key was not picked up"
    (keys / "allowed" / "planner.key").unlink()
    robot = load_client_keys(keys, "robot1")
    deadline = time.monotonic() + 5.0
    while True:  # the main loop checks every 0.5 s (and curve_reload_interval_s)
        with _client(curve_node, robot) as client:
            if client.status().extra["security"]["allowed_keys"] == 1:
                break
        assert time.monotonic() < deadline, "the removed key was not dropped"
        time.sleep(0.1)
    with _client(curve_node, planner, timeout_s=0.5) as client, pytest.raises(TimeoutError):
        client.status()


def test_loopback_default_is_plain_and_says_so(tmp_path: Path) -> None:
    assert NodeConfig().curve_dir is None and not NodeConfig().insecure
    node = MapperNode(_config(tmp_path))
    node.start()
    try:
        with _client(node, None) as client:
            status = client.status()
    finally:
        node.stop()
    assert status.extra["security"] == {"mode": "loopback"}


@pytest.mark.parametrize(
    "endpoint, local",
    [
        ("tcp://127.0.0.1:5555", True), ("tcp://localhost:1", True), ("tcp://[::1]:1", True),
        ("tcp://127.0.0.2:1", True), ("ipc:///tmp/x", True), ("inproc://x", True),
        ("tcp://*:5555", False), ("tcp://0.0.0.0:1", False), ("tcp://192.168.1.5:1", False),
        ("tcp://eth0:1", False), ("tcp://[::]:1", False),
    ],
)  # fmt: skip
def test_loopback_classification(endpoint: str, local: bool) -> None:
    assert is_loopback(endpoint) is local
    assert (exposure_problem([endpoint], None, False) is None) is local
    assert exposure_problem([endpoint], "keys", False) is None
    assert exposure_problem([endpoint], None, True) is None


def test_remote_bind_without_curve_is_refused_unless_insecure(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    port = free_endpoints(1)[0].rpartition(":")[2]
    cfg = _config(tmp_path, allow_remote=True, events_endpoint="")
    remote = config_from_dict({**_as_dict(cfg), "ingest_endpoint": f"tcp://0.0.0.0:{port}"})
    with pytest.raises(RuntimeError, match="refusing to bind tcp://0.0.0.0:.*--curve-dir.*--insecure"):
        MapperNode(remote).start()
    insecure = config_from_dict({**_as_dict(remote), "insecure": True})
    node = MapperNode(insecure)
    with caplog.at_level(logging.WARNING, logger="mapper.node.service"):
        node.start()
    try:
        assert any("INSECURE" in r.getMessage() for r in caplog.records)
        with MapperClient(f"tcp://127.0.0.1:{port}", insecure.query_endpoint, timeout_s=3.0, retries=0) as c:
            assert c.send_frame(synthetic_frame(0, width=32, height=24)).status == "keyframe"
            assert c.status().extra["security"] == {"mode": "insecure"}
    finally:
        node.stop()


def _as_dict(cfg: NodeConfig) -> dict[str, object]:
    from mapper.node.config import to_dict

    return to_dict(cfg)


def test_serve_refuses_remote_bind_with_a_clear_message(tmp_path: Path) -> None:
    ingest, query = free_endpoints(2)
    port = ingest.rpartition(":")[2]
    cmd = [
        sys.executable, "-m", "clients.cli", "serve", "--ingest", f"tcp://*:{port}", "--query", query,
        "--events", "", "--map-dir", str(tmp_path / "maps"), "--set", "allow_remote=true",
        "--set", "serve_model=false",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    done = subprocess.run(cmd, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 3
    assert "refusing to bind tcp://*:" in done.stderr and "--insecure" in done.stderr
    # a curve_dir without keys: also refused, naming the missing file and the command that makes it
    cmd[cmd.index("--set")] = "--curve-dir"
    cmd[cmd.index("allow_remote=true")] = str(tmp_path / "nokeys")
    done = subprocess.run(cmd, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 3
    assert "server.key_secret not found" in done.stderr and "govnesf keys" in done.stderr


def test_cli_commands_take_curve_dir_and_client(
    curve_node: MapperNode, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    keys, query = str(tmp_path / "keys"), curve_node.config.query_endpoint
    common = ["--query", query, "--timeout", "2", "--retries", "0"]
    assert govnesf(["status", *common, "--curve-dir", keys, "--client", "robot1", "--json"]) == 0
    assert '"mode": "curve"' in capsys.readouterr().out
    assert govnesf(["save", "m1", *common, "--curve-dir", keys, "--client", "robot1"]) == 0
    assert govnesf(["status", "--query", query, "--timeout", "0.5", "--retries", "0"]) == 1  # plain: no reply
    assert f"no node answers at {query} (0.5 s); is `govnesf serve` running?" in capsys.readouterr().err
    # the ping goes through CURVE like the request: an allowed client's query passes it and gets
    # the node's own answer (an empty map has no features to query yet)
    assert govnesf(["query", "chair", *common, "--curve-dir", keys, "--client", "robot1"]) == 3
    assert "not_ready" in capsys.readouterr().err
    # keys the node does not know: the ping gets no reply, and the message asks about the key
    _make_keys(tmp_path / "other", "intruder")
    other = ["--curve-dir", str(tmp_path / "other"), "--client", "intruder"]
    assert govnesf(["query", "chair", *common, "--ping-timeout", "0.5", *other]) == 1
    assert "does it allow this client's CurveZMQ key?" in capsys.readouterr().err
    assert govnesf(["status", *common, "--curve-dir", keys]) == 2  # --client missing
    assert "go together" in capsys.readouterr().err
    assert govnesf(["status", *common, "--curve-dir", keys, "--client", "nobody"]) == 2
    assert "not found" in capsys.readouterr().err
    for command in (
        ["replay", "x.govrec"],
        ["render", "--pose", "0,0,1,0,0"],
        ["sim", "stream", "--seed", "1"],
    ):
        with pytest.raises(SystemExit):
            govnesf([*command, "--help"])
        assert "--curve-dir" in capsys.readouterr().out
