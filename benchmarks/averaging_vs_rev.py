"""``segment_points`` averaging of the working tree against the same code at a git revision.

Builds the window of ``govnesf bench``'s stream in an in-process node (``--frames`` frames of
``clients.cli.bench.make_frames``: 30 keyframes, 384-d ``ov`` on a 20 x 15 grid, depth), takes
``--points`` of the stream's surface points (``stream_points``), and times
:func:`mapper.model.baselines.average_similarities` (what ``segment_points average`` /
``average_depth`` call) of this tree and of ``mapper/model/baselines.py`` as it was at ``--rev``,
alternating, ``--repeats`` times each. Prints min / median seconds of both, the largest
difference of their cosines and whether their view counts are equal.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/averaging_vs_rev.py --rev HEAD~1
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from clients.cli.bench import make_frames, stream_points  # noqa: E402
from mapper.model import baselines  # noqa: E402
from mapper.node.config import config_from_dict  # noqa: E402
from mapper.node.service import MapperNode  # noqa: E402


def _module_at(rev: str, folder: Path) -> object:
    """``mapper/model/baselines.py`` at git revision ``rev``, imported as a module."""
    try:
        text = subprocess.run(["git", "show", f"{rev}:mapper/model/baselines.py"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
    except subprocess.CalledProcessError as exc:
        raise SystemExit(f"--rev {rev!r}: git show failed: {exc.stderr.strip()}") from None
    path = folder / "baselines_at_rev.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("baselines_at_rev", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rev", default="HEAD", help="git revision to compare against (default HEAD)")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--repeats", type=int, default=6)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    if args.frames < 1 or args.points < 1 or args.repeats < 1:
        p.error("--frames, --points and --repeats must be >= 1")
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        before = _module_at(args.rev, Path(tmp))
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        node = MapperNode(config_from_dict({"map_dir": str(Path(tmp) / "maps"), "autosave_name": "",
                                            "save_on_exit": False}))
        try:
            for frame in make_frames(args.frames):
                node.handle_ingest(frame)
            node.drain_integrations()
            views = [(k.ov, k.K, k.world_from_cam, (k.width, k.height), k.depth_m)
                     for k in node.state.window.keyframes if k.ov is not None]
        finally:
            node.stop()
    xyz = stream_points(args.points).astype(np.float32)
    texts = np.random.default_rng(0).normal(size=(4, views[0][0].shape[-1])).astype(np.float32)
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    print(f"{len(views)} keyframes with ov {views[0][0].shape}, {len(xyz)} points, {args.threads} threads")
    for use_depth in (False, True):
        times: dict[str, list[float]] = {"rev": [], "tree": []}
        outs = {}
        for _ in range(args.repeats):
            for name, module in (("rev", before), ("tree", baselines)):
                t = time.perf_counter()
                outs[name] = module.average_similarities(xyz, views, texts, use_depth=use_depth)  # type: ignore[attr-defined]
                times[name].append(time.perf_counter() - t)
        diff = float((outs["rev"][0] - outs["tree"][0]).abs().max())
        same = bool(torch.equal(outs["rev"][1], outs["tree"][1]))
        print(f"{'average_depth' if use_depth else 'average'}: {args.rev} min / median "
              f"{min(times['rev']):.3f} / {statistics.median(times['rev']):.3f} s, this tree "
              f"{min(times['tree']):.3f} / {statistics.median(times['tree']):.3f} s; largest cosine "
              f"difference {diff:.2e}, view counts equal: {same}, views a point "
              f"{float(outs['tree'][1].float().mean()):.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
