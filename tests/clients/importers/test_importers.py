"""Dataset importers: each reader on a tiny fixture written in its dataset's layout.

The fixture scene is the textured plane z = 0 seen by 32x24 cameras, with analytic depth. The
views come in pairs related by a rotation about a world point P on the plane, so P is seen at
the same pixel in both views; unprojecting that pixel from each imported frame (imported depth,
K and pose, pixel centres at +0.5) must land on P within a few millimetres. Every valid pixel
must also land on the plane. This checks the pose direction, the intrinsics convention and the
depth scale of every reader at once.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from clients.importers import (
    ImportedFrame,
    ImporterError,
    ReaderOptions,
    SkippedFrame,
    open_dataset,
)

W, H = 32, 24
# Dataset-convention intrinsics (pixel centres at integers), as a dataset's files would store them.
K_DATASET = (30.0, 29.0, 15.2, 11.7)
PIXELS = [(20, 9), (6, 17)]  # (col, row) of the two world points shared by view pairs
TOL_M = 3e-3


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_cam of an OpenCV camera at ``eye`` looking at ``target``."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = np.stack([x, y, z], axis=1)
    world_from_cam[:3, 3] = eye
    return world_from_cam


def pixel_rays(K: tuple[float, float, float, float], width: int, height: int) -> np.ndarray:
    """(H, W, 3) camera-frame directions with z = 1 through integer pixel coordinates (the
    dataset convention the fixture files are written in)."""
    fx, fy, cx, cy = K
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)


def texture(points: np.ndarray) -> np.ndarray:
    """(..., 3) world points on the plane -> (..., 3) uint8 smooth colour."""
    x, y = points[..., 0], points[..., 1]
    rgb = np.stack(
        [128 + 100 * np.sin(3 * x), 128 + 100 * np.cos(2 * y), 128 + 80 * np.sin(2 * x + 2 * y)], axis=-1
    )
    return np.clip(np.round(rgb), 0, 255).astype(np.uint8)


def render(world_from_cam: np.ndarray, K=K_DATASET, width=W, height=H) -> tuple[np.ndarray, np.ndarray]:
    """Analytic view of the plane z = 0: (H, W, 3) uint8 colour and (H, W) float64 depth in metres
    (0 where the ray misses the plane or hits it beyond 8 m)."""
    return render_rays(world_from_cam, pixel_rays(K, width, height))


def render_rays(world_from_cam: np.ndarray, rays_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`render` for given (H, W, 3) camera-frame rays with z = 1."""
    rays_world = rays_cam @ world_from_cam[:3, :3].T
    eye = world_from_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -eye[2] / rays_world[..., 2]
    depth = np.where(np.isfinite(depth) & (depth > 0.05) & (depth < 8.0), depth, 0.0)
    points = eye + depth[..., None] * rays_world
    rgb = np.where(depth[..., None] > 0, texture(points), 0).astype(np.uint8)
    return rgb, depth


def unproject_dataset_pixel(world_from_cam: np.ndarray, depth: np.ndarray, col: int, row: int) -> np.ndarray:
    fx, fy, cx, cy = K_DATASET
    d = depth[row, col]
    cam = np.array([(col - cx) / fx * d, (row - cy) / fy * d, d])
    return world_from_cam[:3, :3] @ cam + world_from_cam[:3, 3]


def make_views() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Five poses (A, B1, C1, B2, C2) and the two world points: views B_k and C_k are view A
    rotated about the world point P_k seen at PIXELS[k] in A, so P_k stays at that pixel."""
    view_a = look_at(np.array([0.2, -0.6, 1.6]), np.array([0.4, 0.3, 0.0]))
    _, depth_a = render(view_a)
    poses = [view_a]
    points = []
    for k, (col, row) in enumerate(PIXELS):
        point = unproject_dataset_pixel(view_a, depth_a, col, row)
        assert abs(point[2]) < 1e-9
        points.append(point)
        for axis, angle in (([0.3, 0.5, 0.8], 18.0 + 5 * k), ([-0.6, 0.2, 0.7], -15.0)):
            rotation = Rotation.from_rotvec(np.deg2rad(angle) * np.asarray(axis) / np.linalg.norm(axis))
            about_point = np.eye(4)
            about_point[:3, :3] = rotation.as_matrix()
            about_point[:3, 3] = point - rotation.as_matrix() @ point
            poses.append(about_point @ view_a)
    return poses, points


POSES, POINTS = make_views()
PAIRS = [(0, 1, 0), (0, 2, 0), (0, 3, 1), (0, 4, 1), (1, 2, 0)]  # (view, view, point index)


def depth_u16(depth_m: np.ndarray, units_per_m: float) -> np.ndarray:
    return np.round(depth_m * units_per_m).astype(np.uint16)


def write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.ndim == 3:
        image = image[:, :, ::-1]
    assert cv2.imwrite(str(path), image)


def write_jpg(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 98])


def K_matrix(K: tuple[float, float, float, float]) -> np.ndarray:
    fx, fy, cx, cy = K
    return np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# Fixture writers (one per dataset layout)


def write_scannet(root: Path, invalid_pose_ids: tuple[int, ...] = (5,)) -> Path:
    """ScanNet export with colour at twice the depth size (as real ScanNet differs in size)."""
    fx, fy, cx, cy = K_DATASET
    K_color = (2 * fx, 2 * fy, 2 * (cx + 0.5) - 0.5, 2 * (cy + 0.5) - 0.5)  # integer-centre convention
    (root / "intrinsic").mkdir(parents=True)
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", K_matrix(K_color))
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K_matrix(K_DATASET))
    (root / "pose").mkdir()
    poses = [*POSES, POSES[0]]
    for i, world_from_cam in enumerate(poses):
        rgb, _ = render(world_from_cam, K_color, 2 * W, 2 * H)
        _, depth = render(world_from_cam)
        write_jpg(root / "color" / f"{i}.jpg", rgb)
        write_png(root / "depth" / f"{i}.png", depth_u16(depth, 1000.0))
        pose = np.full((4, 4), -np.inf) if i in invalid_pose_ids else world_from_cam
        np.savetxt(root / "pose" / f"{i}.txt", pose)
    return root


def write_replica(root: Path, cam_params: bool = True) -> Path:
    """NICE-SLAM Replica: Replica/cam_params.json, Replica/room0/{traj.txt, results/}."""
    scene = root / "room0"
    (scene / "results").mkdir(parents=True)
    if cam_params:
        fx, fy, cx, cy = K_DATASET
        camera = {"w": W, "h": H, "fx": fx, "fy": fy, "cx": cx, "cy": cy, "scale": 6553.5}
        (root / "cam_params.json").write_text(json.dumps({"camera": camera}))
    lines = []
    for i, world_from_cam in enumerate(POSES):
        rgb, depth = render(world_from_cam)
        write_jpg(scene / "results" / f"frame{i:06d}.jpg", rgb)
        write_png(scene / "results" / f"depth{i:06d}.png", depth_u16(depth, 6553.5))
        lines.append(" ".join(f"{v:.17g}" for v in world_from_cam.reshape(16)))
    (scene / "traj.txt").write_text("\n".join(lines) + "\n")
    return scene


TUM_T0 = 1305031102.175304


def distort(x: np.ndarray, y: np.ndarray, D: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (k1, k2, p1, p2, k3) model on normalised coordinates."""
    k1, k2, p1, p2, k3 = D
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (
        r2 + 2 * y * y
    ) + 2 * p2 * x * y


def distorted_pixel_rays(K: tuple[float, float, float, float], D: tuple[float, ...], width: int, height: int):
    """(H, W, 3) rays (z = 1) seen by the pixels of a camera with distortion D (inverted by
    fixed-point iteration, checked to 1e-10)."""
    fx, fy, cx, cy = K
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xd, yd = (u - cx) / fx, (v - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(500):
        ex, ey = distort(x, y, D)
        x, y = x - (ex - xd), y - (ey - yd)
    ex, ey = distort(x, y, D)
    assert max(np.abs(ex - xd).max(), np.abs(ey - yd).max()) < 1e-10
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def write_tum(
    root: Path,
    name: str = "rgbd_dataset_freiburg3_synthetic",
    K: tuple[float, float, float, float] = K_DATASET,
    size: tuple[int, int] = (W, H),
    distortion: tuple[float, ...] | None = None,
) -> Path:
    """TUM sequence: rgb at 30 Hz, depth 4 ms later, ground truth 3 ms later plus a decoy pose
    12 ms earlier, and one last colour image with no pose within 0.02 s. With ``distortion``
    the images are those of a camera with that lens distortion."""
    rays = pixel_rays(K, *size) if distortion is None else distorted_pixel_rays(K, distortion, *size)
    seq = root / name
    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    gt_lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    decoy = look_at(np.array([1.0, 1.0, 3.0]), np.zeros(3))
    stamps = [TUM_T0 + i / 30.0 for i in range(len(POSES) + 1)]
    for i, stamp in enumerate(stamps):
        world_from_cam = POSES[i % len(POSES)]
        rgb, depth = render_rays(world_from_cam, rays)
        write_png(seq / "rgb" / f"{stamp:.6f}.png", rgb)
        write_png(seq / "depth" / f"{stamp + 0.004:.6f}.png", depth_u16(depth, 5000.0))
        rgb_lines.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
        depth_lines.append(f"{stamp + 0.004:.6f} depth/{stamp + 0.004:.6f}.png")
        if i == len(POSES):
            continue  # no ground truth for the last image
        for dt, pose in ((0.003, world_from_cam), (-0.012, decoy)):
            q = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x, y, z, w
            t = pose[:3, 3]
            gt_lines.append(f"{stamp + dt:.4f} " + " ".join(f"{v:.9f}" for v in (*t, *q)))
    (seq / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (seq / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (seq / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return seq


def write_7scenes(root: Path) -> Path:
    """7-Scenes scene with two sequences; a border of depth pixels is 65535 (invalid)."""
    scene = root / "chess"
    for i, world_from_cam in enumerate(POSES):
        seq = scene / ("seq-01" if i < 3 else "seq-02")
        number = i if i < 3 else i - 3
        rgb, depth = render(world_from_cam)
        raw = depth_u16(depth, 1000.0)
        raw[:, 0] = 65535
        write_png(seq / f"frame-{number:06d}.color.png", rgb)
        write_png(seq / f"frame-{number:06d}.depth.png", raw)
        np.savetxt(seq / f"frame-{number:06d}.pose.txt", world_from_cam)
    return scene


# ---------------------------------------------------------------------------------------------
# Checks


def frames_of(reader) -> list[ImportedFrame | SkippedFrame]:
    return list(reader.iter_frames(range(len(reader))))


def unproject(frame: ImportedFrame, col: int, row: int) -> np.ndarray:
    """World point of pixel (col, row) from the imported depth, K (centres at +0.5) and pose."""
    fx, fy, cx, cy = frame.K
    d = float(frame.depth_m[row, col])
    cam = np.array([(col + 0.5 - cx) / fx * d, (row + 0.5 - cy) / fy * d, d, 1.0])
    return (frame.world_from_cam @ cam)[:3]


def check_geometry(frames: list[ImportedFrame]) -> None:
    assert len(frames) == len(POSES)
    for a, b, k in PAIRS:
        col, row = PIXELS[k]
        from_a, from_b = unproject(frames[a], col, row), unproject(frames[b], col, row)
        assert np.linalg.norm(from_a - from_b) < TOL_M, (a, b, from_a, from_b)
        assert np.linalg.norm(from_a - POINTS[k]) < TOL_M, (a, from_a, POINTS[k])
    for frame in frames:  # every valid pixel lands on the plane z = 0
        assert frame.depth_m.dtype == np.float32 and frame.depth_m.shape == (H, W)
        rows, cols = np.nonzero(frame.depth_m > 0)
        assert len(rows) > 0.5 * W * H
        fx, fy, cx, cy = frame.K
        d = frame.depth_m[rows, cols].astype(np.float64)
        cam = np.stack([(cols + 0.5 - cx) / fx * d, (rows + 0.5 - cy) / fy * d, d], axis=-1)
        world = cam @ frame.world_from_cam[:3, :3].T + frame.world_from_cam[:3, 3]
        assert np.abs(world[:, 2]).max() < TOL_M


def check_colour(frames: list[ImportedFrame], max_mean_abs: float) -> None:
    """Imported colour matches the analytic texture of the frame's pose (R, G, B order)."""
    for frame, world_from_cam in zip(frames, POSES, strict=True):
        expected, depth = render(world_from_cam)
        valid = depth > 0
        diff = np.abs(frame.rgb.astype(np.int16) - expected.astype(np.int16))[valid]
        assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3)
        assert diff.mean() < max_mean_abs, diff.mean()


def expected_K() -> np.ndarray:
    fx, fy, cx, cy = K_DATASET
    return np.array([fx, fy, cx + 0.5, cy + 0.5])


# ---------------------------------------------------------------------------------------------
# Readers


def test_fixture_views_share_points() -> None:
    # the fixture itself: P_k projects to PIXELS[k] with the same depth in paired views
    for a, b, k in PAIRS:
        col, row = PIXELS[k]
        _, depth_a = render(POSES[a])
        _, depth_b = render(POSES[b])
        assert depth_a[row, col] > 0.5
        assert np.allclose(unproject_dataset_pixel(POSES[b], depth_b, col, row), POINTS[k], atol=1e-9)
        assert not np.allclose(POSES[a], POSES[b])


def test_scannet_reader(tmp_path: Path) -> None:
    reader = open_dataset("scannet", write_scannet(tmp_path / "scene0000_00"))
    items = frames_of(reader)
    assert isinstance(items[5], SkippedFrame) and "non-finite" in items[5].reason
    frames = items[:5]
    assert all(isinstance(f, ImportedFrame) for f in frames)
    # colour was 64x48: resized to the depth size with K scaled to it
    np.testing.assert_allclose(frames[0].K, expected_K(), rtol=1e-12)
    check_geometry(frames)
    check_colour(frames, max_mean_abs=6.0)
    assert [f.stamp_ns for f in frames] == [round(i * 1e9 / 30) for i in range(5)]
    assert not reader.warnings()  # scaled colour K agrees with intrinsic_depth.txt


def test_replica_reader(tmp_path: Path) -> None:
    reader = open_dataset("replica", write_replica(tmp_path / "Replica"))
    frames = frames_of(reader)
    assert all(isinstance(f, ImportedFrame) for f in frames)
    np.testing.assert_allclose(frames[0].K, expected_K())
    check_geometry(frames)
    check_colour(frames, max_mean_abs=4.0)
    assert reader.meta()["depth_scale"] == 6553.5


def test_replica_defaults_and_K_override(tmp_path: Path) -> None:
    scene = write_replica(tmp_path / "Replica", cam_params=False)
    with pytest.raises(ImporterError, match=r"intrinsics are for 1200x680.*--K"):
        open_dataset("replica", scene)
    reader = open_dataset("replica", scene, ReaderOptions(K=K_DATASET))
    check_geometry(frames_of(reader))


def test_tum_reader(tmp_path: Path) -> None:
    reader = open_dataset("tum", write_tum(tmp_path), ReaderOptions(K=K_DATASET))
    items = frames_of(reader)
    frames = [item for item in items if isinstance(item, ImportedFrame)]
    skipped = [item for item in items if isinstance(item, SkippedFrame)]
    assert len(skipped) == 1 and "no ground-truth pose within 0.02 s" == skipped[0].reason
    check_geometry(frames)  # nearest pose (3 ms) wins over the decoy (12 ms)
    check_colour(frames, max_mean_abs=0.01)  # PNG: lossless
    assert frames[0].stamp_ns == 1305031102_175304000  # exact, no float rounding
    assert abs(frames[1].stamp_ns - frames[0].stamp_ns - 1e9 / 30) <= 1000


def test_tum_default_intrinsics_by_sequence_name(tmp_path: Path) -> None:
    seq = write_tum(tmp_path, name="rgbd_dataset_freiburg1_xyz")
    reader = open_dataset("tum", seq)
    np.testing.assert_allclose(reader.read(0).K, [517.3, 516.5, 318.6 + 0.5, 255.3 + 0.5])
    assert reader.meta()["distortion_removed"] == [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]
    assert not reader.warnings()
    with_K = open_dataset("tum", seq, ReaderOptions(K=K_DATASET))
    assert not any(with_K.meta()["distortion_removed"]) and "without undistortion" in with_K.warnings()[0]
    other = seq.rename(tmp_path / "my_sequence")
    with pytest.raises(ImporterError, match="pass --K"):
        open_dataset("tum", other)


def test_tum_missing_depth_partner_is_skipped(tmp_path: Path) -> None:
    seq = write_tum(tmp_path)
    lines = (seq / "depth.txt").read_text().splitlines()
    (seq / "depth.txt").write_text("\n".join(lines[:-2] + lines[-1:]) + "\n")  # drop depth of image 4
    items = frames_of(open_dataset("tum", seq, ReaderOptions(K=K_DATASET)))
    reasons = [item.reason for item in items if isinstance(item, SkippedFrame)]
    assert sorted(reasons) == ["no depth image within 0.02 s", "no ground-truth pose within 0.02 s"]
    no_depth = frames_of(open_dataset("tum", seq, ReaderOptions(K=K_DATASET, load_depth=False)))
    assert sum(isinstance(item, ImportedFrame) for item in no_depth) == len(POSES)
    assert all(item.depth_m is None for item in no_depth if isinstance(item, ImportedFrame))


def test_7scenes_reader(tmp_path: Path) -> None:
    scene = write_7scenes(tmp_path)
    reader = open_dataset("7scenes", scene, ReaderOptions(K=K_DATASET))
    frames = frames_of(reader)
    assert [f.source for f in frames][2:4] == ["seq-01/frame-000002", "seq-02/frame-000000"]
    assert all(np.all(f.depth_m[:, 0] == 0) for f in frames)  # 65535 = invalid -> 0
    check_geometry(frames)
    check_colour(frames, max_mean_abs=0.01)
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    single = open_dataset("7scenes", scene / "seq-02", ReaderOptions(K=K_DATASET))
    assert len(single) == 2
    default_K = open_dataset("7scenes", scene).read(0).K
    np.testing.assert_allclose(default_K, [585.0, 585.0, 320.5, 240.5])


# ---------------------------------------------------------------------------------------------
# Clear errors


@pytest.mark.parametrize("fmt", ["scannet", "replica", "tum", "7scenes", "sim"])
def test_missing_folder(tmp_path: Path, fmt: str) -> None:
    with pytest.raises(ImporterError, match="does not exist"):
        open_dataset(fmt, tmp_path / "nowhere")


def test_unknown_format(tmp_path: Path) -> None:
    with pytest.raises(ImporterError, match="unknown dataset format 'kitti'; choose one of scannet"):
        open_dataset("kitti", tmp_path)


def test_missing_pose_files(tmp_path: Path) -> None:
    scannet = write_scannet(tmp_path / "scannet")
    (scannet / "pose" / "2.txt").unlink()
    with pytest.raises(ImporterError, match=r"6 colour images but 5 pose/\*\.txt, missing for frames 2"):
        open_dataset("scannet", scannet)

    replica = write_replica(tmp_path / "Replica")
    (replica / "traj.txt").unlink()
    with pytest.raises(ImporterError, match="missing Replica trajectory traj.txt"):
        open_dataset("replica", replica)

    tum = write_tum(tmp_path / "tum")
    (tum / "groundtruth.txt").unlink()
    with pytest.raises(ImporterError, match="missing TUM ground truth groundtruth.txt"):
        open_dataset("tum", tum, ReaderOptions(K=K_DATASET))

    seven = write_7scenes(tmp_path / "7s")
    (seven / "seq-01" / "frame-000001.pose.txt").unlink()
    with pytest.raises(ImporterError, match="missing pose for frames 1"):
        open_dataset("7scenes", seven)


def test_mismatched_counts(tmp_path: Path) -> None:
    replica = write_replica(tmp_path / "Replica")
    lines = (replica / "traj.txt").read_text().splitlines()
    (replica / "traj.txt").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(ImporterError, match="traj.txt has 4 poses for 5 colour frames"):
        open_dataset("replica", replica)

    scannet = write_scannet(tmp_path / "scannet")
    (scannet / "depth" / "0.png").unlink()
    with pytest.raises(ImporterError, match=r"5 depth/\*\.png, missing for frames 0"):
        open_dataset("scannet", scannet)
    no_depth = open_dataset("scannet", scannet, ReaderOptions(load_depth=False))
    assert no_depth.read(0).rgb.shape == (H, W, 3) and no_depth.read(0).depth_m is None  # depth size
    (scannet / "depth" / "3.png").rename(scannet / "depth" / "0.png")
    with pytest.raises(ImporterError, match=r"5 depth/\*\.png, missing for frames 3"):
        open_dataset("scannet", scannet)
    assert len(open_dataset("scannet", scannet, ReaderOptions(load_depth=False))) == len(POSES) + 1

    seven = write_7scenes(tmp_path / "7s")
    (seven / "seq-02" / "frame-000001.depth.png").unlink()
    with pytest.raises(ImporterError, match="missing depth for frames 1.*--no-depth"):
        open_dataset("7scenes", seven)
    assert len(open_dataset("7scenes", seven, ReaderOptions(load_depth=False))) == len(POSES)


def test_unreadable_image(tmp_path: Path) -> None:
    replica = write_replica(tmp_path / "Replica")
    (replica / "results" / "frame000002.jpg").write_bytes(b"not a jpeg")
    reader = open_dataset("replica", replica)
    with pytest.raises(ImporterError, match=r"unreadable colour image .*frame000002\.jpg"):
        frames_of(reader)

    tum = write_tum(tmp_path / "tum")
    depth_name = (tum / "depth.txt").read_text().splitlines()[3].split()[1]
    (tum / depth_name).write_bytes(b"\x89PNG broken")
    with pytest.raises(ImporterError, match="unreadable depth image"):
        frames_of(open_dataset("tum", tum, ReaderOptions(K=K_DATASET)))


def test_bad_K_and_layout_errors(tmp_path: Path) -> None:
    from clients.importers.base import parse_K

    assert parse_K("30, 29 15.2,11.7") == K_DATASET
    for text, message in (("1,2,3", "4 numbers"), ("a,b,c,d", "4 numbers"), ("0,1,2,3", "fx, fy > 0")):
        with pytest.raises(ImporterError, match=message):
            parse_K(text)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImporterError, match="neither a seq-XX folder"):
        open_dataset("7scenes", tmp_path / "empty")
    with pytest.raises(ImporterError, match="missing ScanNet colour folder"):
        open_dataset("scannet", tmp_path / "empty")
    with pytest.raises(ImporterError, match="missing Replica results folder"):
        open_dataset("replica", tmp_path / "empty")


# ---------------------------------------------------------------------------------------------
# Conversion to .govrec and the `govnesf import` command


def read_back(path: Path):
    from protocol.recording import read_recording

    recording = read_recording(path)
    frames = list(recording.frames())
    assert not recording.truncated
    return recording.header.meta, frames


def test_cli_replica_stride_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from clients.importers.cli import main

    scene = write_replica(tmp_path / "Replica")
    out = tmp_path / "room0.govrec"
    rc = main(["replica", str(scene), "--out", str(out), "--stride", "2", "--rgb-encoding", "png"])
    assert rc == 0
    assert "wrote 3 frames (32x24)" in capsys.readouterr().out
    meta, frames = read_back(out)
    assert meta["source_format"] == "replica" and meta["stride"] == 2
    source = frames_of(open_dataset("replica", scene))
    assert [f.seq for f in frames] == [0, 1, 2]
    for frame, expected in zip(frames, source[::2], strict=True):
        assert frame.rgb_encoding == "png"
        np.testing.assert_array_equal(frame.rgb, expected.rgb)  # png: lossless
        np.testing.assert_array_equal(frame.depth_m, expected.depth_m)
        np.testing.assert_array_equal(frame.K, expected.K)
        np.testing.assert_array_equal(frame.world_from_cam, expected.world_from_cam)
        assert frame.stamp_ns == expected.stamp_ns


def test_cli_scannet_summary_counts_skips(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from clients.cli import main as govnesf

    scene = write_scannet(tmp_path / "scene", invalid_pose_ids=(1, 5))
    out = tmp_path / "scene.govrec"
    rc = govnesf(["import", "scannet", str(scene), "--out", str(out), "--quiet", "--rgb-encoding", "jpeg"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "wrote 4 frames" in printed and "2  invalid pose (non-finite values)" in printed
    _, frames = read_back(out)
    assert [f.stamp_ns for f in frames] == [round(i * 1e9 / 30) for i in (0, 2, 3, 4)]
    assert all(f.rgb_encoding == "jpeg" and f.rgb.shape == (H, W, 3) for f in frames)


def test_cli_max_frames_no_depth(tmp_path: Path) -> None:
    from clients.importers.cli import main

    out = tmp_path / "seven.govrec"
    args = ["7scenes", str(write_7scenes(tmp_path)), "--out", str(out), "--K", "30,29,15.2,11.7"]
    assert main([*args, "--max-frames", "2", "--no-depth", "--quiet"]) == 0
    _, frames = read_back(out)
    assert len(frames) == 2 and all(f.depth_m is None for f in frames)
    np.testing.assert_allclose(frames[0].K, expected_K())


def test_cli_errors_leave_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from clients.importers.cli import main

    scene = write_replica(tmp_path / "Replica")
    (scene / "results" / "frame000003.jpg").write_bytes(b"garbage")
    out = tmp_path / "out.govrec"
    assert main(["replica", str(scene), "--out", str(out), "--quiet"]) == 1
    assert "unreadable colour image" in capsys.readouterr().err
    assert list(tmp_path.glob("out.govrec*")) == []  # no output, no partial file

    out.write_bytes(b"keep me")
    assert main(["replica", str(scene), "--out", str(out), "--max-frames", "1", "--quiet"]) == 1
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"
    assert main(["replica", str(scene), "--out", str(out), "--max-frames", "1", "--overwrite"]) == 0
    assert len(read_back(out)[1]) == 1

    assert main(["replica", str(scene), "--out", str(tmp_path / "x.bag"), "--quiet"]) == 1
    assert "--out must name a .govrec file, got" in capsys.readouterr().err
    assert main(["replica", str(scene), "--out", str(tmp_path / "y.govrec"), "--K", "1,2"]) == 1
    assert "--K wants 4 numbers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["replica", str(scene), "--out", str(tmp_path / "z.govrec"), "--stride", "0"])


def test_all_frames_skipped_is_an_error(tmp_path: Path) -> None:
    from clients.importers import convert

    scene = write_scannet(tmp_path / "scene", invalid_pose_ids=tuple(range(len(POSES) + 1)))
    out = tmp_path / "none.govrec"
    with pytest.raises(ImporterError, match=r"no frames to write.*6 x invalid pose"):
        convert(open_dataset("scannet", scene), out, progress=False)
    assert not out.exists() and not out.with_name("none.govrec.partial").exists()


def write_sim_export(root: Path) -> Path:
    """A simulator-style export: DIR/frames.govrec (with depth and OV features) + DIR/gt/."""
    from protocol.messages import Frame
    from protocol.recording import RecordingWriter

    root.mkdir()
    (root / "gt").mkdir()
    rng = np.random.default_rng(0)
    with RecordingWriter(root / "frames.govrec", {"scene": "room_a", "generator": "test"}) as writer:
        for i, world_from_cam in enumerate(POSES):
            rgb, depth = render(world_from_cam)
            writer.write(
                Frame(
                    seq=i,
                    stamp_ns=1_000 + i * 33_000_000,
                    width=W,
                    height=H,
                    K=expected_K(),
                    world_from_cam=world_from_cam,
                    rgb=rgb,
                    depth_m=depth.astype(np.float32),
                    ov=rng.standard_normal((6, 8, 4)).astype(np.float16),
                    ov_space="minilm-l6-v2",
                )
            )
    return root


def test_sim_import_reencodes_and_passes_through(tmp_path: Path) -> None:
    from clients.importers import convert

    export = write_sim_export(tmp_path / "export")
    _, source = read_back(export / "frames.govrec")
    out = tmp_path / "sim.govrec"
    reader = open_dataset("sim", export)
    summary = convert(reader, out, stride=2, rgb_encoding="jpeg", progress=False)
    assert summary.frames_written == 3 and not summary.skipped
    meta, frames = read_back(out)
    assert meta["source_meta"] == {"scene": "room_a", "generator": "test"}
    assert meta["gt_dir"] == str((export / "gt").resolve())
    for frame, expected in zip(frames, source[::2], strict=True):
        assert frame.rgb_encoding == "jpeg"
        assert np.abs(frame.rgb.astype(int) - expected.rgb.astype(int)).mean() < 3.0
        np.testing.assert_array_equal(frame.depth_m, expected.depth_m)
        np.testing.assert_array_equal(frame.ov, expected.ov)
        assert frame.ov_space == "minilm-l6-v2" and frame.stamp_ns == expected.stamp_ns
        np.testing.assert_array_equal(frame.world_from_cam, expected.world_from_cam)
    convert(open_dataset("sim", export / "frames.govrec"), tmp_path / "all.govrec", progress=False)
    _, all_frames = read_back(tmp_path / "all.govrec")
    check_geometry([ImportedFrame(f.rgb, f.depth_m, f.K, f.world_from_cam, 0, "") for f in all_frames])


def test_sim_import_of_a_cut_recording(tmp_path: Path) -> None:
    from clients.importers import convert

    export = write_sim_export(tmp_path / "export")
    path = export / "frames.govrec"
    path.write_bytes(path.read_bytes()[:-100])  # last frame cut short
    with pytest.raises(ImporterError, match="--K does not apply to sim"):
        open_dataset("sim", path, ReaderOptions(K=K_DATASET))
    summary = convert(open_dataset("sim", path), tmp_path / "cut.govrec", progress=False)
    assert summary.frames_written == len(POSES) - 1
    assert any("damaged" in w and "cut short" in w for w in summary.warnings)
    (tmp_path / "junk.govrec").write_bytes(b"\x93not a recording")
    with pytest.raises(ImporterError, match="cannot read recording"):
        open_dataset("sim", tmp_path / "junk.govrec")


def test_up_axis_rotates_the_world(tmp_path: Path) -> None:
    from clients.importers import convert

    scene = write_7scenes(tmp_path)
    options = ReaderOptions(K=K_DATASET)  # 7-Scenes default: dataset -y is up
    convert(open_dataset("7scenes", scene, options), tmp_path / "up.govrec", progress=False)
    meta, frames = read_back(tmp_path / "up.govrec")
    assert meta["up_axis"] == "-y"
    up = np.array([0.0, -1.0, 0.0])  # the dataset's up direction ...
    world_from_dataset = np.asarray(meta["world_from_dataset"]).reshape(4, 4)
    np.testing.assert_allclose(world_from_dataset[:3, :3] @ up, [0, 0, 1])  # ... becomes +z
    for frame, pose in zip(frames, POSES, strict=True):
        np.testing.assert_allclose(frame.world_from_cam, world_from_dataset @ pose, atol=1e-12)
        # the fixture plane z = 0 (normal +z) is now the plane y = 0
        rows, cols = np.nonzero(frame.depth_m > 0)
        fx, fy, cx, cy = frame.K
        d = frame.depth_m[rows, cols].astype(np.float64)
        cam = np.stack([(cols + 0.5 - cx) / fx * d, (rows + 0.5 - cy) / fy * d, d], axis=-1)
        world = cam @ frame.world_from_cam[:3, :3].T + frame.world_from_cam[:3, 3]
        assert np.abs(world[:, 1]).max() < TOL_M and np.ptp(world[:, 2]) > 0.1

    same = ReaderOptions(K=K_DATASET, up_axis="z")
    convert(open_dataset("7scenes", scene, same), tmp_path / "z.govrec", progress=False)
    for frame, pose in zip(read_back(tmp_path / "z.govrec")[1], POSES, strict=True):
        np.testing.assert_array_equal(frame.world_from_cam, pose)
    with pytest.raises(ImporterError, match="--up-axis must be one of z, -z, y, -y, x, -x, got 'up'"):
        open_dataset("7scenes", scene, ReaderOptions(up_axis="up"))


@pytest.mark.parametrize("axis", ["z", "-z", "y", "-y", "x", "-x"])
def test_up_axis_table_is_a_rotation_taking_the_axis_to_z(axis: str) -> None:
    from clients.importers.base import world_from_dataset

    rotation = world_from_dataset(axis)[:3, :3]
    direction = np.zeros(3)
    direction["xyz".index(axis[-1])] = -1.0 if axis.startswith("-") else 1.0
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3))
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation @ direction, [0.0, 0.0, 1.0])


def test_scannet_warns_when_depth_intrinsics_disagree(tmp_path: Path) -> None:
    scene = write_scannet(tmp_path / "scene")
    fx, fy, cx, cy = K_DATASET
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", K_matrix((1.1 * fx, fy, cx, cy)))
    reader = open_dataset("scannet", scene)
    assert len(reader.warnings()) == 1 and "by 9.1%; the colour K is used" in reader.warnings()[0]
    np.testing.assert_allclose(reader.read(0).K, expected_K())  # the scaled colour K is used
    override = open_dataset("scannet", scene, ReaderOptions(K=(60.0, 58.0, 30.9, 23.9)))
    np.testing.assert_allclose(override.read(0).K, [30.0, 29.0, 15.7, 12.2])  # colour K, halved


def test_tum_undistortion(tmp_path: Path) -> None:
    """fr1's lens distortion, at 64x48: undistorted frames put every valid pixel on the plane;
    the raw (distorted) images taken as pinhole do not."""
    from clients.importers.tum import FREIBURG_DISTORTION, TumReader

    K = (60.0, 58.0, 31.9, 23.9)
    D = FREIBURG_DISTORTION["fr1"]
    seq = write_tum(tmp_path, K=K, size=(64, 48), distortion=D)

    def off_plane_m(reader: TumReader) -> list[float]:
        errors = []
        for frame in frames_of(reader):
            if isinstance(frame, SkippedFrame):
                continue
            rows, cols = np.nonzero(frame.depth_m > 0)
            assert len(rows) > 0.5 * 64 * 48
            fx, fy, cx, cy = frame.K
            d = frame.depth_m[rows, cols].astype(np.float64)
            cam = np.stack([(cols + 0.5 - cx) / fx * d, (rows + 0.5 - cy) / fy * d, d], axis=-1)
            world = cam @ frame.world_from_cam[:3, :3].T + frame.world_from_cam[:3, 3]
            errors.append(float(np.abs(world[:, 2]).max()))
        return errors

    undistorted = TumReader(seq, ReaderOptions(K=K), distortion=D)
    assert max(off_plane_m(undistorted)) < TOL_M
    raw = TumReader(seq, ReaderOptions(K=K), distortion=(0.0,) * 5)
    assert max(off_plane_m(raw)) > 10 * TOL_M
    # colour follows the geometry: compare with a pinhole render of the same pose
    frame = undistorted.read(0)
    expected, depth = render(POSES[0], K, 64, 48)
    valid = (depth > 0) & (frame.depth_m > 0)
    diff = np.abs(frame.rgb.astype(int) - expected.astype(int))[valid]
    assert diff.mean() < 4.0, diff.mean()


def test_remap_depth_does_not_mix_surfaces() -> None:
    from clients.importers.base import remap_depth

    depth = np.full((6, 8), 1.0, dtype=np.float32)
    depth[:, 4:] = 3.0  # a step edge between columns 3 and 4
    depth[0, 0] = 0.0  # a hole
    map_y, map_x = np.meshgrid(np.arange(6, dtype=np.float32), np.arange(8, dtype=np.float32), indexing="ij")
    out = remap_depth(depth, (map_x + 0.5, map_y))  # half a pixel to the right
    assert set(np.unique(out[1:, :7]).tolist()) == {1.0, 3.0}  # never 2.0 across the edge
    assert out[0, 0] in (0.0, 1.0) and np.all(out[:, 7] == 0)  # beyond the last centre: unknown
    smooth = np.linspace(1.0, 1.2, 8, dtype=np.float32)[None, :].repeat(6, axis=0)
    np.testing.assert_allclose(
        remap_depth(smooth, (map_x + 0.25, map_y))[:, :7], smooth[:, :7] + 0.25 * 0.2 / 7, rtol=1e-6
    )
