"""``--rerun FILE.rrd`` logging (clients/rerun_log.py): every test writes a real ``.rrd`` and reads
it back with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41), checking entity paths and their data.

The CLI paths run against a real ``govnesf serve`` process (``clients.harness.NodeProcess``, as in
tests/e2e) fed with the demo's synthetic checkerboard frames (``demo-checker`` features: one-hot
sky / dark / light cells). That process registers a text encoder for the ``demo-checker`` space
before it serves (the built-in MiniLM encoder takes longer to load than a test may run), so
``govnesf query dark`` is answered by the node's real global map, scoring, clustering and wire
reply. ``govnesf render`` needs the learned model, so its CLI path runs against a scripted query
endpoint instead.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest

from clients import replay
from clients.cli import query as client_cli
from clients.cli import render as render_cli
from clients.harness import (
    DEMO_OV_DIM,
    DEMO_OV_SPACE,
    REPO_ROOT,
    NodeProcess,
    free_endpoints,
    synthetic_frame,
    write_synthetic_recording,
)
from clients.rerun_log import APPLICATION_ID, RERUN_PIN, RerunLog, RerunLogError, check_rrd_path
from protocol.messages import ObjectCandidate, Points, Render, RenderResult
from tests.node_helpers import ScriptedQueryEndpoint

W, H = 96, 72
N_FRAMES = 12

# ---------------------------------------------------------------------------------------------
# reading an .rrd back


def read_rrd(path: Path) -> dict[str, dict[str, list[Any]]]:
    """entity path -> column name -> one value per logged row (timestamps as int ns), over all
    chunks of the file's only recording, which must be a "govnesf" recording."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    recordings = reader.recordings()
    assert len(recordings) == 1 and recordings[0].application_id == APPLICATION_ID, recordings
    out: dict[str, dict[str, list[Any]]] = {}
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        columns = out.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            col = batch.column(name)
            if pa.types.is_timestamp(col.type):
                col = col.cast(pa.int64())
            columns.setdefault(name, []).extend(col.to_pylist())
    return out


def by_frame(columns: dict[str, list[Any]], name: str) -> list[Any]:
    """Column ``name`` in ``frame`` order."""
    order = np.argsort(columns["frame"], kind="stable")
    return [columns[name][i] for i in order]


def col_major(m: np.ndarray) -> list[float]:
    """How Rerun stores a 3x3 matrix: column-major."""
    return [float(v) for v in np.asarray(m, np.float32).T.ravel()]


def view_dirs(name: str) -> list[int]:
    import rerun as rr

    return [int(d.value) for d in getattr(rr.ViewCoordinates, name).coordinates]


def row_of(columns: dict[str, list[Any]], frame: int | None) -> int:
    """The row logged at ``frame`` on the frame timeline (None: the only row)."""
    if frame is None:
        assert len(columns["rerun.controls.RowId"]) == 1
        return 0
    return columns["frame"].index(frame)


def assert_camera(
    data: dict[str, dict[str, list[Any]]], entity: str, K: np.ndarray, world_from_cam: np.ndarray,
    width: int, height: int, frame: int | None = None,
) -> None:  # fmt: skip
    """The camera at ``entity``: pose = world_from_cam, pinhole = K, size, OpenCV optical axes."""
    pose = data[entity]
    row = row_of(pose, frame)
    assert np.allclose(pose["Transform3D:translation"][row][0], world_from_cam[:3, 3], atol=1e-6)
    assert np.allclose(pose["Transform3D:mat3x3"][row][0], col_major(world_from_cam[:3, :3]), atol=1e-6)
    pinhole = data[f"{entity}/image"]
    row = row_of(pinhole, frame)
    fx, fy, cx, cy = K
    assert np.allclose(pinhole["Pinhole:image_from_camera"][row][0], col_major(
        np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])), atol=1e-4)  # fmt: skip
    assert pinhole["Pinhole:resolution"][row][0] == [width, height]
    assert pinhole["Pinhole:camera_xyz"][row][0] == view_dirs("RDF")  # OpenCV optical (conventions.md)


def context_labels(columns: dict[str, list[Any]]) -> list[str]:
    """Class labels of the (one) annotation context logged at an entity, by class id."""
    (context,) = [row[0] for row in columns["AnnotationContext:context"] if row is not None]
    return [c["class_description"]["info"]["label"] for c in sorted(context, key=lambda c: c["class_id"])]


def image_bytes(columns: dict[str, list[Any]], kind: str, row: int) -> bytes:
    return bytes(columns[f"{kind}:buffer"][row][0])


# ---------------------------------------------------------------------------------------------
# the functions


def _points(n: int = 40) -> Points:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    score = np.linspace(0.2, 0.8, n).astype(np.float32)
    label = (np.arange(n) % 2).astype(np.int32)
    objects = [
        ObjectCandidate(text=t, centroid=xyz[label == i].mean(0), aabb_min=xyz[label == i].min(0),
                        aabb_max=xyz[label == i].max(0), score=0.7 - 0.1 * i,
                        n_points=int((label == i).sum()))
        for i, t in enumerate(["chair", "table"])
    ]  # fmt: skip
    return Points(map_version=7, xyz=xyz, score=score, label=label, objects=objects)


def test_functions_write_frames_query_map_and_render(tmp_path: Path) -> None:
    path = tmp_path / "all.rrd"
    frames = [synthetic_frame(seq, N_FRAMES, W, H) for seq in (0, 5)]
    frames[1].depth_m = None  # a frame without depth logs no depth image
    points = _points()
    K = np.array([50.0, 50.0, 16.0, 12.0])
    pose = frames[0].world_from_cam
    render = RenderResult(
        rgb=np.full((24, 32, 3), 9, np.uint8), depth_m=np.full((24, 32), 2.5, np.float32),
        label=np.where(np.arange(32) < 16, 1, -1).astype(np.int32)[None].repeat(24, 0),
    )  # fmt: skip
    with RerunLog(path) as rlog:
        for frame in frames:
            rlog.log_frame(frame)
        rlog.log_query(points, ["chair", "table"])
        rlog.log_map(points, ["chair", "table"])
        rlog.log_render(render, K, pose, ["chair", "table"])
    assert rlog.closed and rlog.frames_logged == 2
    rerun_cli = Path(sys.executable).with_name("rerun")  # installed with rerun-sdk
    verify = subprocess.run([str(rerun_cli), "rrd", "verify", str(path)], capture_output=True, text=True,
                            timeout=60)  # fmt: skip
    assert verify.returncode == 0, verify.stderr  # a complete, loadable file
    data = read_rrd(path)

    assert data["/world"]["ViewCoordinates:xyz"] == [[view_dirs("RIGHT_HAND_Z_UP")]]  # world +z up
    cam = "/world/cameras/cam0"
    for frame in frames:
        assert_camera(data, cam, frame.K, frame.world_from_cam, W, H, frame.seq)
    stamps = sorted(zip(data[cam]["frame"], data[cam]["stamp"], strict=True))
    assert stamps == [(f.seq, f.stamp_ns) for f in frames]
    rgb = data[f"{cam}/image/rgb"]
    assert by_frame(rgb, "frame") == [0, 5]
    assert [bytes(b[0]) for b in by_frame(rgb, "Image:buffer")] == [f.rgb.tobytes() for f in frames]
    depth = data[f"{cam}/image/depth"]
    assert depth["frame"] == [0]  # only the frame with depth
    assert image_bytes(depth, "DepthImage", 0) == frames[0].depth_m.astype(np.float32).tobytes()
    assert depth["DepthImage:meter"] == [[1.0]]

    q = data["/world/query/points"]
    assert np.allclose(q["Points3D:positions"][0], points.xyz)
    assert q["Points3D:class_ids"][0] == (points.label + 1).tolist()
    colours = np.array(q["Points3D:colors"][0], np.uint32)
    assert len(colours) == 40 and len(set(colours.tolist())) > 10  # coloured by score, not one colour
    assert q["map_version"] == [7]
    boxes = data["/world/query/objects"]
    assert len(boxes["Boxes3D:centers"][0]) == 2
    for o, centre, half in zip(points.objects, boxes["Boxes3D:centers"][0], boxes["Boxes3D:half_sizes"][0],
                               strict=True):  # fmt: skip
        assert np.allclose(centre, (o.aabb_min + o.aabb_max) / 2, atol=1e-6)
        assert np.allclose(half, (o.aabb_max - o.aabb_min) / 2, atol=1e-6)
    assert boxes["Boxes3D:labels"][0] == ["chair 0.70 (20 pts)", "table 0.60 (20 pts)"]
    centroids = data["/world/query/centroids"]["Points3D:positions"][0]
    assert np.allclose(centroids, [o.centroid for o in points.objects])
    assert context_labels(data["/world/query"]) == ["nothing", "chair", "table"]

    m = data["/world/map"]
    assert len(m["Points3D:positions"][0]) == 40 and m["Points3D:class_ids"][0] == (points.label + 1).tolist()

    assert_camera(data, "/world/render", K, pose, 32, 24)
    r = data["/world/render/image/rgb"]
    assert image_bytes(r, "Image", 0) == render.rgb.tobytes()
    label = np.frombuffer(image_bytes(data["/world/render/image/label"], "SegmentationImage", 0), np.uint16)
    assert np.array_equal(label, (render.label + 1).ravel())  # -1 (nothing) -> class id 0
    assert "/world/render/image/depth" in data


def test_bad_shapes_are_errors(tmp_path: Path) -> None:
    with RerunLog(tmp_path / "x.rrd") as rlog:
        with pytest.raises(ValueError, match=r"rgb: expected shape \(4, 6, 3\)"):
            rlog.log_camera("world/c", np.ones(4), np.eye(4), 6, 4, rgb=np.zeros((6, 4, 3), np.uint8))
        with pytest.raises(ValueError, match=r"K: expected shape \(4,\)"):
            rlog.log_camera("world/c", np.ones(3), np.eye(4), 6, 4)
        with pytest.raises(ValueError, match="xyz"):
            rlog.log_points("world/p", np.zeros((5, 2)))


# ---------------------------------------------------------------------------------------------
# bad paths and a missing package: clear errors, nothing written, before any work


@pytest.mark.parametrize(
    ("name", "fragment"),
    [
        ("missing/out.rrd", "does not exist"),
        ("afile/out.rrd", "is not a directory"),
        ("adir", "must end in .rrd"),
        ("adir.rrd", "is a directory"),
        ("out.txt", "must end in .rrd"),
    ],
)
def test_bad_paths_are_refused_and_change_nothing(tmp_path: Path, name: str, fragment: str) -> None:
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir.rrd").mkdir()
    before = sorted(p.name for p in tmp_path.rglob("*"))
    with pytest.raises(RerunLogError, match=fragment):
        check_rrd_path(tmp_path / name)
    with pytest.raises(RerunLogError, match=fragment):
        RerunLog(tmp_path / name)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_clis_refuse_a_bad_path_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = str(tmp_path / "missing" / "x.rrd")
    (nobody,) = free_endpoints(1)  # nothing listens: any attempt to send would time out instead
    with pytest.raises(SystemExit) as exc:
        client_cli.query_main(["chair", "--query", nobody, "--rerun", bad])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err
    assert render_cli.main(["--pose", "0,0,1,0,0", "--query", nobody, "--out", str(tmp_path / "v.png"),
                            "--rerun", bad]) == 2  # fmt: skip
    assert "does not exist" in capsys.readouterr().err
    recording = write_synthetic_recording(tmp_path / "r.govrec", 2, 16, 12)
    with pytest.raises(SystemExit) as exc:
        replay.main([str(recording), "--ingest", nobody, "--no-progress", "--rerun", bad])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err
    from clients import demo

    with pytest.raises(SystemExit) as exc:
        demo.main(["--out", str(tmp_path / "demo"), "--rerun", bad])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.govrec"]  # no PNG, no demo dir, no .rrd


def test_missing_package_names_the_pin(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # makes `import rerun` raise ImportError
    with pytest.raises(RerunLogError, match=RERUN_PIN.replace(".", r"\.")):
        check_rrd_path(tmp_path / "x.rrd")


def test_rerun_env_off_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("RERUN", "off")
    with pytest.raises(RerunLogError, match="RERUN=off"):
        check_rrd_path(tmp_path / "x.rrd")


def test_no_module_imports_rerun_at_import_time() -> None:
    code = ("import sys, clients.cli, clients.cli.query, clients.cli.render, clients.replay, "
            "clients.demo, clients.rerun_log; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'rerun'))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True,
                         timeout=60, env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


# ---------------------------------------------------------------------------------------------
# CLI paths against a real node process

NODE_MAIN = f"""
import sys
import numpy as np
from mapper.ov.encoders import register_text_encoder

class CheckerTextEncoder:
    '''Texts of the {DEMO_OV_SPACE!r} space: sky, dark, light -> its one-hot feature axes; any
    other text -> one of the remaining axes (no feature of the frames points there).'''
    space = {DEMO_OV_SPACE!r}
    dim = {DEMO_OV_DIM}

    def encode(self, texts):
        out = np.zeros((len(texts), self.dim), np.float32)
        for row, text in enumerate(texts):
            axis = {{"sky": 0, "dark": 1, "light": 2}}.get(text, 3 + sum(text.encode()) % (self.dim - 3))
            out[row, axis] = 1.0
        return out

register_text_encoder({DEMO_OV_SPACE!r}, CheckerTextEncoder)
from clients.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    root = tmp_path_factory.mktemp("rerun_node")
    proc = NodeProcess(root / "maps", log_path=root / "node.log", extra_args=["--set", "serve_model=false"])
    assert proc.command[1:3] == ["-m", "clients.cli"]
    proc.command[1:3] = ["-c", NODE_MAIN]  # the same `govnesf serve`, with the checker encoder registered
    with proc:
        proc.wait_ready()
        with proc.client(timeout_s=30.0) as client:
            replies = [r.reply for r in client.send_frames(
                (synthetic_frame(seq, N_FRAMES, W, H) for seq in range(N_FRAMES)), window=4)]  # fmt: skip
        assert all(getattr(r, "status", None) in ("keyframe", "accepted") for r in replies), replies
        yield proc


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    return subprocess.run([sys.executable, "-m", "clients.cli", *args], cwd=REPO_ROOT, env=env,
                          capture_output=True, text=True, timeout=60)  # fmt: skip


def test_query_cli_logs_points_and_objects(node: NodeProcess, tmp_path: Path) -> None:
    rrd, js = tmp_path / "dark.rrd", tmp_path / "dark.json"
    out = _cli("query", "dark", "--negatives", "light", "sky", "--query", node.query,
               "--json", str(js), "--rerun", str(rrd))  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert f"wrote {rrd}" in out.stdout
    answer = json.loads(js.read_text())
    assert answer["n_points"] > 100 and len(answer["objects"]) >= 1, answer  # the dark squares
    data = read_rrd(rrd)
    points = data["/world/query/points"]
    assert len(points["Points3D:positions"][0]) == answer["n_points"]
    assert set(points["Points3D:class_ids"][0]) == {1}  # every point labelled "dark"
    assert points["map_version"] == [answer["map_version"]]
    boxes = data["/world/query/objects"]
    assert len(boxes["Boxes3D:centers"][0]) == len(answer["objects"])
    for obj, centre, label in zip(answer["objects"], boxes["Boxes3D:centers"][0], boxes["Boxes3D:labels"][0],
                                  strict=True):  # fmt: skip
        assert np.allclose(centre, (np.array(obj["aabb_min"]) + obj["aabb_max"]) / 2, atol=1e-3)
        assert label == f"dark {obj['score']:.2f} ({obj['n_points']} pts)"
    centroids = data["/world/query/centroids"]["Points3D:positions"][0]
    assert np.allclose(centroids, [o["centroid"] for o in answer["objects"]], atol=1e-3)
    # every matching point lies on the checkerboard floor (z = 0) within the map's 5 cm voxels
    assert np.abs(np.array(points["Points3D:positions"][0])[:, 2]).max() < 0.05


def test_replay_cli_logs_every_nth_frame(node: NodeProcess, tmp_path: Path) -> None:
    recording = write_synthetic_recording(tmp_path / "r.govrec", 5, W, H)
    rrd = tmp_path / "replay.rrd"
    code = replay.main([str(recording), "--ingest", node.ingest, "--no-progress", "--rerun", str(rrd),
                        "--rerun-every", "2"])  # fmt: skip
    assert code == 0
    data = read_rrd(rrd)
    cam = "/world/cameras/cam0"
    assert sorted(data[cam]["frame"]) == [0, 2, 4]
    frames = [synthetic_frame(seq, 5, W, H) for seq in (0, 2, 4)]
    for frame in frames:
        assert_camera(data, cam, frame.K, frame.world_from_cam, W, H, frame.seq)
    rgb = data[f"{cam}/image/rgb"]
    assert [bytes(b[0]) for b in by_frame(rgb, "Image:buffer")] == [f.rgb.tobytes() for f in frames]
    depth = data[f"{cam}/image/depth"]
    assert [bytes(b[0]) for b in by_frame(depth, "DepthImage:buffer")] == [
        f.depth_m.astype(np.float32).tobytes() for f in frames if f.depth_m is not None
    ]


class ScriptedRenderNode(ScriptedQueryEndpoint[Render]):
    """A query endpoint on a free TCP port that answers ``render`` requests with a fixed image
    (the learned model is too slow to load for a unit test); records the requests."""

    def __init__(self, result: RenderResult) -> None:
        super().__init__(Render, result)


def test_render_cli_logs_the_view_and_its_camera(tmp_path: Path) -> None:
    h, w = 12, 16
    label = (np.arange(w)[None].repeat(h, 0) // 6 - 1).astype(np.int32)  # -1, 0, 1
    result = RenderResult(
        rgb=np.arange(h * w * 3, dtype=np.uint8).reshape(h, w, 3), depth_m=np.full((h, w), 1.5, np.float32),
        label=label, score=np.zeros((h, w, 2), np.float32),
    )  # fmt: skip
    server = ScriptedRenderNode(result)
    rrd = tmp_path / "view.rrd"
    try:
        code = render_cli.main([
            "--pose", "1.0,2.0,1.3,90,-10", "--width", str(w), "--height", str(h),
            "--texts", "chair", "table", "--out", str(tmp_path / "view.png"),
            "--query", server.endpoint, "--timeout", "10", "--rerun", str(rrd),
        ])  # fmt: skip
    finally:
        server.close()
    assert code == 0 and (tmp_path / "view.png").is_file()
    (request,) = server.requests
    data = read_rrd(rrd)
    assert_camera(data, "/world/render", request.K, request.world_from_cam, w, h)
    assert np.allclose(request.world_from_cam[:3, 3], [1.0, 2.0, 1.3])
    assert image_bytes(data["/world/render/image/rgb"], "Image", 0) == result.rgb.tobytes()
    depth = np.frombuffer(image_bytes(data["/world/render/image/depth"], "DepthImage", 0), np.float32)
    assert np.allclose(depth, 1.5)
    seg = data["/world/render/image/label"]
    ids = np.frombuffer(image_bytes(seg, "SegmentationImage", 0), np.uint16).reshape(h, w)
    assert np.array_equal(ids, label + 1)
    assert context_labels(seg) == ["nothing", "chair", "table"]
