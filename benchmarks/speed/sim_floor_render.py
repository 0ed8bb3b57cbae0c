"""The simulator's ray casting on a floor of rooms: frames per second in one room, on a whole floor
with one ray caster, and with `FloorRenderer` (one caster per band of rooms), per backend.

Poses: ``--poses`` evenly spaced along a ``--frames``-frame `floor_tour` of a ``--rooms``-room floor
(seed ``--seed``), and ``--poses`` of a single room's loop (`generate_scene(seed)`), each rendered at
``--width`` x ``--height`` after one warm-up frame (every band's caster built before the timing).

Run: ``python benchmarks/speed/sim_floor_render.py`` (about a minute on 2 cores with both backends).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.sim.floor_render import FloorRenderer  # noqa: E402
from clients.sim.raycast import SceneRenderer  # noqa: E402
from clients.sim.robot import default_intrinsics, robot_trajectory  # noqa: E402
from clients.sim.scenes import generate_scene  # noqa: E402
from clients.sim.scenes.floor import generate_floor  # noqa: E402
from clients.sim.tour import floor_tour  # noqa: E402


def frames_per_s(renderer: SceneRenderer | FloorRenderer, K: np.ndarray, poses: np.ndarray, w: int,
                 h: int) -> float:
    renderer.render(K, poses[0], w, h)
    t0 = time.perf_counter()
    for pose in poses:
        renderer.render(K, pose, w, h)
    return len(poses) / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rooms", type=int, default=20)
    p.add_argument("--frames", type=int, default=20_000, help="tour length the poses are taken from")
    p.add_argument("--poses", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--backend", action="append", choices=("open3d", "torch"), default=None,
                   help="repeat for several (default: both)")
    args = p.parse_args(argv)
    if args.poses < 1 or args.width < 1 or args.height < 1:
        p.error("--poses, --width and --height must be >= 1")
    floor = generate_floor(args.seed, args.rooms)
    tour = floor_tour(floor, args.frames, seed=args.seed)
    floor_poses = tour.poses[np.linspace(0, args.frames - 1, args.poses).astype(int)]
    room = generate_scene(args.seed)
    room_poses = robot_trajectory(room, args.poses, seed=args.seed)
    K = default_intrinsics(args.width, args.height)
    print(f"{args.rooms}-room floor: {floor.scene.num_faces} triangles; one room {room.num_faces}; "
          f"{args.width}x{args.height}, {args.poses} poses")
    print("| backend | one room | floor, one caster | floor, per band |")
    print("|---|---|---|---|")
    for backend in args.backend or ["open3d", "torch"]:
        banded = FloorRenderer(floor, backend=backend).prepare()
        size = (args.width, args.height)
        one = frames_per_s(SceneRenderer(room, backend=backend), K, room_poses, *size)
        whole = frames_per_s(SceneRenderer(floor.scene, backend=backend), K, floor_poses, *size)
        band = frames_per_s(banded, K, floor_poses, *size)
        print(f"| {backend} | {one:.1f} frames/s | {whole:.1f} frames/s | {band:.1f} frames/s |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
