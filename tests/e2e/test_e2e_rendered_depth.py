"""A real ``govnesf serve`` process with the committed checkpoint, fed frames WITHOUT depth: the
rendered-depth worker thread runs in the node process and puts points into the global map
(``status`` reports them), while every ack comes back at once (the worker never blocks ingest)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator

import pytest

from clients.client import MapperClient
from clients.harness import REPO_ROOT, NodeProcess, synthetic_frames

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not (REPO_ROOT / "checkpoints" / "cpu-small.json").exists(),
        reason="no trained checkpoint in checkpoints/",
    ),
]


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    root = tmp_path_factory.mktemp("e2e-rendered-depth")
    args = ["--set", "autosave_name=", "--set", "global_map.rendered_min_views=3",
            "--set", "global_map.rendered_min_opacity=0.0", "--set", "model.device=cpu"]
    with NodeProcess(root / "maps", log_path=root / "node.log", extra_args=args) as proc:
        proc.wait_ready(timeout_s=60.0)
        yield proc


def test_frames_without_depth_get_map_points_from_the_node_worker(node: NodeProcess) -> None:
    frames = [dataclasses.replace(f, depth_m=None) for f in synthetic_frames(12, 64, 48)]
    with node.client(timeout_s=30.0, retries=0) as client:
        assert isinstance(client, MapperClient)
        before = client.status()
        assert before.extra["rendered_depth"]["enabled"] is True
        assert before.extra["rendered_depth"]["integrated"] == 0
        acks = [r.reply for r in client.send_frames(iter(frames), window=4)]
        assert all(getattr(a, "status", None) in ("keyframe", "accepted") for a in acks), acks
        keyframes = sum(getattr(a, "status", None) == "keyframe" for a in acks)
        assert keyframes >= 3
        deadline = time.monotonic() + 60.0
        status = client.status()
        while status.extra["rendered_depth"]["integrated"] < keyframes and time.monotonic() < deadline:
            time.sleep(0.2)
            status = client.status()
        rd = status.extra["rendered_depth"]
        assert rd["integrated"] == keyframes and rd["failed"] == 0 and rd["pending"] == 0, rd
        assert rd["points"] > 0 and status.extra["global_points"] > 0  # no frame carried depth
