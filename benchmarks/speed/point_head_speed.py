"""`segment_points` with the learned model: the checkpoint's own FusionNet against its point head.

An in-process node serving ``checkpoints/cpu-small`` takes ``govnesf bench``'s stream (``--frames``
frames of ``clients.cli.bench.make_frames``: depth, 384-d ``ov``); then ``ModelRuntime.segment``
answers ``--points`` stream points with the bench's texts, the checkpoint's own FusionNet and each
point head given (``--heads``, default the shipped ``checkpoints/cpu-small-point-head``)
alternating, ``--rounds`` times each, with and without depth-guided masking. Prints the minimum and
median seconds per call, the runtime's ``network`` stage, and how many labels equal the own
network's. No sockets: the node's own overhead is in ``govnesf bench``. ``--kernel-ab``: each
network also with the compiled point kernel and sampling off (``FusionNet.point_kernel`` and
``GovNeSF.compiled_sampling`` False: the torch ops of ``forward_fast`` and of
``sample_views_indexed``), alternating.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/point_head_speed.py
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/point_head_speed.py --kernel-ab
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.cli.bench import SEGMENT_TEXTS, make_frames, stream_points  # noqa: E402
from mapper.model.fusion import FusionNet  # noqa: E402
from mapper.model.point_head import load_point_head  # noqa: E402
from mapper.node.backends.learned import install_learned_backend  # noqa: E402
from mapper.node.config import config_from_dict  # noqa: E402
from mapper.node.service import MapperNode  # noqa: E402
from mapper.runtime.model_runtime import ModelRuntime  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--heads", nargs="*", default=["checkpoints/cpu-small-point-head"])
    p.add_argument("--kernel-ab", action="store_true", help="also each network without its compiled kernel")
    args = p.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = config_from_dict({"map_dir": tmp, "autosave_name": "", "save_on_exit": False,
                                "model": {"point_head": ""}})
        node = MapperNode(cfg)
        runtime = ModelRuntime(cfg.model)
        install_learned_backend(node, runtime)
        try:
            for frame in make_frames(args.frames):
                node.handle_ingest(frame)
            node.ctx.drain_integrations()
            xyz = stream_points(args.points).astype(np.float32)
            sha = runtime.metadata["weights_sha256"]
            own = runtime.model.fusion if runtime.model is not None else None
            heads: dict[str, tuple[FusionNet | None, bool]] = {"own FusionNet": (None, True)}
            heads.update({h: (load_point_head(h, teacher_sha256=sha)[0], True) for h in args.heads})
            if args.kernel_ab:
                heads.update({f"{name}, no kernel": (head, False) for name, (head, _) in list(heads.items())})
            for use_depth in (False, True):
                runtime.point_head = None
                if own is not None and runtime.model is not None:
                    own.point_kernel = runtime.model.compiled_sampling = True
                reference = runtime.segment(xyz, SEGMENT_TEXTS, use_depth=use_depth)[0]  # also a warm-up
                stats: dict[str, list[tuple[float, float, float]]] = {name: [] for name in heads}
                for _ in range(args.rounds):
                    for name, (head, kernel) in heads.items():
                        runtime.point_head = head
                        for net in (head, own):
                            if net is not None:
                                net.point_kernel = kernel
                        if runtime.model is not None:
                            runtime.model.compiled_sampling = kernel
                        t = time.perf_counter()
                        label, _, timing = runtime.segment(xyz, SEGMENT_TEXTS, use_depth=use_depth)
                        dt = time.perf_counter() - t
                        stats[name].append((dt, timing["network"] / 1e3, float(np.mean(label == reference))))
                print(f"segment_points govnesf{' + DGM' if use_depth else ''}, {args.points} points:")
                for name, rows in stats.items():
                    total = [r[0] for r in rows]
                    print(f"  {name}: min {min(total):.3f} s, median {statistics.median(total):.3f} s; "
                          f"network stage min {min(r[1] for r in rows):.3f} s; labels equal to the own "
                          f"network's {100 * min(r[2] for r in rows):.2f}%")
        finally:
            node.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
