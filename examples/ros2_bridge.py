"""A ROS 2 node that feeds a govnesf mapper node from camera topics and publishes query answers.

**Untested example.** It needs a ROS 2 installation (rclpy, tf2_ros, message_filters,
sensor_msgs; e.g. Humble on Python 3.10) and is not run by the project's tests or CI, where ROS 2
is absent; nothing in the project imports it. The conversions it uses (image decoding, frame
conventions) are the ones ``govnesf import rosbag`` uses and tests
(``clients/importers/rosbag.py``, ``tests/clients/importers/test_importer_rosbag.py``).

What it does:

- subscribes to a colour ``sensor_msgs/Image`` (rgb8/bgr8/rgba8/bgra8/mono8), an optional depth
  ``Image`` registered to it (16UC1 mm / 32FC1 m; pairs by time with
  ``message_filters.ApproximateTimeSynchronizer``) and the camera's ``CameraInfo``;
- looks up ``world_frame -> <image header.frame_id>`` in TF at the image's stamp (the camera's
  optical frame: x right, y down, z forward, the project's camera frame; docs/concepts/conventions.md
  "ROS TF") and sends each frame to the mapper's ingest endpoint (``clients.client.MapperClient``);
- every ``query_period_s`` asks the mapper ``query_points(queries)`` and publishes the matching
  points as ``sensor_msgs/PointCloud2`` on ``~/points`` in ``world_frame``, with float32 fields
  ``x, y, z, score`` and an int32 ``label`` (index into ``queries``).

Run it (with a sourced ROS 2 environment and this repository on PYTHONPATH), next to
``govnesf serve``::

    PYTHONPATH=/path/to/govnesf python3 examples/ros2_bridge.py --ros-args \\
        -p image_topic:=/camera/color/image_raw \\
        -p depth_topic:=/camera/aligned_depth_to_color/image_raw \\
        -p camera_info_topic:=/camera/color/camera_info \\
        -p world_frame:=map -p "queries:=['chair', 'table']"

Parameters (``--ros-args -p name:=value``): ``ingest``, ``query`` (node endpoints, defaults
``tcp://127.0.0.1:5555`` / ``5556``), ``image_topic``, ``depth_topic`` (empty: colour only),
``camera_info_topic``, ``world_frame`` (``map``), ``queries`` (list of texts), ``query_period_s``
(2.0), ``min_score`` (0.0 = the node's default), ``tf_timeout_s`` (0.1), ``sync_slop_s`` (0.02).
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from clients.client import DEFAULT_INGEST, DEFAULT_QUERY, MapperClient
from clients.importers.rosbag import decode_colour, decode_depth, matrix_from_ros
from protocol.messages import Frame

IMAGE = "sensor_msgs/msg/Image"
POINT_FIELDS = (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("score", 12, 7), ("label", 16, 5))
"""PointCloud2 fields: name, byte offset, datatype (7 = FLOAT32, 5 = INT32)."""
POINT_STEP = 20


def frame_from_ros(
    seq: int, image: Any, depth: Any | None, info: Any, world_from_cam: np.ndarray
) -> Frame:
    """A protocol ``Frame`` from ROS messages; K from CameraInfo with pixel centres moved to +0.5."""
    rgb = decode_colour(image, IMAGE, "image")
    depth_m = decode_depth(depth, IMAGE, "depth") if depth is not None else None
    k = np.asarray(info.k, dtype=np.float64)
    K = np.array([k[0], k[4], k[2] + 0.5, k[5] + 0.5])  # (4,) docs/concepts/conventions.md
    stamp_ns = int(image.header.stamp.sec) * 1_000_000_000 + int(image.header.stamp.nanosec)
    return Frame(
        seq=seq, stamp_ns=stamp_ns, width=rgb.shape[1], height=rgb.shape[0], K=K,
        world_from_cam=world_from_cam, rgb=rgb, depth_m=depth_m, rgb_encoding="jpeg",
    )  # fmt: skip


def pack_points(xyz: np.ndarray, score: np.ndarray, label: np.ndarray) -> bytes:
    """(N, 3) float32, (N,) float32, (N,) int32 -> PointCloud2 ``data`` with :data:`POINT_FIELDS`."""
    record = np.dtype({"names": ["x", "y", "z", "score", "label"],
                       "formats": ["<f4", "<f4", "<f4", "<f4", "<i4"],
                       "offsets": [0, 4, 8, 12, 16], "itemsize": POINT_STEP})  # fmt: skip
    out = np.zeros(len(xyz), record)
    out["x"], out["y"], out["z"] = (np.asarray(xyz, np.float32)[:, i] for i in range(3))
    out["score"] = np.asarray(score, np.float32)
    out["label"] = np.asarray(label, np.int32)
    return out.tobytes()


def main(argv: list[str] | None = None) -> int:
    import message_filters
    import rclpy
    import tf2_ros
    from rclpy.duration import Duration
    from rclpy.node import Node
    from rclpy.time import Time
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField

    class Bridge(Node):  # type: ignore[misc]
        def __init__(self) -> None:
            super().__init__("govnesf_bridge")
            p = self.declare_parameter
            self.world_frame = p("world_frame", "map").value
            self.queries = list(p("queries", ["chair"]).value)
            self.min_score = float(p("min_score", 0.0).value) or None
            self.tf_timeout_s = float(p("tf_timeout_s", 0.1).value)
            image_topic = p("image_topic", "/camera/color/image_raw").value
            depth_topic = p("depth_topic", "").value
            info_topic = p("camera_info_topic", "/camera/color/camera_info").value
            self.client = MapperClient(ingest=p("ingest", DEFAULT_INGEST).value,
                                       query=p("query", DEFAULT_QUERY).value, timeout_s=5.0)  # fmt: skip
            self.tf_buffer = tf2_ros.Buffer()
            self.tf_listener = tf2_ros.TransformListener(self.tf_buffer, self)
            self.info: Any = None
            self.seq = 0
            self.create_subscription(CameraInfo, info_topic, self._on_info, 10)
            subs = [message_filters.Subscriber(self, Image, image_topic)]
            if depth_topic:
                subs.append(message_filters.Subscriber(self, Image, depth_topic))
            slop = float(p("sync_slop_s", 0.02).value)
            self.sync = message_filters.ApproximateTimeSynchronizer(subs, queue_size=10, slop=slop)
            self.sync.registerCallback(self._on_images)
            self.points_pub = self.create_publisher(PointCloud2, "~/points", 1)
            self.create_timer(float(p("query_period_s", 2.0).value), self._on_timer)

        def _on_info(self, msg: Any) -> None:
            self.info = msg

        def _on_images(self, image: Any, depth: Any | None = None) -> None:
            if self.info is None:
                self.get_logger().warn("no CameraInfo yet; frame dropped", throttle_duration_sec=5.0)
                return
            try:
                tf = self.tf_buffer.lookup_transform(
                    self.world_frame, image.header.frame_id, Time.from_msg(image.header.stamp),
                    timeout=Duration(seconds=self.tf_timeout_s),
                )  # fmt: skip
            except tf2_ros.TransformException as exc:
                self.get_logger().warn(f"no TF {self.world_frame} -> {image.header.frame_id}: {exc}")
                return
            # a TransformStamped parent -> child is parent_from_child; quaternion (x, y, z, w)
            world_from_cam = matrix_from_ros(tf.transform.translation, tf.transform.rotation)
            ack = self.client.send_frame(frame_from_ros(self.seq, image, depth, self.info, world_from_cam))
            self.seq += 1
            if ack.status == "rejected":
                self.get_logger().warn(f"frame rejected by the mapper: {ack.reason}")

        def _on_timer(self) -> None:
            answer = self.client.query_points(self.queries, min_score=self.min_score)
            msg = PointCloud2()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.header.frame_id = self.world_frame
            msg.height, msg.width = 1, int(answer.xyz.shape[0])
            msg.fields = [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in POINT_FIELDS]
            msg.is_bigendian, msg.is_dense = False, True
            msg.point_step, msg.row_step = POINT_STEP, POINT_STEP * msg.width
            msg.data = pack_points(answer.xyz, answer.score, answer.label)
            self.points_pub.publish(msg)

    rclpy.init(args=argv)
    node = Bridge()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.client.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
