"""A first robot streaming to a node: posed RGB-D frames in, "find the chair" out.

Start a node in one terminal (loopback defaults of launch/node.toml), then run this in another:

    .venv/bin/govnesf serve
    .venv/bin/python examples/first_robot.py --frames 120

The "robot" is the project's simulator (``govnesf[sim]``, installed by ``make demo`` / ``make
test``): it gives, per frame, a colour image, a depth image, the camera intrinsics, the camera pose
and a 2D open-vocabulary feature map, which is what a real robot's driver and onboard 2D model
give. :func:`make_frame` is the part a real robot needs: it builds the wire message from those
arrays (units and conventions: docs/concepts/conventions.md).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from clients.client import MapperClient
from protocol.messages import Error, Frame


# --8<-- [start:make_frame]
def make_frame(
    seq: int,
    stamp_ns: int,
    rgb: np.ndarray,
    K: np.ndarray,
    world_from_cam: np.ndarray,
    depth_m: np.ndarray | None = None,
    ov: np.ndarray | None = None,
    ov_space: str | None = None,
) -> Frame:
    """One frame as the node takes it.

    rgb: (H, W, 3) uint8, R, G, B. K: (4,) fx, fy, cx, cy in pixels. world_from_cam: (4, 4) pose of
    the camera (OpenCV optical axes: x right, y down, z forward) in the world, metres. depth_m:
    (H, W) float32 metres along the optical axis, 0 where unknown; None for a robot without depth.
    ov: (h, w, D) float32 open-vocabulary features in the embedding space ``ov_space``; None if the
    robot has no 2D model. Bad values raise ``ProtocolError`` here, before anything is sent.
    """
    height, width = rgb.shape[:2]
    return Frame(seq=seq, stamp_ns=stamp_ns, width=width, height=height, K=K, world_from_cam=world_from_cam,
                 rgb=rgb, depth_m=depth_m, ov=ov, ov_space=ov_space)
# --8<-- [end:make_frame]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ingest", default="tcp://127.0.0.1:5555", help="the node's ingest endpoint")
    parser.add_argument("--query", default="tcp://127.0.0.1:5556", help="the node's query endpoint")
    parser.add_argument("--frames", type=int, default=120, help="frames to stream (default 120)")
    parser.add_argument("--seed", type=int, default=3, help="simulated room (default 3, the demo's)")
    parser.add_argument("--no-depth", action="store_true", help="stream without depth (an RGB-only robot)")
    args = parser.parse_args(argv)

    from clients.sim.export import RecordConfig, SimStream  # needs govnesf[sim]

    robot = SimStream.build(RecordConfig(seed=args.seed, frames=args.frames, depth=not args.no_depth,
                                         novel_views=0, previews=0))

    def frames():  # what a robot's driver loop would yield
        for sim_frame, _view in robot.frames():
            yield make_frame(sim_frame.seq, sim_frame.stamp_ns, sim_frame.rgb, sim_frame.K,
                             sim_frame.world_from_cam, sim_frame.depth_m, sim_frame.ov, sim_frame.ov_space)

    with MapperClient(ingest=args.ingest, query=args.query, timeout_s=60, retries=1) as client:
        keyframes = 0
        for result in client.send_frames(frames(), window=8):  # pipelined, acks in order
            if isinstance(result.reply, Error):
                print(f"frame {result.index}: {result.reply.code}: {result.reply.message}", file=sys.stderr)
                return 1
            keyframes += result.reply.status == "keyframe"
        status = client.status()
        print(f"sent {args.frames} frames, {keyframes} keyframes; node holds {status.keyframes} "
              f"keyframes in its window, map version {status.map_version}")

        found = client.query_points(["find the chair"])
        if not found.objects:
            print("no chair found")
            return 1
        for obj in found.objects[:3]:
            x, y, z = obj.centroid
            print(f"{obj.text}: ({x:.2f}, {y:.2f}, {z:.2f}) m, score {obj.score:.3f}, {obj.n_points} points")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
