"""`govnesf sim record / stream`: the recording, the ground truth export and streaming to a node."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
import zmq

from clients.sim.cli import main
from clients.sim.export import RecordConfig, SimStream, count_views, record
from clients.sim.scenes import CLASS_NAMES
from protocol.messages import Ack, Frame, decode, encode
from protocol.recording import read_recording

W, H, N = 48, 36, 6


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "rec"
    cfg = RecordConfig(seed=3, frames=N, width=W, height=H, depth=True, ov=False, novel_views=3,
                       points_per_m2=60.0, previews=2)
    summary = record(cfg, out, progress=False)
    assert summary.frames == N and summary.gt_points > 1000
    return out


def test_layout(export_dir: Path) -> None:
    for rel in ("frames.govrec", "scene.ply", "gt/class_names.json", "gt/scene.json", "gt/mesh.npz",
                "gt/points.npz", "gt/stream.npz", "gt/novel_views.npz", "preview/top_down.png"):
        assert (export_dir / rel).is_file(), rel
    assert len(list((export_dir / "preview").glob("frame_*.png"))) == 2
    assert json.loads((export_dir / "gt/class_names.json").read_text()) == list(CLASS_NAMES)
    info = json.loads((export_dir / "gt/scene.json").read_text())
    assert info["seed"] == 3 and info["style"] == "apartment" and len(info["instances"]) > 5


def test_recording_matches_ground_truth(export_dir: Path) -> None:
    rec = read_recording(export_dir / "frames.govrec")
    frames = list(rec.frames())
    assert not rec.truncated and len(frames) == N
    assert rec.header.meta["seed"] == 3 and rec.header.meta["class_names"] == list(CLASS_NAMES)
    gt = np.load(export_dir / "gt/stream.npz", allow_pickle=False)
    stream = SimStream.build(RecordConfig(seed=3, frames=N, width=W, height=H, ov=False))
    for k, f in enumerate(frames):
        assert f.seq == k and (f.width, f.height) == (W, H)
        assert f.ov is None and f.ov_space is None
        np.testing.assert_allclose(f.K, gt["K"][k])
        np.testing.assert_allclose(f.world_from_cam, gt["world_from_cam"][k])
        np.testing.assert_array_equal(f.depth_m, gt["depth_m"][k])
        view = stream.render(k)  # the export is reproducible from (seed, style, size)
        np.testing.assert_array_equal(f.rgb, view.rgb)
        np.testing.assert_array_equal(gt["label"][k], view.label)
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps) and stamps[1] - stamps[0] == 100_000_000


def test_points_and_novel_views(export_dir: Path) -> None:
    pts = np.load(export_dir / "gt/points.npz", allow_pickle=False)
    assert pts["xyz"].dtype == np.float32 and pts["label"].dtype == np.int32
    assert len(pts["xyz"]) == len(pts["label"]) == len(pts["n_views"]) == len(pts["instance"])
    assert CLASS_NAMES.index("ceiling") not in set(pts["label"].tolist())
    assert 0.02 < (pts["n_views"] > 0).mean() < 1.0 and pts["n_views"].max() <= N
    nv = np.load(export_dir / "gt/novel_views.npz", allow_pickle=False)
    stream_poses = np.load(export_dir / "gt/stream.npz")["world_from_cam"]
    assert nv["rgb"].shape == (3, H, W, 3) and nv["label"].shape == (3, H, W)
    for pose, idx in zip(nv["world_from_cam"], nv["stream_index"], strict=True):
        assert 0 <= idx < N
        diff = np.abs(stream_poses - pose).reshape(N, -1).max(1)
        assert diff.min() > 1e-3  # not a stream frame
        assert np.linalg.norm(pose[:3, 3] - stream_poses[idx][:3, 3]) < 0.4  # but near the path


def test_count_views_depth_test() -> None:
    K = np.array([10.0, 10.0, 5.0, 5.0])
    pose = np.eye(4)                     # camera at the origin looking along world +z
    depth = np.full((10, 10), 2.0, np.float32)
    xyz = np.array([[0.0, 0.0, 2.0],     # on the surface: seen
                    [0.0, 0.0, 3.0],     # behind it: occluded
                    [0.0, 0.0, -2.0],    # behind the camera
                    [5.0, 0.0, 2.0]])    # outside the image
    counts = np.zeros(4, np.int32)
    count_views(xyz, K, pose, depth, counts)
    np.testing.assert_array_equal(counts, [1, 0, 0, 0])


@pytest.mark.slow  # loads the real text encoder (a few seconds, more on a loaded machine)
def test_cli_record_with_ov(tmp_path: Path) -> None:
    out = tmp_path / "ov"
    rc = main(["record", "--seed", "1", "--frames", "2", "--width", "32", "--height", "24", "--out", str(out),
               "--novel-views", "0", "--previews", "0", "--points-per-m2", "20", "--quiet"])
    assert rc == 0
    frames = list(read_recording(out / "frames.govrec").frames())
    assert len(frames) == 2 and frames[0].depth_m is None
    assert frames[0].ov_space == "minilm-l6-v2" and frames[0].ov.dtype == np.float16
    assert frames[0].ov.ndim == 3 and frames[0].ov.shape[2] == 384
    assert not (out / "gt/novel_views.npz").exists()


def test_cli_rejects_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["record", "--seed", "0", "--frames", "0", "--out", str(tmp_path / "a"), "--no-ov"]) == 2
    assert "frames 0 out of range" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x").write_text("keep me")
    assert main(["record", "--seed", "0", "--frames", "2", "--out", str(tmp_path / "b"), "--no-ov"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "b" / "x").read_text() == "keep me"


@pytest.mark.parametrize("robot,pose_error", [("", "exact"), ("r2", "noise_3cm")])
def test_cli_stream_sends_frames_and_waits_for_acks(robot: str, pose_error: str) -> None:
    ctx = zmq.Context.instance()
    router = ctx.socket(zmq.ROUTER)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    received: list[Frame] = []

    def serve() -> None:
        while len(received) < 3 and router.poll(10_000):
            *envelope, payload = router.recv_multipart()  # identity (+ empty delimiter), message
            frame = decode(payload)
            assert isinstance(frame, Frame)
            received.append(frame)
            status = "keyframe" if frame.seq == 0 else "accepted"
            reply = Ack(seq=frame.seq, status=status, map_version=frame.seq, id=frame.id)
            router.send_multipart([*envelope, encode(reply)])

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        rc = main(["stream", "--seed", "2", "--frames", "3", "--width", "32", "--height", "24", "--no-ov",
                   "--depth", "--ingest", f"tcp://127.0.0.1:{port}", "--rate", "0", "--quiet",
                   "--pose-error", pose_error, *(["--robot", robot] if robot else [])])
    finally:
        t.join(timeout=15)
        router.close(linger=0)
    assert rc == 0
    assert [f.seq for f in received] == [0, 1, 2]
    assert all(f.depth_m is not None and f.ov is None and f.robot == robot for f in received)
    from clients.sim.export import RecordConfig, SimStream
    from clients.sim.sensor import perturb_poses

    true = SimStream.build(RecordConfig(seed=2, frames=3, width=32, height=24, depth=True, ov=False,
                                        novel_views=0, previews=0)).poses
    sent = np.stack([f.world_from_cam for f in received])
    np.testing.assert_allclose(sent, perturb_poses(true, pose_error, seed=2))  # odometry's poses went out
    assert (pose_error == "exact") == bool(np.allclose(sent, true))


def test_cli_stream_rejects_bad_endpoint(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["stream", "--seed", "0", "--frames", "2", "--no-ov", "--ingest", "localhost:5555"]) == 2
    assert "not a ZeroMQ endpoint" in capsys.readouterr().err
    assert main(["stream", "--seed", "0", "--frames", "2", "--no-ov", "--robot", "a b"]) == 2
    assert "not a robot name" in capsys.readouterr().err
