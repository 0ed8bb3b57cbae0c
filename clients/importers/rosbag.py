"""ROS 2 bags (rosbag2: a folder with ``metadata.yaml``, or one ``.mcap`` / ``.db3`` file).

Read with the pure-Python ``rosbags`` package (no ROS installation; the ``[import]`` extra).
The bag must hold:

- colour images: ``sensor_msgs/msg/Image`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``)
  or ``sensor_msgs/msg/CompressedImage`` (JPEG / PNG);
- optionally depth images registered to the colour camera (same size): ``sensor_msgs/msg/Image``
  with ``16UC1`` (millimetres, REP 118) or ``32FC1`` (metres); NaN, inf, <= 0 become 0;
- intrinsics: ``sensor_msgs/msg/CameraInfo`` (``k``, ``width``, ``height``), or ``--K``;
- poses: TF (``/tf`` and ``/tf_static``, ``tf2_msgs/msg/TFMessage``), chained from the world frame
  (``--world-frame``, default ``map``) to the colour image's ``header.frame_id`` (the camera's
  optical frame, REP 103: x right, y down, z forward = our camera frame, so no axis change), or a
  pose topic (``geometry_msgs/msg/PoseStamped``, ``PoseWithCovarianceStamped`` or
  ``nav_msgs/msg/Odometry``) giving the camera's pose in its ``header.frame_id``.

Topics are found by type when there is no doubt (one colour topic, one ``CameraInfo``, ...);
otherwise the import stops and lists the bag's topics with their types. Each colour image is
paired, by its ``header.stamp``, with the nearest depth image within ``max_dt_s`` and with a pose
interpolated between the samples around its stamp (translation linear, rotation slerp), each
within ``max_dt_s`` (``pose_interp="nearest"``: the nearest sample). Static transforms hold at
all times. Images without a partner are skipped and counted.

ROS quaternions are (x, y, z, w) (scalar last), as ``scipy.spatial.transform.Rotation.from_quat``
takes them; a TF ``parent -> child`` transform is ``parent_from_child`` in our naming. See
``docs/concepts/conventions.md`` ("ROS TF") and ``docs/how-to/import.md``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from clients.importers.base import (
    DatasetReader,
    ImportedFrame,
    ImporterError,
    ReaderOptions,
    SkippedFrame,
    half_pixel_K,
    pose_problem,
)

ROSBAGS_PIN = "rosbags==0.11.9"
"""The pinned reader package (the ``[import]`` extra)."""

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
)
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = {"16UC1": 0.001, "32FC1": 1.0}
"""Depth encoding -> metres per unit (16UC1 is millimetres by REP 118)."""
POSE_INTERP = ("linear", "nearest")
POSE_AXES = ("optical", "body")

BODY_FROM_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
"""(4, 4) a REP 103 body / ``camera_link`` frame (x forward, y left, z up) from the camera's
optical frame (x right, y down, z forward): the fixed ``*_link -> *_optical_frame`` rotation
(roll -90 deg, yaw -90 deg) every ROS camera driver publishes."""


@dataclass(frozen=True)
class RosbagOptions:
    """What to read from a bag (the ``rosbag`` options of ``govnesf import``)."""

    image_topic: str | None = None
    """Colour topic (Image or CompressedImage); None = the only one that is not a depth topic."""
    depth_topic: str | None = None
    """Depth topic (Image 16UC1 / 32FC1); None = the only Image topic with "depth" in its name, if
    any (no depth without one)."""
    camera_info_topic: str | None = None
    """CameraInfo topic; None = ``<image topic's namespace>/camera_info``, else the only one."""
    pose_topic: str | None = None
    """PoseStamped / PoseWithCovarianceStamped / Odometry topic; None = TF (``/tf``, ``/tf_static``)."""
    world_frame: str | None = None
    """TF frame the poses are expressed in (default ``map``); with a pose topic, it must equal the
    poses' ``header.frame_id`` (default: whatever they say)."""
    camera_frame: str | None = None
    """TF frame of the camera's optical frame; None = the colour images' ``header.frame_id``."""
    max_dt_s: float = 0.05
    """Largest time between a colour image and the depth image / pose samples it is paired with."""
    pose_interp: str = "linear"
    """``linear`` (interpolate between the samples around the image's stamp) or ``nearest``."""
    pose_axes: str = "optical"
    """Axes of the frame a pose topic describes: ``optical`` (x right, y down, z forward, as TF's
    ``*_optical_frame``) or ``body`` (REP 103 x forward, y left, z up; :data:`BODY_FROM_OPTICAL`
    is applied)."""


def _import_rosbags() -> Any:
    """rosbags' ``AnyReader``; :class:`ImporterError` naming the extra and the pin when missing."""
    from govnesf._extras import MissingExtraError, require

    try:
        highlevel = require("rosbags.highlevel", "import", f"reading ROS 2 bags ({ROSBAGS_PIN}, pure Python)")
    except MissingExtraError as exc:
        raise ImporterError(f"rosbag import: {exc}") from exc
    return highlevel.AnyReader


def stamp_ns(header: Any) -> int:
    """``header.stamp`` (builtin_interfaces/Time: sec, nanosec) in nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _frame_id(name: str) -> str:
    """TF frame ids without the leading slash ROS 1 style bags carry."""
    return name.lstrip("/")


def matrix_from_ros(translation: Any, rotation: Any) -> np.ndarray:
    """(4, 4) float64 from a ROS translation (x, y, z) and quaternion (x, y, z, w), normalised.

    ROS stores the quaternion scalar-last, exactly the order ``Rotation.from_quat`` expects.
    """
    from scipy.spatial.transform import Rotation

    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], dtype=np.float64)
    t = np.array([translation.x, translation.y, translation.z], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    out = np.full((4, 4), np.nan)
    if np.all(np.isfinite(t)) and math.isfinite(norm) and norm > 1e-9:
        out = np.eye(4)
        out[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
        out[:3, 3] = t
    return out


class PoseTrack:
    """Time-stamped rigid transforms (one TF edge, or a pose topic), looked up with a tolerance."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self.static: np.ndarray | None = None
        """(4, 4) a static transform, valid at every time (``/tf_static``)."""

    def add(self, stamp: int, pose: np.ndarray, static: bool = False) -> None:
        if static:
            self.static = pose
        else:
            self._stamps.append(stamp)
            self._poses.append(pose)

    def freeze(self) -> None:
        order = np.argsort(np.asarray(self._stamps, dtype=np.int64), kind="stable")
        self.stamps = np.asarray(self._stamps, dtype=np.int64)[order]
        self.poses = np.stack(self._poses)[order] if self._poses else np.zeros((0, 4, 4))

    def __len__(self) -> int:
        return len(self._stamps) + (self.static is not None)

    def at(self, t: int, max_dt_ns: int, interp: str) -> np.ndarray | None:
        """(4, 4) the transform at time ``t`` (ns), or None without samples within ``max_dt_ns``."""
        if self.static is not None and not len(self.stamps):
            return self.static
        stamps = self.stamps
        if not len(stamps):
            return None
        right = int(np.searchsorted(stamps, t))
        left = right - 1
        if right < len(stamps) and stamps[right] == t:
            return self.poses[right]
        if interp == "linear" and 0 <= left and right < len(stamps):
            if t - stamps[left] <= max_dt_ns and stamps[right] - t <= max_dt_ns:
                return _interpolate(self.poses[left], self.poses[right],
                                    (t - stamps[left]) / (stamps[right] - stamps[left]))  # fmt: skip
        candidates = [
            i for i in (left, right) if 0 <= i < len(stamps) and abs(int(stamps[i]) - t) <= max_dt_ns
        ]
        if not candidates:
            return None
        best = min(candidates, key=lambda i: abs(int(stamps[i]) - t))
        return self.poses[best]


def _interpolate(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """(4, 4) between poses ``a`` (w = 0) and ``b`` (w = 1): translation linear, rotation slerp."""
    from scipy.spatial.transform import Rotation, Slerp

    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return np.full((4, 4), np.nan)
    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))([w]).as_matrix()[
        0
    ]
    out[:3, 3] = (1 - w) * a[:3, 3] + w * b[:3, 3]
    return out


class TfTree:
    """The TF tree of a bag: one :class:`PoseTrack` per ``parent -> child`` edge."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.edges: dict[str, PoseTrack] = {}
        """child frame -> its track of ``parent_from_child``."""

    def add(self, msg: Any, static: bool) -> None:
        for tf in msg.transforms:
            parent, child = _frame_id(tf.header.frame_id), _frame_id(tf.child_frame_id)
            known = self.parent.get(child)
            if known is not None and known != parent:
                raise ImporterError(
                    f"TF frame {child!r} has two parents, {known!r} and {parent!r}; a TF tree allows one"
                )
            self.parent[child] = parent
            track = self.edges.setdefault(child, PoseTrack(f"{parent} -> {child}"))
            track.add(
                stamp_ns(tf.header), matrix_from_ros(tf.transform.translation, tf.transform.rotation), static
            )

    def freeze(self) -> None:
        for track in self.edges.values():
            track.freeze()

    def frames(self) -> list[str]:
        return sorted(set(self.parent) | set(self.parent.values()))

    def _to_root(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.parent:
            chain.append(self.parent[chain[-1]])
            if len(chain) > len(self.parent) + 1:
                raise ImporterError(f"TF has a loop through {frame!r}: {' -> '.join(chain)}")
        return chain

    def chain(self, world: str, camera: str) -> tuple[list[str], list[str]]:
        """Frames from ``world`` up to the common ancestor, and from ``camera`` up to it (both
        inclusive); ImporterError naming the frames when they are not connected."""
        for frame in (world, camera):
            if frame not in self.parent and frame not in self.parent.values():
                raise ImporterError(
                    f"TF has no frame {frame!r}; frames in the bag: {', '.join(self.frames()) or 'none'} "
                    "(set --world-frame / --camera-frame)"
                )
        up_world, up_camera = self._to_root(world), self._to_root(camera)
        common = next((f for f in up_camera if f in up_world), None)
        if common is None:
            raise ImporterError(
                f"TF frames {world!r} and {camera!r} are not connected (roots {up_world[-1]!r} and "
                f"{up_camera[-1]!r})"
            )
        return up_world[: up_world.index(common) + 1], up_camera[: up_camera.index(common) + 1]

    def lookup(
        self, world: str, camera: str, t: int, max_dt_ns: int, interp: str
    ) -> tuple[np.ndarray | None, str]:
        """(4, 4) ``world_from_camera`` at ``t``, or (None, the edge that had no sample near ``t``)."""
        up_world, up_camera = self.chain(world, camera)

        def root_from(chain: list[str]) -> tuple[np.ndarray | None, str]:
            out = np.eye(4)
            for child in chain[:-1]:  # child -> its parent, up to the common ancestor
                track = self.edges[child]
                pose = track.at(t, max_dt_ns, interp)
                if pose is None:
                    return None, track.name
                out = pose @ out
            return out, ""

        common_from_camera, missing = root_from(up_camera)
        if common_from_camera is None:
            return None, missing
        common_from_world, missing = root_from(up_world)
        if common_from_world is None:
            return None, missing
        return np.linalg.inv(common_from_world) @ common_from_camera, ""


# ---------------------------------------------------------------------------------------------
# image decoding


def _rows(msg: Any, channels: int, dtype: np.dtype[Any]) -> np.ndarray:
    """(H, W, channels) view of a raw Image's data honouring ``step`` (row padding) and endianness."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < width * channels * item or data.size < step * height:
        raise ImporterError(
            f"image {width}x{height} {msg.encoding}: step {step} and {data.size} data bytes are too few"
        )
    rows = data[: step * height].reshape(height, step)[:, : width * channels * item]
    stored = np.dtype(dtype).newbyteorder(">" if int(msg.is_bigendian) else "<") if item > 1 else dtype
    arr = np.ascontiguousarray(rows).view(stored)
    return arr.reshape(height, width, channels).astype(np.dtype(dtype).newbyteorder("="), copy=False)


def _decode_compressed(data: np.ndarray, fmt: str, topic: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB from a JPEG / PNG CompressedImage (OpenCV, else Pillow)."""
    if "compresseddepth" in fmt.lower():
        raise ImporterError(
            f"topic {topic}: CompressedImage format {fmt!r} (compressed_depth_image_transport) is not "
            "supported; record the raw depth Image (16UC1 or 32FC1)"
        )
    buf = np.asarray(data, dtype=np.uint8)
    try:
        import cv2
    except ImportError:  # OpenCV is optional here: Pillow decodes JPEG and PNG too
        cv2 = None  # type: ignore[assignment]
    if cv2 is not None:
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if bgr is None:
            raise ImporterError(f"topic {topic}: CompressedImage ({fmt!r}) is not a decodable JPEG/PNG")
        return np.ascontiguousarray(bgr[:, :, ::-1])
    import io

    from PIL import Image as PILImage

    try:
        with PILImage.open(io.BytesIO(buf.tobytes())) as image:
            return np.asarray(image.convert("RGB"), dtype=np.uint8)
    except OSError as exc:
        raise ImporterError(
            f"topic {topic}: CompressedImage ({fmt!r}) is not a decodable JPEG/PNG: {exc}"
        ) from None


def decode_colour(msg: Any, msgtype: str, topic: str) -> np.ndarray:
    """(H, W, 3) uint8 R,G,B from an Image (rgb8/bgr8/rgba8/bgra8/mono8) or CompressedImage."""
    if msgtype == COMPRESSED:
        return _decode_compressed(msg.data, str(msg.format), topic)
    encoding = str(msg.encoding)
    if encoding not in COLOUR_ENCODINGS:
        raise ImporterError(
            f"topic {topic}: colour encoding {encoding!r} is not supported; supported: "
            f"{', '.join(COLOUR_ENCODINGS)} (Image) or JPEG/PNG (CompressedImage)"
        )
    channels = {"mono8": 1, "rgb8": 3, "bgr8": 3}.get(encoding, 4)
    pixels = _rows(msg, channels, np.dtype(np.uint8))
    if encoding == "mono8":
        return np.ascontiguousarray(np.repeat(pixels, 3, axis=2))
    rgb = pixels[:, :, :3] if encoding.startswith("rgb") else pixels[:, :, 2::-1]
    return np.ascontiguousarray(rgb)


def decode_depth(msg: Any, msgtype: str, topic: str) -> np.ndarray:
    """(H, W) float32 metres from an Image in 16UC1 (mm) or 32FC1 (m); invalid -> 0."""
    encoding = str(getattr(msg, "encoding", getattr(msg, "format", "")))
    if msgtype != IMAGE or encoding not in DEPTH_ENCODINGS:
        raise ImporterError(
            f"depth topic {topic}: {msgtype} encoding {encoding!r} is not supported; supported: "
            f"sensor_msgs/msg/Image with {', '.join(DEPTH_ENCODINGS)} (16UC1 = millimetres, 32FC1 = metres)"
        )
    dtype = np.dtype(np.uint16) if encoding == "16UC1" else np.dtype(np.float32)
    raw = _rows(msg, 1, dtype)[:, :, 0]
    depth = raw.astype(np.float32) * np.float32(DEPTH_ENCODINGS[encoding])
    depth[~np.isfinite(depth) | (depth <= 0)] = 0.0
    return depth


# ---------------------------------------------------------------------------------------------
# the reader


@dataclass
class _ImageRef:
    index: int  # position among the topic's messages, in bag order
    stamp: int  # header stamp, ns (bag time when the header has none)


class RosbagReader(DatasetReader):
    format_name = "rosbag"
    description = "ROS 2 bag (rosbag2 folder, .mcap or .db3): Image/CompressedImage, CameraInfo, TF or poses"

    def __init__(
        self, root: Path | str, options: ReaderOptions | None = None, ros: RosbagOptions | None = None
    ) -> None:
        super().__init__(root, options)
        self.ros = ros = ros or RosbagOptions()
        if not (0 < ros.max_dt_s < 10) or not math.isfinite(ros.max_dt_s):
            raise ImporterError(f"--max-dt must be in (0, 10) s, got {ros.max_dt_s}")
        if ros.pose_interp not in POSE_INTERP:
            raise ImporterError(
                f"--pose-interp must be one of {', '.join(POSE_INTERP)}, got {ros.pose_interp!r}"
            )
        if ros.pose_axes not in POSE_AXES:
            raise ImporterError(f"--pose-axes must be one of {', '.join(POSE_AXES)}, got {ros.pose_axes!r}")
        if self.root.suffix == ".bag":
            raise ImporterError(
                f"{str(self.root)!r} is a ROS 1 bag; this importer reads ROS 2 bags (convert it with "
                "`rosbags-convert --src FILE.bag --dst DIR`)"
            )
        if self.root.is_file() and self.root.suffix not in (".mcap", ".db3"):
            raise ImporterError(
                f"{str(self.root)!r} is not a ROS 2 bag: give the bag folder (with metadata.yaml) or a "
                ".mcap / .db3 file"
            )
        if self.root.is_dir() and not (self.root / "metadata.yaml").is_file():
            raise ImporterError(f"{str(self.root)!r} is a folder without metadata.yaml, not a rosbag2 bag")
        self._max_dt_ns = int(round(ros.max_dt_s * 1e9))
        self._warnings: list[str] = []
        any_reader = _import_rosbags()
        try:
            self._bag = any_reader([self.root])
            self._bag.open()
        except Exception as exc:  # rosbags raises its own error types, sqlite and yaml errors
            raise ImporterError(f"cannot open bag {str(self.root)!r}: {exc}") from None
        try:
            self._scan()
        finally:
            self._bag.close()

    # -- topics --------------------------------------------------------------------------------

    def _topics(self) -> dict[str, str]:
        return {c.topic: c.msgtype for c in self._bag.connections}

    def _topic_list(self) -> str:
        counts: dict[str, int] = {}
        for c in self._bag.connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        return "; ".join(f"{t} [{m}, {counts[t]} msgs]" for t, m in sorted(self._topics().items())) or "none"

    def _pick(self, given: str | None, types: Iterable[str], what: str, flag: str,
              prefer: list[str] | None = None, exclude: Iterable[str] = ()) -> str | None:  # fmt: skip
        topics = self._topics()
        types = tuple(types)
        if given is not None:
            if given not in topics:
                raise ImporterError(
                    f"{flag} {given}: the bag has no such topic; its topics: {self._topic_list()}"
                )
            if topics[given] not in types:
                raise ImporterError(
                    f"{flag} {given}: has type {topics[given]}, expected {' or '.join(types)}"
                )
            return given
        candidates = sorted(t for t, m in topics.items() if m in types and t not in set(exclude))
        for p in prefer or []:
            if p in candidates:
                return p
        if len(candidates) == 1:
            return candidates[0]
        if len(candidates) > 1:
            raise ImporterError(
                f"the bag has {len(candidates)} {what} topics ({', '.join(candidates)}); "
                f"choose one with {flag}"
            )
        return None

    def _messages(self, topic: str) -> Iterator[tuple[int, Any]]:
        """(bag time, deserialised message) of ``topic`` in bag order (bag must be open)."""
        conns = [c for c in self._bag.connections if c.topic == topic]
        for conn, bag_time, raw in self._bag.messages(connections=conns):
            try:
                msg = self._bag.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise ImporterError(f"topic {topic}: cannot decode a {conn.msgtype} message: {exc}") from None
            yield int(bag_time), msg

    def _scan(self) -> None:
        ros = self.ros
        topics = self._topics()
        if not topics:
            raise ImporterError(f"bag {str(self.root)!r} holds no topics")
        image_types = (IMAGE, COMPRESSED)
        depth_named = [t for t, m in topics.items() if m == IMAGE and "depth" in t.lower()]
        if self.options.load_depth:
            self.depth_topic = self._pick(
                ros.depth_topic, (IMAGE,), "depth image", "--depth-topic",
                exclude=[t for t in topics if t not in depth_named] if ros.depth_topic is None else (),
            )  # fmt: skip
        else:
            self.depth_topic = None
        image_topic = self._pick(
            ros.image_topic, image_types, "colour image", "--image-topic",
            exclude=[*depth_named, *([self.depth_topic] if self.depth_topic else [])],
        )  # fmt: skip
        if image_topic is None:
            raise ImporterError(
                f"the bag has no colour image topic (sensor_msgs/msg/Image or CompressedImage); its topics: "
                f"{self._topic_list()}"
            )
        self.image_topic = image_topic
        if self.depth_topic == image_topic:
            raise ImporterError(f"--depth-topic and --image-topic are the same topic {image_topic}")
        namespace = image_topic.rsplit("/", 1)[0]
        info_prefer = [f"{namespace}/camera_info", f"{namespace.rsplit('/', 1)[0]}/camera_info"]
        self.camera_info_topic = self._pick(
            ros.camera_info_topic, (CAMERA_INFO,), "CameraInfo", "--camera-info-topic", prefer=info_prefer
        )
        self.pose_topic = (
            self._pick(ros.pose_topic, POSE_TYPES, "pose", "--pose-topic") if ros.pose_topic else None
        )
        tf_topics = [t for t in ("/tf", "/tf_static") if topics.get(t) == TF_MESSAGE]
        if self.pose_topic is None and not tf_topics:
            raise ImporterError(
                "the bag has no poses: no /tf or /tf_static (tf2_msgs/msg/TFMessage) and no --pose-topic "
                f"(PoseStamped, PoseWithCovarianceStamped or Odometry); its topics: {self._topic_list()}"
            )

        # colour images: header stamps and frame id (every message is decoded once here)
        self._images: list[_ImageRef] = []
        frame_ids: set[str] = set()
        zero_stamps = 0
        self._image_type = topics[image_topic]
        first_size: tuple[int, int] | None = None
        for bag_time, msg in self._messages(image_topic):
            stamp = stamp_ns(msg.header)
            if stamp == 0:
                zero_stamps += 1
                stamp = bag_time
            self._images.append(_ImageRef(len(self._images), stamp))
            frame_ids.add(_frame_id(msg.header.frame_id))
            if first_size is None:
                rgb = decode_colour(msg, self._image_type, image_topic)  # fails early on a bad encoding
                first_size = (rgb.shape[1], rgb.shape[0])
        if not self._images or first_size is None:
            raise ImporterError(f"topic {image_topic} has no messages")
        if zero_stamps:
            self._warnings.append(
                f"{zero_stamps} colour images have no header stamp; their bag receive time is used"
            )
        self.image_frame = sorted(frame_ids)[0] if frame_ids else ""
        if len(frame_ids) > 1:
            raise ImporterError(f"topic {image_topic}: images come in several frames {sorted(frame_ids)}")
        self._size = first_size

        self._depth: list[_ImageRef] = []
        if self.depth_topic is not None:
            for bag_time, msg in self._messages(self.depth_topic):
                stamp = stamp_ns(msg.header) or bag_time
                if not self._depth:
                    depth = decode_depth(msg, topics[self.depth_topic], self.depth_topic)
                    if (depth.shape[1], depth.shape[0]) != self._size:
                        raise ImporterError(
                            f"depth topic {self.depth_topic} is {depth.shape[1]}x{depth.shape[0]}, colour "
                            f"{image_topic} is {self._size[0]}x{self._size[1]}: depth must be registered to "
                            "the colour camera (e.g. .../aligned_depth_to_color/image_raw)"
                        )
                self._depth.append(_ImageRef(len(self._depth), stamp))
        elif self.options.load_depth:
            self._warnings.append("no depth topic found: frames carry no depth (--depth-topic to choose one)")

        self._K_dataset, self._distortion = self._intrinsics()
        self._K = half_pixel_K(*self._K_dataset)
        self._poses_from_bag(tf_topics)
        self._pair()

    def _intrinsics(self) -> tuple[tuple[float, float, float, float], list[float]]:
        width, height = self._size
        infos = list(self._messages(self.camera_info_topic)) if self.camera_info_topic else []
        if self.options.K is not None:
            return self.options.K, []
        if not infos:
            raise ImporterError(
                f"no CameraInfo for {self.image_topic}: the bag has no sensor_msgs/msg/CameraInfo topic "
                "(or it is empty); pass --camera-info-topic or --K fx,fy,cx,cy. "
                f"Its topics: {self._topic_list()}"
            )
        _, info = infos[0]
        k = np.asarray(info.k, dtype=np.float64).reshape(-1)
        if k.size != 9 or not np.all(np.isfinite(k)) or k[0] <= 0 or k[4] <= 0:
            raise ImporterError(
                f"{self.camera_info_topic}: K must be 9 finite numbers with fx, fy > 0, got {k}"
            )
        if (int(info.width), int(info.height)) != (width, height):
            raise ImporterError(
                f"{self.camera_info_topic} describes a {info.width}x{info.height} image but "
                f"{self.image_topic} "
                f"is {width}x{height}"
            )
        changed = sum(
            1 for _, other in infos[1:] if not np.allclose(np.asarray(other.k, np.float64).reshape(-1), k)
        )
        if changed:
            self._warnings.append(
                f"{changed} later CameraInfo messages differ from the first; the first is used"
            )
        d = [float(v) for v in np.asarray(getattr(info, "d", []), dtype=np.float64).reshape(-1)]
        if any(d):
            self._warnings.append(
                f"CameraInfo has distortion ({info.distortion_model} {d}); images are imported as they are: "
                "use the rectified topic (image_rect) for exact geometry"
            )
        return (float(k[0]), float(k[4]), float(k[2]), float(k[5])), d

    def _poses_from_bag(self, tf_topics: list[str]) -> None:
        ros = self.ros
        self._tf: TfTree | None = None
        self._track: PoseTrack | None = None
        if self.pose_topic is not None:
            track = PoseTrack(self.pose_topic)
            frames: set[str] = set()
            for bag_time, msg in self._messages(self.pose_topic):
                pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
                world_from_x = matrix_from_ros(pose.position, pose.orientation)
                if ros.pose_axes == "body":
                    world_from_x = world_from_x @ BODY_FROM_OPTICAL
                track.add(stamp_ns(msg.header) or bag_time, world_from_x)
                frames.add(_frame_id(msg.header.frame_id))
            track.freeze()
            if not len(track):
                raise ImporterError(f"pose topic {self.pose_topic} has no messages")
            if len(frames) > 1:
                raise ImporterError(f"pose topic {self.pose_topic}: poses in several frames {sorted(frames)}")
            self.world_frame = frames.pop()
            if ros.world_frame is not None and _frame_id(ros.world_frame) != self.world_frame:
                raise ImporterError(
                    f"--world-frame {ros.world_frame}: the poses of {self.pose_topic} are in "
                    f"{self.world_frame!r}"
                )
            self.camera_frame = self.image_frame
            self._track = track
            return
        tree = TfTree()
        for topic in tf_topics:
            for _, msg in self._messages(topic):
                tree.add(msg, static=topic == "/tf_static")
        tree.freeze()
        self.world_frame = _frame_id(ros.world_frame or "map")
        self.camera_frame = _frame_id(ros.camera_frame or self.image_frame)
        if not self.camera_frame:
            raise ImporterError(
                f"the images of {self.image_topic} have no header.frame_id; pass --camera-frame"
            )
        tree.chain(self.world_frame, self.camera_frame)  # connected, or a clear error now
        if "optical" not in self.camera_frame:
            self._warnings.append(
                f"camera frame {self.camera_frame!r} is not named *_optical_frame: its axes are taken as "
                "optical (x right, y down, z forward), as REP 103 defines for image frames"
            )
        self._tf = tree

    def _pair(self) -> None:
        """Depth partner and pose for each colour image (decided here, before any frame is written)."""
        interp = self.ros.pose_interp
        depth_stamps = np.asarray([d.stamp for d in self._depth], dtype=np.int64)
        order = np.argsort(depth_stamps, kind="stable")
        sorted_stamps = depth_stamps[order]
        self._pairs: list[tuple[int, np.ndarray | None, str]] = []
        for ref in self._images:
            depth_index = -1
            if len(sorted_stamps):
                right = int(np.clip(np.searchsorted(sorted_stamps, ref.stamp), 0, len(sorted_stamps) - 1))
                left = max(right - 1, 0)
                pick = (
                    left
                    if abs(sorted_stamps[left] - ref.stamp) <= abs(sorted_stamps[right] - ref.stamp)
                    else right
                )
                if abs(int(sorted_stamps[pick]) - ref.stamp) <= self._max_dt_ns:
                    depth_index = int(order[pick])
            reason = ""
            pose: np.ndarray | None
            if self._track is not None:
                pose = self._track.at(ref.stamp, self._max_dt_ns, interp)
                if pose is None:
                    reason = f"no pose on {self.pose_topic} within {self.ros.max_dt_s} s"
            else:
                assert self._tf is not None
                pose, edge = self._tf.lookup(
                    self.world_frame, self.camera_frame, ref.stamp, self._max_dt_ns, interp
                )
                if pose is None:
                    reason = f"no TF {edge} within {self.ros.max_dt_s} s"
            if pose is not None:
                reason = pose_problem(pose) or ""
            if not reason and self.depth_topic is not None and depth_index < 0:
                reason = f"no depth image within {self.ros.max_dt_s} s"
            self._pairs.append((depth_index, pose, reason))

    # -- DatasetReader -------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._images)

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        return next(iter(self.iter_frames([index])))

    def iter_frames(self, indices: Iterable[int]) -> Iterator[ImportedFrame | SkippedFrame]:
        """One pass over the bag's colour and depth messages, decoding only the ones needed."""
        wanted = list(indices)
        need_colour = {i for i in wanted if not self._pairs[i][2]}
        need_depth: dict[int, int] = {}  # depth index -> how many wanted frames still use it
        for i in need_colour:
            d = self._pairs[i][0]
            if d >= 0:
                need_depth[d] = need_depth.get(d, 0) + 1
        colour: dict[int, np.ndarray] = {}
        depth: dict[int, np.ndarray] = {}
        position = 0

        def ready() -> Iterator[ImportedFrame | SkippedFrame]:
            nonlocal position
            while position < len(wanted):
                i = wanted[position]
                depth_index, pose, reason = self._pairs[i]
                source = f"{self.image_topic}#{i}"
                if reason:
                    position += 1
                    yield SkippedFrame(source, reason)
                    continue
                if i not in colour or (depth_index >= 0 and depth_index not in depth):
                    return
                depth_m = depth.get(depth_index) if depth_index >= 0 else None
                if depth_index >= 0:
                    need_depth[depth_index] -= 1
                    if not need_depth[depth_index]:
                        del depth[depth_index]
                assert pose is not None
                position += 1
                yield ImportedFrame(
                    rgb=colour.pop(i), depth_m=depth_m, K=self._K.copy(), world_from_cam=pose,
                    stamp_ns=self._images[i].stamp, source=source,
                )  # fmt: skip

        yield from ready()
        if position >= len(wanted):
            return
        topics = [self.image_topic] + ([self.depth_topic] if self.depth_topic and need_depth else [])
        counters = {t: 0 for t in topics}
        with _reopen(self._bag):
            conns = [c for c in self._bag.connections if c.topic in topics]
            for conn, _, raw in self._bag.messages(connections=conns):
                k = counters[conn.topic]
                counters[conn.topic] += 1
                if conn.topic == self.image_topic and k in need_colour:
                    msg = self._bag.deserialize(raw, conn.msgtype)
                    rgb = decode_colour(msg, conn.msgtype, conn.topic)
                    if (rgb.shape[1], rgb.shape[0]) != self._size:
                        raise ImporterError(
                            f"{conn.topic}#{k}: image is {rgb.shape[1]}x{rgb.shape[0]}, the first was "
                            f"{self._size[0]}x{self._size[1]}"
                        )
                    colour[k] = rgb
                elif conn.topic == self.depth_topic and k in need_depth:
                    depth[k] = decode_depth(
                        self._bag.deserialize(raw, conn.msgtype), conn.msgtype, conn.topic
                    )
                else:
                    continue
                yield from ready()
                if position >= len(wanted):
                    return
        yield from ready()

    def meta(self) -> dict[str, Any]:
        return {
            "image_topic": self.image_topic,
            "depth_topic": self.depth_topic,
            "camera_info_topic": self.camera_info_topic,
            "pose_source": self.pose_topic or "tf",
            "world_frame": self.world_frame,
            "camera_frame": self.camera_frame,
            "K_dataset": list(self._K_dataset),
            "distortion": self._distortion,
            "max_dt_s": self.ros.max_dt_s,
            "pose_interp": self.ros.pose_interp,
            "pose_axes": self.ros.pose_axes if self.pose_topic else "optical",
        }

    def warnings(self) -> list[str]:
        return list(self._warnings)


class _reopen:  # noqa: N801 - used like a function: `with _reopen(bag):`
    """Open an AnyReader for the duration of a ``with`` block (the reader keeps it closed between
    passes so that no file handle outlives an import)."""

    def __init__(self, bag: Any) -> None:
        self.bag = bag

    def __enter__(self) -> Any:
        self.bag.open()
        return self.bag

    def __exit__(self, *exc: object) -> None:
        self.bag.close()
