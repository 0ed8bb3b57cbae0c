"""End-to-end semantic mapping: the simulated robot streams a generated room into a real node
process; "find the chair", segment_points baselines, not_ready answers, autosave and a restart
after ``kill -9``. Small frames (80x60) and 40 keyframes keep the module around half a minute."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.client import MapperClient
from clients.harness import REPO_ROOT, NodeProcess, chair_distance, mean_iou, sim_stream
from protocol.messages import Error, Frame, Points

pytestmark = pytest.mark.slow

SEED = 3
N_PATH, STEP = 240, 6  # every 6th pose of a 240-frame loop: 40 frames around the whole room
W, H = 80, 60
NODE_ARGS = [
    "--set", "window.max_keyframes=60", "--set", "autosave_name=auto", "--set", "autosave_interval_s=1.0",
    "--set", "poll_interval_s=0.02",
]  # fmt: skip
TIMEOUT_S = 120.0  # generous: the node loads the text encoder on a shared, busy machine


@functools.lru_cache(maxsize=2)
def sim_frames(depth: bool = True) -> tuple[list[Frame], Any]:
    """Frames every STEP poses along the robot's loop, and the stream (scene, K, poses)."""
    stream = sim_stream(SEED, N_PATH, W, H, depth=depth)
    frames = [stream.frame(k, stream.render(k)) for k in range(0, N_PATH, STEP)]
    return frames, stream


def gt_points(n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    from clients.sim.scenes import LABEL_OF

    _, stream = sim_frames()
    xyz, label, _ = stream.scene.sample_surface(n, seed=1, exclude_labels=(LABEL_OF["ceiling"],))
    return xyz, label.astype(np.int64)


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    root = tmp_path_factory.mktemp("e2e_semantic")
    proc = NodeProcess(root / "maps", log_path=root / "node.log", extra_args=NODE_ARGS)
    with proc:
        proc.wait_ready()
        frames, _ = sim_frames()
        with proc.client(timeout_s=TIMEOUT_S) as client:
            replies = [r.reply for r in client.send_frames(frames, window=4)]
            # acked keyframes reach the global map shortly after their ack (the node's integrator)
            deadline = time.monotonic() + TIMEOUT_S
            while client.status().extra["integration"]["backlog"]:
                assert time.monotonic() < deadline, "the integrator's backlog did not drain"
                time.sleep(0.05)
        assert all(not isinstance(r, Error) and r.status != "rejected" for r in replies), replies
        yield proc


@pytest.fixture()
def client(node: NodeProcess) -> Iterator[MapperClient]:
    with node.client(timeout_s=TIMEOUT_S, retries=0) as c:
        yield c


def test_status_reports_the_global_map(client: MapperClient) -> None:
    status = client.status()
    extra = status.extra
    assert status.keyframes > 20 and status.ov_space == "minilm-l6-v2"
    assert extra["global_points"] > 1000 and extra["global_points_with_features"] == extra["global_points"]
    assert extra["global_map_bytes"] > extra["global_points"] * 384 * 2  # fp16 features at least
    assert status.memory_bytes >= extra["global_map_bytes"]
    assert {"query_points", "segment_points"} <= set(extra["serving"])
    assert extra["segment_methods"] == ["average", "average_depth", "govnesf"]
    assert "render" in extra["serving"] and extra["model"]["ready"], extra.get("model")


def test_find_the_chair_lies_within_half_a_metre_of_a_real_chair(client: MapperClient) -> None:
    _, stream = sim_frames()
    reply = client.query_points(["find the chair"])
    assert reply.map_version == client.status().map_version
    assert reply.xyz.shape[0] > 0 and reply.objects
    top = reply.objects[0]
    assert chair_distance(top.centroid, stream.scene) <= 0.5, top
    assert top.text == "find the chair" and np.all(reply.label == 0)
    assert {"encode_text", "score", "cluster", "total"} <= set(reply.timing_ms)


def test_segment_points_average_methods_against_ground_truth(client: MapperClient) -> None:
    from clients.sim.scenes import CLASS_NAMES

    xyz, gt = gt_points()
    far = np.array([[100.0, 100.0, 100.0]], np.float32)
    xyz = np.concatenate([xyz, far]).astype(np.float32)
    texts = list(CLASS_NAMES)
    scores = {}
    for method in ("average", "average_depth"):
        seg = client.segment_points(xyz, texts, method=method)
        assert seg.label.shape == (xyz.shape[0],) and seg.score.shape == (xyz.shape[0],)
        assert seg.label[-1] == -1 and seg.score[-1] == 0.0  # nobody sees the far point
        seen = seg.label[:-1] >= 0
        assert seen.mean() > 0.5
        assert np.all(seg.label < len(texts)) and np.all(np.abs(seg.score) <= 1.0 + 1e-5)
        miou, _ = mean_iou(seg.label[:-1][seen].astype(np.int64), gt[seen], len(texts))
        scores[method] = miou
    # 32 classes: chance is ~3%; the depth test removes occluded views and does better
    assert scores["average"] > 0.2 and scores["average_depth"] > scores["average"]


def test_govnesf_segmentation_and_render_with_the_committed_checkpoint(client: MapperClient) -> None:
    """The node loads checkpoints/cpu-small and serves learned blending (with and without DGM)."""
    from clients.sim.scenes import CLASS_NAMES

    xyz, gt = gt_points(1500)
    far = np.array([[100.0, 100.0, 100.0]], np.float32)
    xyz = np.concatenate([xyz, far]).astype(np.float32)
    texts = list(CLASS_NAMES)
    for use_depth in (False, True):
        seg = client.segment_points(xyz, texts, method="govnesf", use_depth=use_depth)
        assert seg.label.shape == (xyz.shape[0],) and seg.label[-1] == -1
        seen = seg.label[:-1] >= 0
        assert seen.mean() > 0.5 and np.all(np.isfinite(seg.score))
        miou, _ = mean_iou(seg.label[:-1][seen].astype(np.int64), gt[seen], len(texts))
        assert miou > 0.2, (use_depth, miou)  # 32 classes: chance is ~3%
    _, stream = sim_frames()
    pose = stream.poses[N_PATH // 2]
    reply = client.render(  # fmt: skip
        width=W,
        height=H,
        K=stream.K,
        world_from_cam=pose,
        outputs=["rgb", "depth", "label"],
        texts=["chair", "wall"],
    )
    assert reply.rgb is not None and reply.rgb.shape == (H, W, 3)
    assert reply.depth_m is not None and np.isfinite(reply.depth_m).all() and reply.depth_m.max() > 0
    assert reply.label is not None and set(np.unique(reply.label)) <= {-1, 0, 1}


def test_govnesf_query_cli_prints_objects_and_writes_ply_and_json(node: NodeProcess, tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), HF_HUB_OFFLINE="1")
    out = subprocess.run(
        [sys.executable, "-m", "clients.cli", "query", "find the chair", "--query", node.query,
         "--out", str(tmp_path / "chair.ply"), "--json", str(tmp_path / "chair.json"), "--top", "3"],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "find the chair" in out.stdout and "points matched" in out.stdout
    objects = json.loads((tmp_path / "chair.json").read_text())["objects"]
    assert objects and {"text", "centroid", "aabb_min", "aabb_max", "score", "n_points"} <= set(objects[0])
    o3d = pytest.importorskip("open3d", reason="the PLY is read back with Open3D")
    cloud = o3d.io.read_point_cloud(str(tmp_path / "chair.ply"))
    assert len(cloud.points) > 0 and cloud.has_colors()


def _same_answer(a: Points, b: Points) -> None:
    assert a.map_version == b.map_version
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_allclose(a.score, b.score, atol=1e-5)  # BLAS may round the last bit differently
    np.testing.assert_array_equal(a.label, b.label)
    assert [(o.text, o.n_points) for o in a.objects] == [(o.text, o.n_points) for o in b.objects]
    for oa, ob in zip(a.objects, b.objects, strict=True):
        np.testing.assert_allclose(oa.centroid, ob.centroid)


def test_kill_9_then_restart_serves_the_last_autosave(node: NodeProcess) -> None:
    """Runs last in this module: it kills the module's node."""
    with node.client(timeout_s=TIMEOUT_S, retries=0) as client:
        deadline = time.monotonic() + 30.0
        status = client.status()
        while (status.extra.get("last_save") or {}).get("map_version") != status.map_version:
            assert time.monotonic() < deadline, f"no autosave of version {status.map_version}: {status.extra}"
            time.sleep(0.2)
            status = client.status()
        answer = client.query_points(["chair", "table"])
    assert node.process is not None
    node.process.kill()  # SIGKILL: no final save, no cleanup
    node.process.wait(timeout=10)
    restarted = NodeProcess(node.map_dir, log_path=node.map_dir.parent / "node2.log", extra_args=NODE_ARGS)
    with restarted:
        restarted.wait_ready(timeout_s=60.0)
        with restarted.client(timeout_s=TIMEOUT_S, retries=0) as client:
            again = client.status()
            for key in ("map_version", "keyframes", "ov_space"):
                assert getattr(again, key) == getattr(status, key), key
            for key in ("global_points", "global_points_with_features", "ov_dim"):
                assert again.extra[key] == status.extra[key], key
            _same_answer(answer, client.query_points(["chair", "table"]))
    assert "start-up: loaded map 'auto'" in (node.map_dir.parent / "node2.log").read_text()
