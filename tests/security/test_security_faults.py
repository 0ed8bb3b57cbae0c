"""Faults: ``kill -9`` mid-stream and a restart with autosave (the client resends what was not
acked, nothing acked as a keyframe before the last save is lost, queries work after the restart),
disk full and an unwritable map directory on save (a clear error, the old map intact), a resent
frame that is already a keyframe is not added twice."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from clients.harness import REPO_ROOT, NodeProcess, synthetic_frame
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from mapper.node.store import MapStore
from protocol.messages import Ack, Error, Ok, Save, Status, StatusRequest, decode, encode

W, H = 48, 36


def _node(map_dir: Path) -> MapperNode:
    return MapperNode(
        config_from_dict({"map_dir": str(map_dir), "events_endpoint": "", "save_on_exit": False})
    )


def _ingest(node: MapperNode, seqs: range) -> None:
    for seq in seqs:
        reply = decode(node.handle_ingest(encode(synthetic_frame(seq, 60, W, H))), direction="reply")
        assert isinstance(reply, Ack), reply


def _save(node: MapperNode, name: str) -> Ok | Error:
    reply = decode(node.handle_query(encode(Save(name=name, id=1))), direction="reply")
    assert isinstance(reply, Ok | Error)
    return reply


def test_a_resent_keyframe_is_acked_again_not_added_twice(tmp_path: Path) -> None:
    node = _node(tmp_path / "maps")
    frame = encode(synthetic_frame(0, 60, W, H))
    first = decode(node.handle_ingest(frame), direction="reply")
    again = decode(node.handle_ingest(frame), direction="reply")
    assert isinstance(first, Ack) and isinstance(again, Ack)
    assert first.status == "keyframe" and again.status == "accepted"
    assert again.reason is not None and "duplicate" in again.reason
    assert again.map_version == first.map_version and len(node.state.window) == 1
    status = decode(node.handle_query(encode(StatusRequest())), direction="reply")
    assert isinstance(status, Status) and status.extra["frames_duplicate"] == 1


def _assert_old_map_intact(map_dir: Path, name: str, version: int) -> None:
    _, manifest = MapStore(map_dir).load(name)
    assert manifest["map_version"] == version
    assert [p.name for p in map_dir.iterdir() if p.name.endswith(".tmp")] == []


def test_unwritable_map_directory_gives_a_clear_error_and_keeps_the_old_map(tmp_path: Path) -> None:
    maps = tmp_path / "maps"
    node = _node(maps)
    _ingest(node, range(0, 30, 10))
    assert isinstance(_save(node, "kitchen"), Ok)
    saved_version = node.state.map_version
    _ingest(node, range(30, 60, 10))
    os.chmod(maps, stat.S_IRUSR | stat.S_IXUSR)
    immutable = False
    try:
        probe = maps / "probe"
        try:  # root ignores the mode bits: make the directory immutable instead, where allowed
            probe.touch()
            probe.unlink()
            immutable = subprocess.run(["chattr", "+i", str(maps)], capture_output=True).returncode == 0
            if not immutable:
                pytest.skip("cannot make a directory unwritable here (root without chattr)")
        except PermissionError:
            pass
        reply = _save(node, "kitchen")
        assert isinstance(reply, Error) and reply.code == "internal" and reply.id == 1
        assert "save failed on the node" in reply.message and "map directory" in reply.message
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(maps)], check=True)
        os.chmod(maps, stat.S_IRWXU)
    _assert_old_map_intact(maps, "kitchen", saved_version)
    assert node.state.map_version > saved_version  # the node itself is unchanged and serving
    assert isinstance(_save(node, "kitchen"), Ok)


DISK_FULL_SCRIPT = r"""
import json, os, resource, sys
sys.path.insert(0, sys.argv[2])
from tests.security.test_security_faults import _ingest, _node, _save
from pathlib import Path
maps = Path(sys.argv[1])
node = _node(maps)
_ingest(node, range(0, 30, 10))
first = _save(node, "kitchen")
size = (maps / "kitchen.govmap").stat().st_size
_ingest(node, range(30, 60, 10))
resource.setrlimit(resource.RLIMIT_FSIZE, (size // 2, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
second = _save(node, "kitchen")
print(json.dumps({"first": first.TYPE, "version": int(first.message.split()[3]), "second": second.TYPE,
                  "code": getattr(second, "code", None), "message": getattr(second, "message", None)}))
"""


def test_disk_full_on_save_gives_a_clear_error_and_keeps_the_old_map(tmp_path: Path) -> None:
    maps = tmp_path / "maps"
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    done = subprocess.run(
        [sys.executable, "-c", DISK_FULL_SCRIPT, str(maps), str(REPO_ROOT)],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    out: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["first"] == "ok" and out["second"] == "error" and out["code"] == "internal"
    assert "save failed on the node" in out["message"] and "File too large" in out["message"]
    _assert_old_map_intact(maps, "kitchen", out["version"])


@pytest.mark.slow
def test_kill_9_mid_stream_then_restart_loses_no_keyframe_acked_before_the_last_save(tmp_path: Path) -> None:
    maps = tmp_path / "maps"
    args = [
        "--set", "serve_model=false", "--set", "autosave_name=auto", "--set", "autosave_interval_s=0.5",
        "--set", "window.max_keyframes=500", "--set", "poll_interval_s=0.02",
    ]  # fmt: skip
    first = NodeProcess(maps, log_path=tmp_path / "node1.log", extra_args=args, events=False).start()
    second = NodeProcess(maps, log_path=tmp_path / "node2.log", extra_args=args, events=False)
    second.ingest, second.query, second.command = first.ingest, first.query, first.command
    n_frames, kill_after = 160, 60
    acked = threading.Event()
    saved: dict[str, Any] = {}

    def crash_and_restart() -> None:
        acked.wait(timeout=60)
        assert first.process is not None
        first.process.kill()  # SIGKILL: no final save, no clean shutdown
        first.process.wait(timeout=10)
        _, manifest = MapStore(maps).load("auto")  # the last autosave before the crash
        saved["version"] = manifest["map_version"]
        saved["seqs"] = [entry["seq"] for entry in manifest["keyframes"]]
        time.sleep(0.5)  # the client times out and retries meanwhile
        second.start()

    crasher = threading.Thread(target=crash_and_restart, daemon=True)
    try:
        first.wait_ready()
        time.sleep(0.6)  # let the node's main loop start its autosave clock
        crasher.start()
        results = []
        with first.client(timeout_s=1.0, retries=40) as client:
            frames = (synthetic_frame(seq, n_frames, W, H) for seq in range(n_frames))
            for result in client.send_frames(frames, window=4, rate_hz=40.0):
                results.append(result)
                if len(results) == kill_after:
                    acked.set()
            crasher.join(timeout=60)
            status = client.status()
            assert isinstance(client.save("after"), Ok)
        assert "version" in saved, "the crash did not happen"
        # the client resent what was not acked: every frame got exactly one answer, no error
        assert sorted(r.index for r in results) == list(range(n_frames))
        assert all(isinstance(r.reply, Ack) for r in results), [
            r.reply for r in results if isinstance(r.reply, Error)
        ]
        keyframes_before_save = {
            r.index
            for r in results
            if isinstance(r.reply, Ack)
            and r.reply.status == "keyframe"
            and r.reply.map_version <= saved["version"]
        }
        assert keyframes_before_save, "no keyframe was acked before the last save: nothing was tested"
        assert keyframes_before_save <= set(saved["seqs"])  # none lost
        # after the restart the node serves the saved keyframes and the ones streamed since
        _, after = MapStore(maps).load("after")
        after_seqs = [entry["seq"] for entry in after["keyframes"]]
        assert set(saved["seqs"]) <= set(after_seqs) and len(after_seqs) == len(set(after_seqs))
        assert status.map_version >= saved["version"] and status.keyframes == len(after_seqs)
        assert status.extra["global_points"] > 0
    finally:
        first.kill()
        second.kill()
        shutil.rmtree(maps, ignore_errors=True)
