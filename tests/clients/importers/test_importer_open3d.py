"""The ``open3d`` importer (Open3D reconstruction layout with ``trajectory.log``, e.g. ICL-NUIM).

The synthetic fixture is the textured plane of ``test_importers`` written in the Open3D layout;
the real-data test converts a few frames of ``shared/data/icl_livingroom1`` and checks that depth
reprojects between frames with the imported poses and intrinsics.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from clients.importers import ImporterError, ReaderOptions, convert, open_dataset
from clients.importers.base import world_from_dataset
from tests.clients.importers.test_importers import (
    K_DATASET,
    POSES,
    H,
    W,
    check_colour,
    check_geometry,
    depth_u16,
    expected_K,
    frames_of,
    read_back,
    render,
    write_jpg,
    write_png,
)

ICL = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "icl_livingroom1"
ICL_K = "525,525,319.5,239.5"


def log_text(poses: list[np.ndarray], ids: list[int] | None = None, fmt: str = "{:.17g}") -> str:
    """An Open3D trajectory log as Open3D writes it: 'i i i+1' then the 4x4 rows."""
    ids = list(range(len(poses))) if ids is None else ids
    lines = []
    for i, pose in zip(ids, poses, strict=True):
        lines.append(f"{i} {i} {i + 1}")
        lines.extend(" ".join(fmt.format(v) for v in row) for row in pose)
    return "\n".join(lines) + "\n"


def intrinsic_json(K: tuple[float, float, float, float], width: int = W, height: int = H) -> str:
    fx, fy, cx, cy = K
    return json.dumps({"width": width, "height": height, "intrinsic_matrix": [fx, 0, 0, 0, fy, 0, cx, cy, 1]})


def write_open3d(root: Path, intrinsics: bool = True, numbers: list[int] | None = None) -> Path:
    """image/NNNNN.jpg, depth/NNNNN.png (mm), trajectory.log and camera_intrinsic.json."""
    numbers = list(range(len(POSES))) if numbers is None else numbers
    for number, world_from_cam in zip(numbers, POSES, strict=True):
        rgb, depth = render(world_from_cam)
        write_jpg(root / "image" / f"{number:05d}.jpg", rgb)
        write_png(root / "depth" / f"{number:05d}.png", depth_u16(depth, 1000.0))
    (root / "trajectory.log").write_text(log_text(POSES))
    if intrinsics:
        (root / "camera_intrinsic.json").write_text(intrinsic_json(K_DATASET))
    return root


# ---------------------------------------------------------------------------------------------
# Synthetic fixture


def test_open3d_reader_geometry(tmp_path: Path) -> None:
    reader = open_dataset("open3d", write_open3d(tmp_path / "seq"), ReaderOptions(up_axis="z"))
    assert len(reader) == len(POSES)
    frames = frames_of(reader)
    check_geometry(frames)  # pose direction, K convention (+0.5) and millimetre depth scale
    check_colour(frames, max_mean_abs=6.0)
    for frame, pose in zip(frames, POSES, strict=True):
        np.testing.assert_allclose(frame.K, expected_K())
        np.testing.assert_array_equal(frame.world_from_cam, pose)
    assert [f.source for f in frames][:2] == ["image/00000.jpg", "image/00001.jpg"]
    assert reader.meta()["intrinsics"] == "camera_intrinsic.json"
    assert reader.warnings() == []  # up axis given: no warning about pose 0


def test_open3d_round_trip_through_govrec(tmp_path: Path) -> None:
    seq = write_open3d(tmp_path / "seq")
    reader = open_dataset("open3d", seq)
    assert reader.up_axis == "-y"  # default: the world is the first camera's (OpenCV) frame
    assert any("first pose is not the identity" in w for w in reader.warnings())
    source = frames_of(reader)
    summary = convert(reader, tmp_path / "seq.govrec", rgb_encoding="png", progress=False)
    assert summary.frames_written == len(POSES) and (summary.width, summary.height) == (W, H)

    meta, frames = read_back(tmp_path / "seq.govrec")
    assert meta["source_format"] == "open3d" and meta["up_axis"] == "-y"
    assert meta["K_dataset"] == list(K_DATASET) and meta["depth_scale"] == 1000.0
    assert meta["pairing"] == "by frame number"
    up = world_from_dataset("-y")
    for seq_no, (frame, imported, pose) in enumerate(zip(frames, source, POSES, strict=True)):
        assert frame.seq == seq_no and frame.stamp_ns == round(seq_no * 1e9 / 30)
        np.testing.assert_allclose(frame.world_from_cam, up @ pose, atol=1e-12)
        np.testing.assert_array_equal(frame.K, expected_K())
        np.testing.assert_array_equal(frame.rgb, imported.rgb)  # png: lossless
        np.testing.assert_array_equal(frame.depth_m, imported.depth_m)
        _, depth = render(pose)
        np.testing.assert_allclose(frame.depth_m, depth, atol=0.5e-3 + 1e-6)  # mm rounding
    assert np.allclose(up @ np.array([0.0, -1.0, 0.0, 0.0]), [0.0, 0.0, 1.0, 0.0])


def test_open3d_cli_alias_and_K(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from clients.importers.cli import main

    seq = write_open3d(tmp_path / "seq", intrinsics=False)
    out = tmp_path / "icl.govrec"
    assert main(["icl", str(seq), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "camera_intrinsic.json" in err and "--K fx,fy,cx,cy" in err and "525,525,319.5,239.5" in err
    assert not out.exists()

    args = ["icl", str(seq), "--out", str(out), "--K", "30,29,15.2,11.7", "--stride", "2", "--quiet"]
    assert main([*args, "--up-axis", "z"]) == 0
    assert "import open3d: wrote 3 frames (32x24)" in capsys.readouterr().out
    meta, frames = read_back(out)
    assert meta["source_format"] == "open3d" and meta["intrinsics"] == "--K"
    for frame, pose in zip(frames, POSES[::2], strict=True):
        np.testing.assert_allclose(frame.world_from_cam, pose)
        np.testing.assert_allclose(frame.K, expected_K())


def test_open3d_intrinsics(tmp_path: Path) -> None:
    seq = write_open3d(tmp_path / "seq", intrinsics=False)
    with pytest.raises(ImporterError, match=r"no intrinsics .*camera_intrinsic\.json.*or pass --K"):
        open_dataset("open3d", seq)
    # column-major: fx != fy and cx != cy catch a transposed read
    (seq / "camera_intrinsic.json").write_text(intrinsic_json((31.0, 28.0, 15.5, 11.0)))
    np.testing.assert_allclose(open_dataset("open3d", seq).read(0).K, [31.0, 28.0, 16.0, 11.5])
    # --K overrides the file
    with_K = open_dataset("open3d", seq, ReaderOptions(K=K_DATASET))
    np.testing.assert_allclose(with_K.read(0).K, expected_K())

    (seq / "camera_intrinsic.json").write_text(intrinsic_json(K_DATASET, width=640, height=480))
    with pytest.raises(ImporterError, match=r"colour images are 32x24 but .* is for 640x480; pass --K"):
        open_dataset("open3d", seq)
    assert len(open_dataset("open3d", seq, ReaderOptions(K=K_DATASET))) == len(POSES)
    bad = {"width": W, "height": H, "intrinsic_matrix": [30, 0, 15, 0, 29, 11, 0, 0, 1]}  # row-major
    (seq / "camera_intrinsic.json").write_text(json.dumps(bad))
    with pytest.raises(ImporterError, match="column-major"):
        open_dataset("open3d", seq)
    (seq / "camera_intrinsic.json").write_text("{not json")
    with pytest.raises(ImporterError, match="is not an Open3D camera_intrinsic.json"):
        open_dataset("open3d", seq)


def _lines(seq: Path) -> list[str]:
    return (seq / "trajectory.log").read_text().splitlines()


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda ls: ls[:-2], r"truncated: the block of frame 4 \(line 21\) has 2 of 4 matrix rows"),
        (lambda ls: [*ls[:7], "0.5 nan 0.1 0.2", *ls[8:]], r"trajectory\.log:6: frame 1: .*non-finite"),
        (
            lambda ls: [*ls[:1], " ".join(str(1.05 * float(v)) for v in ls[1].split()), *ls[2:]],
            r"trajectory\.log:1: frame 0: invalid pose \(rotation not orthonormal\)",
        ),
        (lambda ls: [*ls[:10], "2 2", *ls[11:]], r"trajectory\.log:11: expected a block header 'i j n'"),
        (
            lambda ls: [*ls[:11], "1 0 0", *ls[12:]],
            r":12: expected 4 numbers \(a row of the 4x4 pose of frame 2\)",
        ),
        (lambda ls: [*ls[:12], "1 x 0 0", *ls[13:]], r":13: not numbers in the pose of frame 2"),
        (lambda ls: [*ls[:5], "1 2 5", *ls[6:]], r"pairs two frames \(i != j\).*pose-graph log"),
        (lambda ls: [*ls[:5], "0 0 2", *ls[6:]], r":6: frame 0 appears twice \(first at line 1\)"),
        (lambda ls: ["", "  "], r"trajectory .*trajectory\.log' is empty"),
    ],
    ids=[
        "truncated",
        "nan",
        "not-orthonormal",
        "bad-header",
        "short-row",
        "not-numbers",
        "pairwise",
        "dup",
        "empty",
    ],
)
def test_open3d_bad_trajectory(tmp_path: Path, damage, message: str) -> None:
    seq = write_open3d(tmp_path / "seq")
    (seq / "trajectory.log").write_text("\n".join(damage(_lines(seq))) + "\n")
    with pytest.raises(ImporterError, match=message):
        open_dataset("open3d", seq)


def test_open3d_missing_files_and_counts(tmp_path: Path) -> None:
    with pytest.raises(ImporterError, match="does not exist"):
        open_dataset("open3d", tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImporterError, match=r"missing Open3D colour folder: none of image/, color/, rgb/"):
        open_dataset("open3d", tmp_path / "empty")

    seq = write_open3d(tmp_path / "seq")
    (seq / "trajectory.log").rename(seq / "traj.log")
    with pytest.raises(ImporterError, match=r"missing Open3D trajectory trajectory\.log"):
        open_dataset("open3d", seq)
    (seq / "traj.log").rename(seq / "trajectory.log")

    (seq / "image" / "00002.jpg").unlink()
    with pytest.raises(
        ImporterError, match=r"4 colour images in image/ but 5 poses .*missing colour images for frames 2"
    ):
        open_dataset("open3d", seq)
    write_jpg(seq / "image" / "00002.jpg", render(POSES[2])[0])
    write_jpg(seq / "image" / "00007.jpg", render(POSES[2])[0])
    with pytest.raises(ImporterError, match=r"6 colour images .* 5 poses .*no pose for colour images 7"):
        open_dataset("open3d", seq)
    (seq / "image" / "00007.jpg").unlink()

    (seq / "depth" / "00003.png").unlink()
    with pytest.raises(ImporterError, match=r"missing depth for frames 3 \(use --no-depth"):
        open_dataset("open3d", seq)
    colour_only = frames_of(open_dataset("open3d", seq, ReaderOptions(load_depth=False)))
    assert len(colour_only) == len(POSES) and all(f.depth_m is None for f in colour_only)

    write_png(seq / "depth" / "00003.png", np.zeros((H + 1, W), dtype=np.uint16))
    with pytest.raises(
        ImporterError, match=r"depth image .*00003\.png' is 32x25, colour image/00003\.jpg is 32x24"
    ):
        frames_of(open_dataset("open3d", seq))
    (seq / "image" / "00001.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ImporterError, match=r"unreadable colour image .*00001\.jpg"):
        open_dataset("open3d", seq).read(1)


def test_open3d_pairs_in_order_when_numbers_differ(tmp_path: Path) -> None:
    seq = write_open3d(tmp_path / "seq", numbers=[1, 2, 3, 4, 5])  # 1-based images, 0-based log
    reader = open_dataset("open3d", seq, ReaderOptions(up_axis="z"))
    assert any("paired in order" in w for w in reader.warnings())
    assert reader.meta()["pairing"] == "in order"
    check_geometry(frames_of(reader))


# ---------------------------------------------------------------------------------------------
# Real data: ICL-NUIM living room 1 (Open3D's test excerpt)


def reprojection_error(frame_a, frame_b, invert_poses: bool = False) -> tuple[float, float]:
    """Median relative depth error of frame A's depth seen from frame B (nearest pixel, points in
    front of B and inside its image, valid depth in B), and the fraction of A's pixels compared.
    ``invert_poses`` reads the poses the wrong way round (as world-to-camera)."""
    fx, fy, cx, cy = frame_a.K
    rows, cols = np.nonzero(frame_a.depth_m > 0)
    d = frame_a.depth_m[rows, cols].astype(np.float64)
    cam_a = np.stack([(cols + 0.5 - cx) / fx * d, (rows + 0.5 - cy) / fy * d, d, np.ones_like(d)])
    pose_a, pose_b = frame_a.world_from_cam, frame_b.world_from_cam
    if invert_poses:
        pose_a, pose_b = np.linalg.inv(pose_a), np.linalg.inv(pose_b)
    cam_b = np.linalg.inv(pose_b) @ pose_a @ cam_a
    z = cam_b[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = fx * cam_b[0] / z + cx, fy * cam_b[1] / z + cy
    height, width = frame_b.depth_m.shape
    inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    seen = frame_b.depth_m[v[inside].astype(np.int64), u[inside].astype(np.int64)].astype(np.float64)
    ok = seen > 0
    rel = np.abs(z[inside][ok] - seen[ok]) / seen[ok]
    return float(np.median(rel)), float(ok.sum() / len(d))


@pytest.mark.skipif(not (ICL / "trajectory.log").is_file(), reason=f"ICL-NUIM excerpt not found at {ICL}")
def test_icl_livingroom_reprojects(tmp_path: Path) -> None:
    from clients.importers.cli import main

    out = tmp_path / "icl.govrec"
    args = ["open3d", str(ICL), "--out", str(out), "--K", ICL_K, "--stride", "5", "--max-frames", "3"]
    assert main([*args, "--up-axis", "z", "--quiet"]) == 0  # dataset world: compare with the log
    meta, frames = read_back(out)  # source frames 0, 5, 10
    assert len(frames) == 3 and (frames[0].width, frames[0].height) == (640, 480)
    np.testing.assert_allclose(frames[0].K, [525.0, 525.0, 320.0, 240.0])
    np.testing.assert_allclose(frames[0].world_from_cam, np.eye(4), atol=1e-7)  # Open3D anchors pose 0
    depth = frames[0].depth_m
    assert depth.dtype == np.float32 and 0.3 < np.median(depth[depth > 0]) < 5.0  # millimetres -> metres

    error_0_10, overlap = reprojection_error(frames[0], frames[2])
    assert error_0_10 < 0.02 and overlap > 0.5, (error_0_10, overlap)
    assert reprojection_error(frames[0], frames[1])[0] < 0.02
    # the check has teeth: reading the log as world-to-camera breaks it
    assert reprojection_error(frames[0], frames[2], invert_poses=True)[0] > 5 * error_0_10
