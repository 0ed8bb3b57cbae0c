"""The commands that talk to a node (``status``, ``query``, ``render``, ``save``, ``load``) ping it
first (``--ping-timeout``): with nothing listening at the endpoint they fail with exit code 1 and a
message naming the endpoint, before the long ``--timeout`` of the request could run; a node that
answers the ping then gets the request itself, with ``--timeout``."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zmq

from clients.cli import query as query_cli
from clients.cli import render as render_cli
from clients.client import MapperClient, NodeUnreachableError
from clients.harness import free_endpoints
from protocol.messages import Points, Status, StatusRequest, decode, encode
from tests.clients.test_ply import ScriptedQueryNode

# Each command with a long request timeout and retries: if the ping did not stop it, the command
# would wait that long and print the request's timeout message, not the ping's.
COMMANDS: dict[str, tuple[Callable[[list[str]], int], list[str]]] = {
    "status": (query_cli.status_main, []),
    "save": (query_cli.save_main, ["m1"]),
    "load": (query_cli.load_main, ["m1"]),
    "query": (query_cli.query_main, ["find the chair"]),
    "render": (render_cli.main, ["--pose", "0,0,1,0,0"]),
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_no_node_at_the_endpoint_fails_with_the_ping_message(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    main, args = COMMANDS[command]
    (nobody,) = free_endpoints(1)  # a free port: nothing listens there
    code = main([*args, "--query", nobody, "--timeout", "60", "--retries", "3", "--ping-timeout", "0.2"])
    err = capsys.readouterr().err
    assert code == 1
    assert f"no node answers at {nobody} (0.2 s); is `govnesf serve` running?" in err
    assert err.startswith(f"govnesf {command}: ")


def test_the_ping_waits_at_most_timeout(capsys: pytest.CaptureFixture[str]) -> None:
    (nobody,) = free_endpoints(1)
    assert query_cli.status_main(["--query", nobody, "--timeout", "0.1", "--retries", "0"]) == 1
    assert f"no node answers at {nobody} (0.1 s)" in capsys.readouterr().err


def test_a_node_that_answers_the_ping_gets_the_request(capsys: pytest.CaptureFixture[str]) -> None:
    answer = Points(map_version=2, xyz=np.zeros((0, 3), np.float32), score=np.zeros(0, np.float32),
                    label=np.zeros(0, np.int32))  # fmt: skip
    server = ScriptedQueryNode(answer)
    try:
        assert query_cli.query_main(["chair", "--query", server.endpoint, "--timeout", "10"]) == 0
        assert server.pings == 1 and len(server.requests) == 1
        # --ping-timeout 0: no ping, the request goes out at once
        assert query_cli.query_main(["chair", "--query", server.endpoint, "--ping-timeout", "0"]) == 0
        assert server.pings == 1 and len(server.requests) == 2
        # `govnesf status` prints the ping's answer: one status request, not two
        assert query_cli.status_main(["--query", server.endpoint]) == 0
        assert server.pings == 2
    finally:
        server.close()
    assert "map_version" in capsys.readouterr().out


@pytest.fixture()
def status_only_node() -> Iterator[str]:
    """A query endpoint that answers ``status`` and never anything else (a node stuck on a
    request); yields its endpoint."""
    (endpoint,) = free_endpoints(1)
    ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    sock = ctx.socket(zmq.ROUTER)
    sock.bind(endpoint)
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            if not sock.poll(20):
                continue
            parts = sock.recv_multipart()
            msg = decode(parts[-1], direction="request")
            if isinstance(msg, StatusRequest):
                status = Status(
                    map_version=0, keyframes=0, frames_received=0, frames_rejected=0, ov_space=None,
                    memory_bytes=0, uptime_s=1.0, id=msg.id,
                )
                sock.send_multipart([*parts[:-1], encode(status)])

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield endpoint
    finally:
        stop.set()
        thread.join(timeout=5)
        sock.close(linger=0)
        ctx.term()


def test_a_request_unanswered_after_the_ping_says_so(
    status_only_node: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code = query_cli.query_main(["chair", "--query", status_only_node, "--timeout", "0.3", "--retries", "0"])
    err = capsys.readouterr().err
    assert code == 1
    assert f"the node at {status_only_node} answers its status but sent no reply" in err
    assert "--timeout 0.3 s (1 try)" in err and "no node answers" not in err
    code = render_cli.main(["--pose", "0,0,1,0,0", "--query", status_only_node, "--timeout", "0.3"])
    assert code == 1 and "answers its status but sent no reply" in capsys.readouterr().err


def test_client_ping_names_the_endpoint() -> None:
    (nobody,) = free_endpoints(1)
    with MapperClient(query=nobody, timeout_s=60.0, retries=5) as client:
        with pytest.raises(NodeUnreachableError, match=f"no node answers at {nobody}") as info:
            client.ping(0.1)
    assert isinstance(info.value, TimeoutError) and info.value.endpoint == nobody


@pytest.mark.parametrize("value", ["-1", "nan", "x"])
def test_bad_ping_timeout_is_a_usage_error(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        query_cli.status_main(["--ping-timeout", value])
    assert exc.value.code == 2 and "--ping-timeout" in capsys.readouterr().err


def test_help_documents_the_ping(capsys: pytest.CaptureFixture[str]) -> None:
    for main in (query_cli.status_main, query_cli.query_main, render_cli.main):
        with pytest.raises(SystemExit):
            main(["--help"])
        assert "--ping-timeout" in capsys.readouterr().out
