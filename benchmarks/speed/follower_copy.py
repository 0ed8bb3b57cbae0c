"""How far behind a read-only follower (``follow_map``) serves the writer's map: the writer's save
and the follower's load of the same file, as the map grows.

A writer node (in process, the shipped settings without the learned model) takes a simulated room
(``clients.sim``: 160x120 rgb8 with depth and SimLSeg ``ov``, the ``loop`` path) and saves it as
``latest`` every ``--every`` frames; a follower node on the same map directory loads each save
(:meth:`mapper.node.follower.MapFollower.poll_once`). Per save: frames, map voxels, file size, the
save's and the load's seconds, and whether the follower's ``segment_points`` (``average_depth``) and
``query_points`` answers equal the writer's. A follower's copy lags the writer by
``autosave_interval_s`` + the save + ``follow_interval_s`` (at most) + the load.

Run: ``python benchmarks/speed/follower_copy.py [--frames 240 --every 60 --seed 1]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from clients.sim.scenes import CLASS_NAMES
from mapper.node.config import load_config
from mapper.node.service import MapperNode
from protocol.messages import Points, QueryPoints, Save, Segmentation, SegmentPoints, decode, encode


def _frames(seed: int, frames: int) -> list[bytes]:
    from clients.matrix.driver import RunSettings, prepare
    from clients.matrix.scenarios import Scenario

    scenario = Scenario(0, seed, "apartment", "loop", frames, 160, 120, 70.0, "none", "exact", "calibrated",
                        True)
    return [encode(f) for f in prepare(scenario, RunSettings(gt_samples=500, min_class_points=0)).frames]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=240)
    p.add_argument("--every", type=int, default=60, help="frames between the writer's saves")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    frames = _frames(args.seed, args.frames)
    with tempfile.TemporaryDirectory(prefix="govnesf-follow-") as tmp:
        common = {"map_dir": tmp, "serve_model": False, "events_endpoint": "", "save_on_exit": False,
                  "load_autosave_on_start": False, "global_map.integrate_queue": 0}
        writer = MapperNode(load_config(None, {**common, "ingest_endpoint": f"ipc://{tmp}/wi",
                                               "query_endpoint": f"ipc://{tmp}/wq"}))
        follower = MapperNode(load_config(None, {**common, "follow_map": "latest",
                                                 "ingest_endpoint": f"ipc://{tmp}/fi",
                                                 "query_endpoint": f"ipc://{tmp}/fq"}))
        assert follower.follower is not None
        print("| frames | voxels | file MB | save s | load s | same answers |")
        print("|---|---|---|---|---|---|")
        try:
            for n, data in enumerate(frames, start=1):
                writer.handle_ingest(data)
                if n % args.every and n != len(frames):
                    continue
                t0 = time.perf_counter()
                decode(writer.handle_query(encode(Save(name="latest"))), direction="reply")
                t1 = time.perf_counter()
                loaded = follower.follower.poll_once()
                t2 = time.perf_counter()
                snap = writer.state.global_map.snapshot()
                xyz = np.ascontiguousarray(snap.xyz[:: max(1, len(snap) // 5000)])
                same = loaded
                for node_msg in (SegmentPoints(xyz=xyz, texts=list(CLASS_NAMES), method="average_depth"),
                                 QueryPoints(texts=["find the chair"])):
                    mine = decode(writer.handle_query(encode(node_msg)), direction="reply")
                    theirs = decode(follower.handle_query(encode(node_msg)), direction="reply")
                    if isinstance(mine, Segmentation) and isinstance(theirs, Segmentation):
                        same &= bool(np.array_equal(mine.label, theirs.label))
                    elif isinstance(mine, Points) and isinstance(theirs, Points):
                        same &= bool(np.array_equal(mine.xyz, theirs.xyz))
                    else:
                        same = False
                size = (Path(tmp) / "latest.govmap").stat().st_size / 1e6
                row = f"| {n} | {len(snap)} | {size:.1f} | {t1 - t0:.2f} | {t2 - t1:.2f} | {same} |"
                print(row, flush=True)
        finally:
            writer.stop()
            follower.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
