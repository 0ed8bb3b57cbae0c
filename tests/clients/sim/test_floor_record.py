"""`govnesf sim record --floor-rooms`: a floor tour written as a recording that replays into a node."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from clients.harness import NodeProcess
from clients.sim.cli import main
from protocol.recording import read_recording


def test_sim_record_floor_writes_a_recording_that_replays(tmp_path: Path) -> None:
    out = tmp_path / "floor"
    assert main(["record", "--seed", "2", "--floor-rooms", "3", "--frames", "60", "--width", "32",
                 "--height", "24", "--depth", "--no-ov", "--novel-views", "2", "--points-per-m2", "20",
                 "--previews", "1", "--quiet", "--out", str(out)]) == 0
    rec = read_recording(out / "frames.govrec")
    frames = list(rec.frames())
    assert len(frames) == 60 and rec.header.meta["floor_rooms"] == 3
    assert rec.header.meta["path"] == "floor_tour"
    info = json.loads((out / "gt/scene.json").read_text())
    assert len(info["floor"]["rooms"]) == 3 and info["floor"]["visits"] == [0, 1, 2, 0, 1]
    gt = np.load(out / "gt/stream.npz", allow_pickle=False)
    assert set(gt["room"].tolist()) >= {0, 1, 2}
    assert all(f.depth_m is not None and (f.depth_m > 0).mean() > 0.9 for f in frames)
    from clients.replay import replay

    with NodeProcess(tmp_path / "maps", extra_args=["--set", "serve_model=false"]) as node:
        node.wait_ready(timeout_s=120.0)
        with node.client(timeout_s=60.0, retries=0) as client:
            summary = replay(out / "frames.govrec", client, progress=False)
            st = client.status()
    assert summary.sent == 60 and sum(summary.statuses.values()) == 60 and summary.statuses["rejected"] == 0
    assert st.extra["global_points"] > 1000


def test_sim_record_refuses_a_bad_floor(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cases = ((["--floor-rooms", "31"], "floor_rooms 31 out of range 2..30"),
             (["--floor-rooms", "3", "--path", "sparse"], "path 'sparse' unknown for a floor"),
             (["--floor-rooms", "3", "--revisit-rooms", "4"], "revisit_rooms 4 out of range 0..3"),
             (["--path", "floor_tour"], "path 'floor_tour' unknown for a room"))
    for bad, message in cases:
        assert main(["record", "--seed", "0", "--frames", "60", "--out", str(tmp_path / "x"), *bad]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
