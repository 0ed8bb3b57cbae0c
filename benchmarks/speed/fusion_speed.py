"""FusionNet forward alone: the reference pass against the inference pass.

The network of a checkpoint (default ``checkpoints/cpu-small``; ``--random-init`` for an untrained
``cpu-small``) on synthetic inputs with the shapes and memory layouts of the two calls that
dominate the runtime's CPU time:

* ``segment``: ``segment_points`` of ``--segment-points`` points, point mode (no query direction),
  in chunks of the runtime's ``chunk_points`` (4096) with N = ``num_source_views`` slots;
* ``render``: the appearance of a 160 x 120 render with the default ``appearance_groups = 4``
  (92,532 evaluations measured in docs/concepts/rendering.md), in the chunks a 4096-ray chunk makes.

The inputs are laid out as ``GovNeSF.sample_views_indexed`` hands them over ((C, N, P)
storage, P fastest). Each variant runs ``--repeats`` times under ``torch.no_grad`` (how the
runtime calls it), the reference and the fast pass alternating; reported per workload and
``--threads`` setting: median and minimum CPU time (``time.process_time``, less sensitive than
wall time to other jobs on a shared machine) and the median wall time. Run::

    .venv/bin/python benchmarks/speed/fusion_speed.py --threads 1 2 --json out/fusion_speed.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from mapper.model.checkpoint import load_model  # noqa: E402
from mapper.model.config import get_preset  # noqa: E402
from mapper.model.field import GovNeSF  # noqa: E402
from mapper.model.fusion import FusionNet  # noqa: E402


def make_inputs(
    P: int, N: int, feature_dim: int, volume_dim: int, see_prob: float, gen: torch.Generator
) -> tuple[torch.Tensor, ...]:
    """Random (rgb (P,N,3), features (P,N,F), v (P,Dv), dirs (P,N,3), mask (P,N), query (P,3)),
    rgb and features as (P, N, C) views of (C, N, P) storage."""

    def per_point(c: int, randn: bool) -> torch.Tensor:
        buf = torch.randn(c, N, P, generator=gen) if randn else torch.rand(c, N, P, generator=gen)
        return buf.permute(2, 1, 0)

    rgb = per_point(3, False)
    features = per_point(feature_dim, True)
    volume = torch.randn(P, volume_dim, generator=gen)
    dirs = F.normalize(torch.randn(N, P, 3, generator=gen), dim=-1).transpose(0, 1)
    mask = (torch.rand(N, P, generator=gen) < see_prob).T
    query = F.normalize(torch.randn(P, 3, generator=gen), dim=-1)
    return rgb, features, volume, dirs, mask, query


def run_workload(
    net: FusionNet, chunks: list[tuple[torch.Tensor, ...]], with_query: bool, fast: bool
) -> tuple[float, float]:
    """CPU and wall seconds of one pass over the chunks."""
    net.fast_inference = fast
    c0, w0 = time.process_time(), time.perf_counter()
    with torch.no_grad():
        for rgb, feat, v, dirs, mask, query in chunks:
            net(rgb, feat, v, dirs, mask, query if with_query else None)
    return time.process_time() - c0, time.perf_counter() - w0


def _load() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="checkpoints/cpu-small")
    ap.add_argument("--random-init", action="store_true", help="untrained cpu-small FusionNet")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--segment-points", type=int, default=100_000)
    ap.add_argument("--segment-chunk", type=int, default=4096, help="runtime chunk_points")
    ap.add_argument("--render-evals", type=int, default=92_532, help="appearance evaluations of 160x120")
    ap.add_argument("--render-chunk", type=int, default=19_740, help="evaluations per 4096-ray chunk")
    ap.add_argument("--see-prob", type=float, default=0.7, help="fraction of (point, view) pairs seen")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if args.repeats < 1 or min(args.threads) < 1:
        ap.error("--repeats and --threads must be >= 1")

    if args.random_init:
        model = GovNeSF(get_preset("cpu-small"))
        source = "random-init cpu-small"
    else:
        model, _ = load_model(args.checkpoint)
        source = args.checkpoint
    net = model.fusion.eval()
    cfg = model.cfg
    N, Fd, Dv = cfg.num_source_views, cfg.encoder.feature_dim, cfg.volume.volume_feature_dim
    gen = torch.Generator().manual_seed(0)

    def chunks(total: int, size: int) -> list[tuple[torch.Tensor, ...]]:
        sizes = [min(size, total - i) for i in range(0, total, size)]
        return [make_inputs(p, N, Fd, Dv, args.see_prob, gen) for p in sizes]

    workloads = {
        "segment": (chunks(args.segment_points, args.segment_chunk), False),
        "render": (chunks(args.render_evals, args.render_chunk), True),
    }
    rows: list[dict[str, Any]] = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for name, (data, with_query) in workloads.items():
            times: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
            for fast in (False, True):
                run_workload(net, data[:1], with_query, fast)  # warm-up
            for _ in range(args.repeats):  # interleaved, so that load changes hit both alike
                for fast in (False, True):
                    times[fast].append(run_workload(net, data, with_query, fast))
            for fast in (False, True):
                cpu = [t[0] for t in times[fast]]
                wall = [t[1] for t in times[fast]]
                rows.append({
                    "workload": name, "threads": threads, "path": "fast" if fast else "reference",
                    "points": sum(c[0].shape[0] for c in data), "chunks": len(data),
                    "cpu_s": statistics.median(cpu), "cpu_min_s": min(cpu),
                    "wall_s": statistics.median(wall), "cpu_all_s": cpu,
                })  # fmt: skip
                r = rows[-1]
                print(
                    f"{name:8s} threads={threads} {r['path']:9s} cpu {r['cpu_s']:.3f} s "
                    f"(min {r['cpu_min_s']:.3f})  wall {r['wall_s']:.3f} s",
                    flush=True,
                )
    net.fast_inference = True

    proc = platform.processor() or platform.machine()
    lines = [
        f"FusionNet of {source}, N = {N}, torch {torch.__version__}, {proc}",
        "",
        "| workload | points | threads | reference CPU s | fast CPU s | speed-up (median CPU) "
        "| min CPU s ref / fast | reference wall s | fast wall s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for threads in args.threads:
        for name in workloads:
            ref_row, fast_row = (
                next(r for r in rows if (r["workload"], r["threads"], r["path"]) == (name, threads, p))
                for p in ("reference", "fast")
            )
            lines.append(
                f"| {name} | {ref_row['points']:,} | {threads} | {ref_row['cpu_s']:.3f} | "
                f"{fast_row['cpu_s']:.3f} | "
                f"{ref_row['cpu_s'] / max(fast_row['cpu_s'], 1e-9):.2f}x | {ref_row['cpu_min_s']:.3f} / "
                f"{fast_row['cpu_min_s']:.3f} | {ref_row['wall_s']:.3f} | {fast_row['wall_s']:.3f} |"
            )
    print("\n".join(lines))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {"source": source, "load_average": _load(), "rows": rows, "markdown": "\n".join(lines)}
        args.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
