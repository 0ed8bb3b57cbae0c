"""``govnesf import rosbag`` (clients/importers/rosbag.py) on ROS 2 bags this test writes itself
with rosbags' own writer, in both storages (sqlite3 ``.db3`` and MCAP).

The bags hold exact, known data: random colour pixels (rgb8 / bgr8 / mono8 / PNG / JPEG, one with
row padding in ``step``), depth in 16UC1 millimetres or 32FC1 metres, a CameraInfo, and a TF tree
``map -> odom -> base_link -> camera_link -> camera_color_optical_frame`` (the last edge the
standard optical rotation every ROS camera driver publishes), with ``odom -> base_link`` sampled
10 ms before and after each image so that the pose at the image's stamp is an interpolation. The
expected camera poses are built here without quaternions (yaw angles and axis-angle matrices),
so a wrong quaternion order (w first) or a missing optical rotation changes the result.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from clients.importers import ImportedFrame, ImporterError, ReaderOptions, SkippedFrame  # noqa: E402
from clients.importers.rosbag import BODY_FROM_OPTICAL, RosbagOptions, RosbagReader  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
W, H = 16, 12
FX, FY, CX, CY = 20.0, 21.0, 7.6, 5.4  # ROS / OpenCV convention: pixel centres at integers
N = 4
T0 = 1_700_000_000 * 10**9  # ns
DT = 100_000_000  # 10 Hz images
TF_OFFSET = 10_000_000  # odom -> base_link samples 10 ms before and after each image
OPTICAL = "camera_color_optical_frame"
STORAGES = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}


def T(name: str) -> Any:
    return TS.types[name]


def stamp(ns: int) -> Any:
    return T("builtin_interfaces/msg/Time")(sec=ns // 10**9, nanosec=ns % 10**9)


def header(ns: int, frame: str) -> Any:
    return T("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=frame)


def axis_angle(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    """(3, 3) rotation by Rodrigues' formula (no quaternions involved)."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def rigid(rot: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = t
    return out


def quat_xyzw(axis: tuple[float, float, float], angle: float) -> tuple[float, float, float, float]:
    """The ROS quaternion (x, y, z, w) of the rotation ``angle`` about ``axis``."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    s = math.sin(angle / 2)
    return float(k[0] * s), float(k[1] * s), float(k[2] * s), math.cos(angle / 2)


def transform(parent: str, child: str, ns: int, t: tuple[float, float, float],
              axis: tuple[float, float, float], angle: float) -> Any:  # fmt: skip
    x, y, z, w = quat_xyzw(axis, angle)
    return T("geometry_msgs/msg/TransformStamped")(
        header=header(ns, parent), child_frame_id=child,
        transform=T("geometry_msgs/msg/Transform")(
            translation=T("geometry_msgs/msg/Vector3")(x=t[0], y=t[1], z=t[2]),
            rotation=T("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w),
        ),
    )  # fmt: skip


# The fixed parts of the tree, as (translation, axis, angle); odom -> base_link moves.
MAP_FROM_ODOM = ((1.0, -2.0, 0.0), (0.0, 0.0, 1.0), 0.3)
BASE_FROM_LINK = ((0.2, 0.0, 0.5), (0.0, 1.0, 0.0), 0.1)  # camera mount pitched down 0.1 rad
# camera_link -> optical: rpy = (-pi/2, 0, -pi/2), the quaternion (x, y, z, w) = (-0.5, 0.5, -0.5, 0.5)
# drivers publish: one rotation of 120 deg about (-1, 1, -1) / sqrt(3) = BODY_FROM_OPTICAL (checked below)
LINK_FROM_OPTICAL = ((0.0, 0.0, 0.0), (-1.0, 1.0, -1.0), 2 * math.pi / 3)


def base_motion(ns: int) -> tuple[tuple[float, float, float], float]:
    """odom -> base_link at time ns: translation linear in time, yaw linear in time."""
    s = (ns - T0) / 1e9
    return (0.5 * s, 0.25 * s, 0.0), 0.2 + 0.8 * s


def expected_world_from_cam(ns: int) -> np.ndarray:
    (t_mo, a_mo, g_mo), (t_bl, a_bl, g_bl), (t_lo, a_lo, g_lo) = (
        MAP_FROM_ODOM,
        BASE_FROM_LINK,
        LINK_FROM_OPTICAL,
    )
    t_ob, yaw = base_motion(ns)
    return (
        rigid(axis_angle(a_mo, g_mo), t_mo) @ rigid(axis_angle((0, 0, 1), yaw), t_ob)
        @ rigid(axis_angle(a_bl, g_bl), t_bl) @ rigid(axis_angle(a_lo, g_lo), t_lo)
    )  # fmt: skip


def image_stamp(i: int) -> int:
    return T0 + i * DT


def colour_pixels(i: int) -> np.ndarray:
    return np.random.default_rng(100 + i).integers(0, 256, (H, W, 3), dtype=np.uint8)


def smooth_pixels(i: int) -> np.ndarray:
    """A smooth image (JPEG keeps it close)."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.stack([xx * 15 + i * 10, yy * 20, 255 - xx * 10], -1).clip(0, 255).astype(np.uint8)


def depth_mm(i: int) -> np.ndarray:
    depth = np.random.default_rng(200 + i).integers(500, 4000, (H, W)).astype(np.uint16)
    depth[0, 0] = 0  # no measurement
    return depth


def image_msg(ns: int, frame: str, pixels: np.ndarray, encoding: str, pad: int = 0) -> Any:
    rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
    if pad:
        rows = np.concatenate([rows, np.full((rows.shape[0], pad), 7, np.uint8)], axis=1)
    return T("sensor_msgs/msg/Image")(
        header=header(ns, frame), height=pixels.shape[0], width=pixels.shape[1], encoding=encoding,
        is_bigendian=0, step=rows.shape[1], data=np.ascontiguousarray(rows).reshape(-1),
    )  # fmt: skip


def camera_info(ns: int, frame: str, width: int = W, height: int = H) -> Any:
    return T("sensor_msgs/msg/CameraInfo")(
        header=header(ns, frame), height=height, width=width, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array([FX, 0, CX, 0, FY, CY, 0, 0, 1], np.float64), r=np.eye(3).reshape(-1),
        p=np.array([FX, 0, CX, 0, 0, FY, CY, 0, 0, 0, 1, 0], np.float64), binning_x=0, binning_y=0,
        roi=T("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False),
    )  # fmt: skip


def encode_colour(pixels: np.ndarray, colour: str, ns: int, pad: int) -> tuple[str, Any]:
    import cv2

    frame = OPTICAL
    if colour == "rgb8":
        return "sensor_msgs/msg/Image", image_msg(ns, frame, pixels, "rgb8", pad)
    if colour == "bgr8":
        return "sensor_msgs/msg/Image", image_msg(ns, frame, pixels[:, :, ::-1].copy(), "bgr8", pad)
    if colour == "mono8":
        return "sensor_msgs/msg/Image", image_msg(ns, frame, pixels[:, :, :1].copy(), "mono8", pad)
    if colour == "yuv422":
        return "sensor_msgs/msg/Image", image_msg(ns, frame, pixels[:, :, :2].copy(), "yuv422", pad)
    ok, buf = cv2.imencode(".png" if colour == "png" else ".jpg", pixels[:, :, ::-1])
    assert ok
    return "sensor_msgs/msg/CompressedImage", T("sensor_msgs/msg/CompressedImage")(
        header=header(ns, frame), format=f"rgb8; {colour} compressed bgr8", data=buf.reshape(-1),
    )  # fmt: skip


def write_bag(
    path: Path,
    storage: str = "mcap",
    *,
    colour: str = "rgb8",
    depth: str | None = "16UC1",
    poses: str = "tf",
    info: bool = True,
    n: int = N,
    pad: int = 0,
    tf_gap_at: int | None = None,
) -> Path:
    """A rosbag2 bag at ``path`` with ``n`` colour images (``colour``: rgb8, bgr8, mono8, png,
    jpeg, yuv422), depth (``16UC1`` mm, ``32FC1`` m, ``mono16`` (unsupported) or None), CameraInfo
    (``info``) and poses (``tf``, ``pose`` = PoseStamped of the optical frame in map, ``body`` =
    PoseStamped of a REP 103 body frame, ``none``). ``tf_gap_at``: image index whose nearby
    odom -> base_link samples are left out (its pose cannot be looked up within the tolerance)."""
    with Writer(path, version=9, storage_plugin=STORAGES[storage]) as writer:
        conns: dict[str, Any] = {}

        def write(topic: str, msgtype: str, msg: Any, ns: int) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=TS)
            writer.write(conns[topic], ns, TS.serialize_cdr(msg, msgtype))

        if poses == "tf":
            static = [transform("map", "odom", T0, *MAP_FROM_ODOM),
                      transform("base_link", "camera_link", T0, *BASE_FROM_LINK),
                      transform("camera_link", OPTICAL, T0, *LINK_FROM_OPTICAL)]  # fmt: skip
            write("/tf_static", "tf2_msgs/msg/TFMessage", T("tf2_msgs/msg/TFMessage")(transforms=static), T0)
        for i in range(n):
            ns = image_stamp(i)
            if poses == "tf" and i != tf_gap_at:
                for sample in (ns - TF_OFFSET, ns + TF_OFFSET):
                    t, yaw = base_motion(sample)
                    tf = transform("odom", "base_link", sample, t, (0.0, 0.0, 1.0), yaw)
                    write(
                        "/tf", "tf2_msgs/msg/TFMessage", T("tf2_msgs/msg/TFMessage")(transforms=[tf]), sample
                    )
            if poses in ("pose", "body"):
                world_from_x = expected_world_from_cam(ns)
                if poses == "body":
                    world_from_x = world_from_x @ np.linalg.inv(BODY_FROM_OPTICAL)
                from scipy.spatial.transform import Rotation

                qx, qy, qz, qw = Rotation.from_matrix(world_from_x[:3, :3]).as_quat()  # scalar last
                pose = T("geometry_msgs/msg/Pose")(
                    position=T("geometry_msgs/msg/Point")(x=world_from_x[0, 3], y=world_from_x[1, 3],
                                                          z=world_from_x[2, 3]),
                    orientation=T("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
                )  # fmt: skip
                msg = T("geometry_msgs/msg/PoseStamped")(header=header(ns, "map"), pose=pose)
                write("/camera/pose", "geometry_msgs/msg/PoseStamped", msg, ns)
            if info:
                write("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", camera_info(ns, OPTICAL), ns)
            pixels = smooth_pixels(i) if colour == "jpeg" else colour_pixels(i)
            msgtype, msg = encode_colour(pixels, colour, ns, pad)
            topic = "/camera/color/image_raw" + ("/compressed" if msgtype.endswith("CompressedImage") else "")
            write(topic, msgtype, msg, ns + 3_000_000)  # received 3 ms after capture
            if depth is not None:
                mm = depth_mm(i)
                values = mm if depth in ("16UC1", "mono16") else mm.astype(np.float32) / 1000
                if depth == "32FC1":
                    values[0, 1] = np.nan
                dmsg = image_msg(ns + 2_000_000, OPTICAL, values[:, :, None], depth)  # 2 ms after colour
                write(
                    "/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", dmsg, ns + 4_000_000
                )
    return path


def frames_of(reader: RosbagReader) -> list[ImportedFrame | SkippedFrame]:
    return list(reader.iter_frames(range(len(reader))))


def expected_K() -> np.ndarray:
    return np.array([FX, FY, CX + 0.5, CY + 0.5])


# ---------------------------------------------------------------------------------------------


def test_fixture_tf_parts_match_the_ros_conventions() -> None:
    # the camera_link -> optical rotation written to the bag is the fixed one every driver publishes
    rot = axis_angle(*LINK_FROM_OPTICAL[1:])
    assert np.allclose(quat_xyzw(*LINK_FROM_OPTICAL[1:]), (-0.5, 0.5, -0.5, 0.5))
    np.testing.assert_allclose(rot, BODY_FROM_OPTICAL[:3, :3], atol=1e-12)
    # optical z (forward) = link x, optical x (right) = link -y, optical y (down) = link -z
    np.testing.assert_allclose(rot @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rot @ [1, 0, 0], [0, -1, 0], atol=1e-12)


@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_tf_chain_intrinsics_pixels_and_depth(tmp_path: Path, storage: str) -> None:
    bag = write_bag(tmp_path / "bag", storage)
    reader = RosbagReader(bag)
    assert len(reader) == N and reader.warnings() == []
    meta = reader.meta()
    assert meta["image_topic"] == "/camera/color/image_raw"
    assert meta["depth_topic"] == "/camera/aligned_depth_to_color/image_raw"
    assert meta["camera_info_topic"] == "/camera/color/camera_info"
    assert (meta["world_frame"], meta["camera_frame"], meta["pose_source"]) == ("map", OPTICAL, "tf")
    frames = frames_of(reader)
    assert all(isinstance(f, ImportedFrame) for f in frames)
    for i, frame in enumerate(frames):
        assert isinstance(frame, ImportedFrame)
        assert frame.stamp_ns == image_stamp(i)  # the header stamp, not the bag's receive time
        np.testing.assert_array_equal(frame.K, expected_K())
        np.testing.assert_array_equal(frame.rgb, colour_pixels(i))
        assert frame.depth_m is not None and frame.depth_m.dtype == np.float32
        np.testing.assert_array_equal(frame.depth_m, depth_mm(i).astype(np.float32) * np.float32(0.001))
        assert frame.depth_m[0, 0] == 0
        # odom -> base_link interpolated halfway between its samples: exactly the motion at the stamp
        np.testing.assert_allclose(frame.world_from_cam, expected_world_from_cam(image_stamp(i)), atol=1e-9)


def test_pose_directions_follow_the_optical_frame(tmp_path: Path) -> None:
    """Independent of the fixture's chain algebra: the camera's forward axis (our +z) points
    where base_link's x points (pitched down by the mount), its right axis (+x) is base -y."""
    frames = frames_of(RosbagReader(write_bag(tmp_path / "bag", n=2)))
    frame = frames[0]
    assert isinstance(frame, ImportedFrame)
    _, yaw = base_motion(image_stamp(0))
    heading = MAP_FROM_ODOM[2] + yaw  # both rotations are about world z
    pitch = BASE_FROM_LINK[2]  # about base y: positive pitches the x axis down
    forward = [math.cos(heading) * math.cos(pitch), math.sin(heading) * math.cos(pitch), -math.sin(pitch)]
    right = [math.sin(heading), -math.cos(heading), 0.0]
    np.testing.assert_allclose(frame.world_from_cam[:3, 2], forward, atol=1e-9)
    np.testing.assert_allclose(frame.world_from_cam[:3, 0], right, atol=1e-9)
    assert frame.world_from_cam[2, 1] < 0  # image down (+y) points down in the world (z up)


@pytest.mark.parametrize("storage", sorted(STORAGES))
@pytest.mark.parametrize("poses", ["pose", "body"])
def test_pose_stamped_topic(tmp_path: Path, storage: str, poses: str) -> None:
    bag = write_bag(tmp_path / "bag", storage, poses=poses, depth=None)
    ros = RosbagOptions(pose_topic="/camera/pose", pose_axes="body" if poses == "body" else "optical")
    reader = RosbagReader(bag, ReaderOptions(load_depth=False), ros)
    assert reader.meta()["pose_source"] == "/camera/pose" and reader.meta()["world_frame"] == "map"
    for i, frame in enumerate(frames_of(reader)):
        assert isinstance(frame, ImportedFrame) and frame.depth_m is None
        np.testing.assert_allclose(frame.world_from_cam, expected_world_from_cam(image_stamp(i)), atol=1e-9)


@pytest.mark.parametrize(("colour", "pad"), [("bgr8", 0), ("mono8", 0), ("rgb8", 5), ("png", 0)])
def test_colour_encodings_are_exact(tmp_path: Path, colour: str, pad: int) -> None:
    frames = frames_of(RosbagReader(write_bag(tmp_path / "bag", "sqlite3", colour=colour, pad=pad, n=2)))
    for i, frame in enumerate(frames):
        assert isinstance(frame, ImportedFrame)
        want = colour_pixels(i)
        if colour == "mono8":
            want = np.repeat(want[:, :, :1], 3, axis=2)
        np.testing.assert_array_equal(frame.rgb, want)


def test_jpeg_and_32fc1_depth(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", colour="jpeg", depth="32FC1", n=2)
    reader = RosbagReader(bag)
    assert reader.meta()["image_topic"] == "/camera/color/image_raw/compressed"
    for i, frame in enumerate(frames_of(reader)):
        assert isinstance(frame, ImportedFrame) and frame.depth_m is not None
        assert np.abs(frame.rgb.astype(int) - smooth_pixels(i)).mean() < 4  # JPEG is lossy
        want = depth_mm(i).astype(np.float32) / 1000
        want[0, 1] = 0  # NaN -> no measurement
        np.testing.assert_array_equal(frame.depth_m, want)


def test_pose_tolerance_skips_images_without_nearby_tf(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", tf_gap_at=1)
    frames = frames_of(RosbagReader(bag))  # default 50 ms: image 1 is 90 ms from its nearest samples
    assert isinstance(frames[1], SkippedFrame)
    assert frames[1].reason == "no TF odom -> base_link within 0.05 s"
    assert all(isinstance(frames[i], ImportedFrame) for i in (0, 2, 3))
    loose = frames_of(RosbagReader(bag, ros=RosbagOptions(max_dt_s=0.095)))  # linear across the gap
    assert isinstance(loose[1], ImportedFrame)
    np.testing.assert_allclose(loose[1].world_from_cam, expected_world_from_cam(image_stamp(1)), atol=1e-9)
    nearest = frames_of(RosbagReader(bag, ros=RosbagOptions(pose_interp="nearest")))
    first = nearest[0]
    assert isinstance(first, ImportedFrame)  # samples at -10 ms and +10 ms: the earlier one wins a tie
    np.testing.assert_allclose(
        first.world_from_cam, expected_world_from_cam(image_stamp(0) - TF_OFFSET), atol=1e-9
    )


def test_K_override_without_camera_info(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", info=False, n=2)
    with pytest.raises(ImporterError, match="no CameraInfo for /camera/color/image_raw.*--K fx,fy,cx,cy"):
        RosbagReader(bag)
    frames = frames_of(RosbagReader(bag, ReaderOptions(K=(30.0, 31.0, 8.0, 6.0))))
    assert isinstance(frames[0], ImportedFrame)
    np.testing.assert_array_equal(frames[0].K, [30.0, 31.0, 8.5, 6.5])


def test_errors_name_the_problem_and_list_the_topics(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", n=1)
    with pytest.raises(ImporterError, match=r"--image-topic /nope: the bag has no such topic; its topics: "
                       r".*/camera/color/image_raw \[sensor_msgs/msg/Image, 1 msgs\]"):  # fmt: skip
        RosbagReader(bag, ros=RosbagOptions(image_topic="/nope"))
    with pytest.raises(ImporterError, match="--image-topic /tf_static: has type tf2_msgs/msg/TFMessage"):
        RosbagReader(bag, ros=RosbagOptions(image_topic="/tf_static"))
    with pytest.raises(ImporterError, match="TF has no frame 'world'; frames in the bag: base_link, "):
        RosbagReader(bag, ros=RosbagOptions(world_frame="world"))
    yuv = write_bag(tmp_path / "yuv", colour="yuv422", n=1)
    with pytest.raises(ImporterError, match="colour encoding 'yuv422' is not supported; supported: rgb8"):
        RosbagReader(yuv)
    no_poses = write_bag(tmp_path / "none", poses="none", n=1)
    with pytest.raises(ImporterError, match=r"the bag has no poses: no /tf or /tf_static .* its topics: "):
        RosbagReader(no_poses)
    mono16 = write_bag(tmp_path / "mono16", depth="mono16", n=1)
    with pytest.raises(ImporterError, match="depth topic /camera/aligned_depth_to_color/image_raw: "
                       "sensor_msgs/msg/Image encoding 'mono16' is not supported; .* 16UC1"):  # fmt: skip
        RosbagReader(mono16)
    with pytest.raises(ImporterError, match="--depth-topic and --image-topic are the same topic"):
        RosbagReader(bag, ros=RosbagOptions(depth_topic="/camera/color/image_raw",
                                            image_topic="/camera/color/image_raw"))  # fmt: skip
    (tmp_path / "plain").mkdir()
    with pytest.raises(ImporterError, match="without metadata.yaml"):
        RosbagReader(tmp_path / "plain")
    (tmp_path / "x.bag").write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(ImporterError, match="ROS 1 bag"):
        RosbagReader(tmp_path / "x.bag")


def test_single_storage_file_is_accepted(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", "mcap", n=2)
    (mcap,) = bag.glob("*.mcap")
    frames = frames_of(RosbagReader(mcap))
    assert len(frames) == 2 and all(isinstance(f, ImportedFrame) for f in frames)


@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_cli_writes_a_govrec(tmp_path: Path, storage: str, capsys: pytest.CaptureFixture[str]) -> None:
    from clients.importers.cli import main
    from protocol.recording import read_recording

    bag = write_bag(tmp_path / "bag", storage, tf_gap_at=2)
    out = tmp_path / "bag.govrec"
    assert main(["rosbag", str(bag), "--out", str(out), "--quiet", "--world-frame", "map"]) == 0
    printed = capsys.readouterr().out
    assert "wrote 3 frames (16x12)" in printed and "no TF odom -> base_link within 0.05 s" in printed
    recording = read_recording(out)
    frames = list(recording.frames())
    meta = recording.header.meta
    assert meta["source_format"] == "rosbag" and meta["camera_frame"] == OPTICAL and meta["up_axis"] == "z"
    assert [f.seq for f in frames] == [0, 1, 2]
    for frame, i in zip(frames, (0, 1, 3), strict=True):
        assert frame.stamp_ns == image_stamp(i)
        np.testing.assert_array_equal(frame.K, expected_K())
        np.testing.assert_allclose(frame.world_from_cam, expected_world_from_cam(image_stamp(i)), atol=1e-9)
        np.testing.assert_array_equal(frame.rgb, colour_pixels(i))
        assert frame.depth_m is not None
        np.testing.assert_allclose(frame.depth_m, depth_mm(i) / 1000.0, atol=1e-6)
    # rosbag options with another format are a usage error
    with pytest.raises(SystemExit):
        main(["tum", str(bag), "--out", str(tmp_path / "x.govrec"), "--image-topic", "/x"])
    assert main(["rosbag", str(bag), "--out", str(tmp_path / "y.govrec"), "--image-topic", "/x"]) == 1
    assert "--image-topic /x: the bag has no such topic" in capsys.readouterr().err
    assert not (tmp_path / "y.govrec").exists()


def test_world_frame_below_the_tf_root(tmp_path: Path) -> None:
    """--world-frame odom: the chain goes up from both frames to their common ancestor."""
    frames = frames_of(RosbagReader(write_bag(tmp_path / "bag", n=2), ros=RosbagOptions(world_frame="odom")))
    map_from_odom = rigid(axis_angle(*MAP_FROM_ODOM[1:]), MAP_FROM_ODOM[0])
    for i, frame in enumerate(frames):
        assert isinstance(frame, ImportedFrame)
        want = np.linalg.inv(map_from_odom) @ expected_world_from_cam(image_stamp(i))
        np.testing.assert_allclose(frame.world_from_cam, want, atol=1e-9)


def test_missing_package_names_the_pin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bag = write_bag(tmp_path / "bag", n=1)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # `from rosbags.highlevel ...` fails
    with pytest.raises(ImporterError, match=r"rosbags==0\.11\.9.*'govnesf\[import\]'"):
        RosbagReader(bag)


@pytest.mark.parametrize("colour", ["png", "jpeg"])
def test_compressed_images_decode_with_pillow_without_opencv(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, colour: str
) -> None:
    bag = write_bag(tmp_path / "bag", colour=colour, depth=None, n=2)  # written with OpenCV
    with_cv2 = frames_of(RosbagReader(bag, ReaderOptions(load_depth=False)))
    monkeypatch.setitem(sys.modules, "cv2", None)  # `import cv2` fails: the Pillow path
    without = frames_of(RosbagReader(bag, ReaderOptions(load_depth=False)))
    for i, (a, b) in enumerate(zip(with_cv2, without, strict=True)):
        assert isinstance(a, ImportedFrame) and isinstance(b, ImportedFrame)
        if colour == "png":
            np.testing.assert_array_equal(b.rgb, colour_pixels(i))
        else:  # two JPEG decoders may round a few values differently
            assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 2
