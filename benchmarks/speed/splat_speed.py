"""Cost of finding the surfaces a render takes from the map: ``mapper.geometry.splat.splat_points``
and ``mapper.node.queries.surface_depth`` (splat, see-through test, hole filling) on synthetic maps.

A synthetic room (10 x 10 m floor and a volume of points up to 3 m; half the points on the floor)
of ``--points`` points, seen by a camera 1.5 m above the floor looking along +x. Reports the best
of ``--repeat`` wall times per size (no torch involved).

    python benchmarks/speed/splat_speed.py --points 100000 1000000 --sizes 160x120 320x240
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from mapper.geometry.splat import splat_points  # noqa: E402
from mapper.node.queries import surface_depth  # noqa: E402
from mapper.runtime.config import ModelRuntimeConfig  # noqa: E402


def room(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(0, 3, n)])
    xyz[: n // 2, 2] = 0.0
    return xyz.astype(np.float32)


def size(text: str) -> tuple[int, int]:
    """``WxH`` -> (W, H), each 1..4096 (argparse type: a clear error otherwise)."""
    w, sep, h = text.partition("x")
    if not (sep and w.isdigit() and h.isdigit() and 1 <= int(w) <= 4096 and 1 <= int(h) <= 4096):
        raise argparse.ArgumentTypeError(f"{text!r}: expected WxH, e.g. 160x120 (each 1..4096)")
    return int(w), int(h)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--points", type=int, nargs="+", default=[100_000, 1_000_000])
    p.add_argument("--sizes", nargs="+", type=size, default=[(160, 120), (320, 240)], metavar="WxH")
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    if min(args.points) < 1 or args.repeat < 1:
        p.error("--points and --repeat must be >= 1")
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float).T  # optical axis along +x
    pose[:3, 3] = [0.0, 0.0, 1.5]
    config = ModelRuntimeConfig()
    print("| map points | size | splat_points ms | surface_depth ms | pixels with a surface |")
    print("|---|---|---|---|---|")
    for n in args.points:
        xyz = room(n)
        for w, h in args.sizes:
            K = np.array([0.9 * w, 0.9 * w, w / 2, h / 2])
            best = [float("inf"), float("inf")]
            for _ in range(args.repeat):
                t = time.perf_counter()
                splat_points(xyz, K, pose, w, h, 0.05)
                best[0] = min(best[0], time.perf_counter() - t)
                t = time.perf_counter()
                z = surface_depth(xyz, 0.05, K, pose, w, h, config)
                best[1] = min(best[1], time.perf_counter() - t)
            print(f"| {n:,} | {w}x{h} | {1e3 * best[0]:.1f} | {1e3 * best[1]:.1f} | {(z > 0).mean():.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
