"""The node's heavy queries in this tree against the same at a git revision: time and answers.

Exports ``--rev`` (``git archive``) into a temporary folder and runs the same measurement in each
tree, in a child process whose imports come from that tree, alternating rev / this tree
``--rounds`` times: an in-process node with the learned model (``checkpoints/cpu-small``) takes
``govnesf bench``'s stream (``--frames`` frames of ``clients.cli.bench.make_frames``: depth,
384-d ``ov``), then answers ``segment_points`` on ``--points`` stream points (``govnesf``,
``govnesf`` with DGM, ``average``, ``average_depth``; ``--shuffle``: the points in one fixed random
order, as an unordered cloud would come) and a 160x120 ``render`` (colour, depth, labels), each
``--repeats`` times after one warm-up. Prints min / median seconds per query and tree, and how
equal the answers are (labels equal, largest score / depth difference).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/queries_vs_rev.py --rev HEAD~1
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
QUERIES = ("govnesf", "govnesf+dgm", "average", "average_depth", "render")


def _worker(out: Path, frames: int, points: int, repeats: int, shuffle: bool) -> None:
    """Runs in a child whose ``mapper`` / ``clients`` / ``protocol`` come from the tree under test."""
    import torch

    from clients.cli.bench import SEGMENT_TEXTS, make_frames, stream_points
    from clients.harness import look_at
    from mapper.node.backends.learned import install_learned_backend
    from mapper.node.config import config_from_dict
    from mapper.node.service import MapperNode
    from mapper.runtime.model_runtime import ModelRuntime
    from protocol import decode, encode
    from protocol.messages import Render, SegmentPoints

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = config_from_dict({"map_dir": tmp, "autosave_name": "", "save_on_exit": False})
        node = MapperNode(cfg)
        runtime = ModelRuntime(cfg.model)
        install_learned_backend(node, runtime)
        try:
            for frame in make_frames(frames):
                node.handle_ingest(frame)
            node.ctx.drain_integrations()
            xyz = stream_points(points).astype(np.float32)
            if shuffle:  # the same permutation in both trees
                xyz = np.ascontiguousarray(xyz[np.random.default_rng(0).permutation(xyz.shape[0])])
            pose = look_at(np.array([3.0, 0.0, 1.5]), np.array([0.0, 0.0, 0.3]))
            msgs = {
                "govnesf": SegmentPoints(xyz=xyz, texts=SEGMENT_TEXTS, method="govnesf"),
                "govnesf+dgm": SegmentPoints(xyz=xyz, texts=SEGMENT_TEXTS, method="govnesf", use_depth=True),
                "average": SegmentPoints(xyz=xyz, texts=SEGMENT_TEXTS, method="average"),
                "average_depth": SegmentPoints(xyz=xyz, texts=SEGMENT_TEXTS, method="average_depth"),
                "render": Render(width=160, height=120, K=np.array([144.0, 144.0, 80.0, 60.0]),
                                 world_from_cam=pose, outputs=["rgb", "depth", "label"], texts=SEGMENT_TEXTS),
            }
            times: dict[str, list[float]] = {}
            arrays: dict[str, np.ndarray] = {}
            for name, msg in msgs.items():
                data = encode(msg)
                node.handle_query(data)  # warm-up
                times[name] = []
                for _ in range(repeats):
                    t = time.perf_counter()
                    reply = decode(node.handle_query(data), direction="reply")
                    times[name].append(time.perf_counter() - t)
                if name == "render":
                    arrays.update(render_label=reply.label, render_depth=reply.depth_m, render_rgb=reply.rgb)
                else:
                    arrays[f"{name}_label"], arrays[f"{name}_score"] = reply.label, reply.score
        finally:
            node.stop()
    np.savez(out, **arrays)
    out.with_suffix(".json").write_text(json.dumps(times))


def _run_in(tree: Path, out: Path, args: argparse.Namespace) -> dict[str, list[float]]:
    env = {**os.environ, "PYTHONPATH": str(tree), "HF_HUB_OFFLINE": "1"}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(out), "--frames", str(args.frames),
           "--points", str(args.points), "--repeats", str(args.repeats)]
    cmd += ["--shuffle"] if args.shuffle else []
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"the measurement in {tree} failed:\n{done.stderr[-2000:]}")
    return json.loads(out.with_suffix(".json").read_text())


def _compare(a: Any, b: Any) -> str:
    parts = []
    for key in sorted(a.files):
        x, y = np.asarray(a[key]), np.asarray(b[key])
        if x.dtype.kind == "f":
            diff = float(np.max(np.abs(x.astype(np.float64) - y))) if x.size else 0.0
            parts.append(f"{key} max diff {diff:.1e}")
        else:
            parts.append(f"{key} equal {100.0 * float(np.mean(x == y)) if x.size else 100.0:.2f}%")
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rev", default="HEAD", help="git revision to compare against (default HEAD)")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--shuffle", action="store_true", help="the points in a random (fixed) order")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2, help="alternations of rev and this tree")
    p.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if min(args.frames, args.points, args.repeats, args.rounds) < 1:
        p.error("--frames, --points, --repeats and --rounds must be >= 1")
    if args.worker is not None:
        _worker(args.worker, args.frames, args.points, args.repeats, args.shuffle)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        rev_tree = Path(tmp) / "rev"
        rev_tree.mkdir()
        archive = subprocess.run(["git", "archive", args.rev], cwd=ROOT, capture_output=True, check=False)
        if archive.returncode != 0:
            raise SystemExit(f"--rev {args.rev!r}: git archive failed: {archive.stderr.decode()[-500:]}")
        subprocess.run(["tar", "-x", "-C", str(rev_tree)], input=archive.stdout, check=True)
        times: dict[str, dict[str, list[float]]] = {t: {q: [] for q in QUERIES} for t in ("rev", "tree")}
        for r in range(args.rounds):
            for label, tree in (("rev", rev_tree), ("tree", ROOT)):
                got = _run_in(tree, Path(tmp) / f"{label}.npz", args)
                for q in QUERIES:
                    times[label][q] += got[q]
                print(f"round {r + 1}: {label} done", flush=True)
        print(f"{args.points} points{' (shuffled)' if args.shuffle else ''}, {args.frames} frames, "
              f"{args.rounds} x {args.repeats} repeats, "
              f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}")
        for q in QUERIES:
            a, b = times["rev"][q], times["tree"][q]
            print(f"{q:>14}: {args.rev} min / median {min(a):.3f} / {statistics.median(a):.3f} s, "
                  f"this tree {min(b):.3f} / {statistics.median(b):.3f} s")
        with np.load(Path(tmp) / "rev.npz") as a, np.load(Path(tmp) / "tree.npz") as b:
            print("answers:", _compare(a, b))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
