"""Live Rerun viewing (``--rerun-connect ADDR``, clients/rerun_log.py).

The live path is tested against a real Rerun gRPC server: the ``rerun`` command installed with
rerun-sdk, run as ``rerun --serve-grpc --port P --save F.rrd`` (the proxy a viewer would connect
to, without a display; ``--save`` streams what it receives to a file). The test sends a query
answer through ``govnesf query --rerun-connect`` (against a scripted query endpoint) and reads the
server's file back: the same entities and points as the ``--rerun`` file of the same command.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from clients.cli import query as query_cli
from clients.harness import free_endpoints
from clients.rerun_log import RerunLog, RerunLogError, check_connect_addr
from protocol.messages import ObjectCandidate, Points
from tests.clients.test_ply import ScriptedQueryNode
from tests.clients.test_rerun_log import read_rrd


def _free_port() -> int:
    return int(free_endpoints(1)[0].rsplit(":", 1)[1])


@pytest.mark.parametrize(
    ("addr", "url"),
    [
        ("9876", "rerun+http://127.0.0.1:9876/proxy"),
        ("viewer.local:9000", "rerun+http://viewer.local:9000/proxy"),
        ("[::1]:9000", "rerun+http://[::1]:9000/proxy"),
        ("rerun+http://10.0.0.5:9876/proxy", "rerun+http://10.0.0.5:9876/proxy"),
        ("rerun+https://example.org:443/proxy", "rerun+https://example.org:443/proxy"),
        ("rerun://127.0.0.1:9876/proxy", "rerun://127.0.0.1:9876/proxy"),
    ],
)
def test_addresses_become_grpc_urls(addr: str, url: str) -> None:
    assert check_connect_addr(addr, probe=False) == url


@pytest.mark.parametrize(
    ("addr", "fragment"),
    [
        ("", "expected PORT, HOST:PORT"),
        ("http://127.0.0.1:9876/proxy", "expected PORT, HOST:PORT"),
        ("rerun+http://127.0.0.1:9876", "expected PORT, HOST:PORT"),
        ("127.0.0.1", "expected PORT, HOST:PORT"),
        ("127.0.0.1:99999", "port 99999 is not in 1..65535"),
        ("0", "port 0 is not in 1..65535"),
    ],
)
def test_malformed_addresses_are_refused(addr: str, fragment: str) -> None:
    with pytest.raises(RerunLogError, match=fragment):
        check_connect_addr(addr, probe=False)


def test_no_viewer_is_an_error_before_any_work(capsys: pytest.CaptureFixture[str]) -> None:
    port = _free_port()  # nothing listens there
    with pytest.raises(RerunLogError, match=f"no Rerun viewer answers at 127.0.0.1:{port}"):
        check_connect_addr(str(port))
    with pytest.raises(RerunLogError, match="needs a file path, a viewer address"):
        RerunLog()
    (nobody,) = free_endpoints(1)  # no node either: a request sent would time out instead
    with pytest.raises(SystemExit) as exc:
        query_cli.query_main(["chair", "--query", nobody, "--rerun-connect", f"127.0.0.1:{port}"])
    assert exc.value.code == 2 and "no Rerun viewer answers" in capsys.readouterr().err


def test_rerun_env_off_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RERUN", "off")
    with pytest.raises(RerunLogError, match="RERUN=off"):
        check_connect_addr("9876", probe=False)


@pytest.fixture()
def grpc_server(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """``rerun --serve-grpc`` on a free port saving what it receives to a file; yields (addr, file)."""
    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if exe is None:
        pytest.skip("the `rerun` command of rerun-sdk is not installed")
    port = _free_port()
    saved = tmp_path / "received.rrd"
    env = {**os.environ, "RERUN_APP_ONLY": "true"}  # as rerun's own spawn: no analytics opt-in prompt
    proc = subprocess.Popen(
        [exe, "--serve-grpc", "--bind", "127.0.0.1", "--port", str(port), "--save", str(saved)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
        start_new_session=True,  # `rerun` may be a launcher whose server is a child: stop the group
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 20.0
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
                    pytest.fail(f"rerun --serve-grpc did not start on port {port}: {err[-2000:]}")
                time.sleep(0.1)
        yield f"127.0.0.1:{port}", saved
    finally:
        # the server finishes its --save file on SIGTERM; the whole group, so that a server the
        # launcher started does not outlive the test (it used to, reparented to init)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # the server's file is still open
def test_query_streams_live_and_to_file(
    grpc_server: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    addr, saved = grpc_server
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-1, 1, (30, 3)).astype(np.float32)
    score = np.linspace(0.2, 0.6, 30).astype(np.float32)
    obj = ObjectCandidate(text="chair", centroid=xyz.mean(0), aabb_min=xyz.min(0), aabb_max=xyz.max(0),
                          score=0.6, n_points=30)  # fmt: skip
    server = ScriptedQueryNode(Points(map_version=5, xyz=xyz, score=score, label=np.zeros(30, np.int32),
                                      objects=[obj]))  # fmt: skip
    rrd = tmp_path / "chair.rrd"
    try:
        code = query_cli.query_main(["chair", "--query", server.endpoint, "--timeout", "10",
                                     "--rerun", str(rrd), "--rerun-connect", addr])  # fmt: skip
    finally:
        server.close()
    assert code == 0
    out = capsys.readouterr().out
    assert f"wrote {rrd}" in out and f"sent to the Rerun viewer at rerun+http://{addr}/proxy" in out
    # the server writes its file as data arrives; stopping it (fixture) is not needed to read it
    deadline = time.monotonic() + 10.0
    live: dict = {}
    while time.monotonic() < deadline:
        if saved.is_file() and saved.stat().st_size > 0:
            live = read_rrd(saved)
            if "/world/query/points" in live:
                break
        time.sleep(0.2)
    from_file = read_rrd(rrd)
    assert "/world/query/points" in live, sorted(live)
    for entity in ("/world", "/world/query/points", "/world/query/objects", "/world/query/centroids"):
        assert entity in live and entity in from_file
    np.testing.assert_allclose(live["/world/query/points"]["Points3D:positions"][0], xyz)
    assert (live["/world/query/points"]["Points3D:positions"]
            == from_file["/world/query/points"]["Points3D:positions"])  # fmt: skip
    assert live["/world/query/points"]["map_version"] == [5]


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_render_streams_live_without_a_file(
    grpc_server: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from clients.cli import render as render_cli
    from protocol.messages import RenderResult
    from tests.clients.test_rerun_log import ScriptedRenderNode

    addr, saved = grpc_server
    h, w = 6, 8
    rgb = np.arange(h * w * 3, dtype=np.uint8).reshape(h, w, 3)
    server = ScriptedRenderNode(RenderResult(rgb=rgb, depth_m=np.full((h, w), 2.0, np.float32)))
    try:
        code = render_cli.main(["--pose", "0,0,1,0,0", "--width", str(w), "--height", str(h),
                                "--out", str(tmp_path / "v.png"), "--query", server.endpoint,
                                "--timeout", "10", "--rerun-connect", addr])  # fmt: skip
    finally:
        server.close()
    assert code == 0
    assert f"the Rerun viewer at rerun+http://{addr}/proxy" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".rrd") == ["received.rrd"]
    deadline = time.monotonic() + 10.0
    live: dict = {}
    while time.monotonic() < deadline and "/world/render/image/rgb" not in live:
        time.sleep(0.2)
        live = read_rrd(saved) if saved.is_file() and saved.stat().st_size else {}
    assert bytes(live["/world/render/image/rgb"]["Image:buffer"][0][0]) == rgb.tobytes()
