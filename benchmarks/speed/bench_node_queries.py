"""The ``govnesf bench`` phases of the point queries alone, on a real node: ``segment_points``
(``average`` / ``average_depth``, 100k stream points, after an ingest that fills the window) and
``query_points`` on a synthetic 100k-point map (first after the ``load`` and cached, with the
floor). The phases are ``clients/cli/bench.py``'s own functions; this only skips the others
(render, RSS, ...), so it takes a minute instead of the whole bench. Prints JSON.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/bench_node_queries.py --frames 60 --points 100000
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.cli import bench  # noqa: E402
from clients.harness import NodeProcess  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="ingested frames (every one a keyframe)")
    parser.add_argument("--points", type=int, default=100_000, help="segment_points points and map size")
    parser.add_argument("--methods", default="average,average_depth")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="node config override, repeatable (e.g. queries.evicted_views=false)")
    args = parser.parse_args()
    bench.SEGMENT_METHODS = tuple(args.methods.split(","))
    out: dict[str, object] = {"machine": bench.describe_machine()}
    with tempfile.TemporaryDirectory(prefix="govnesf-h11-") as tmp:
        root = Path(tmp)
        node_args = ["--set", "global_map.max_points=2000000", "--set", "poll_interval_s=0.02"]
        for override in args.set:
            node_args += ["--set", override]
        node = NodeProcess(root / "maps", log_path=root / "node.log", extra_args=node_args)
        with node:
            node.wait_ready(timeout_s=120.0)
            t = time.perf_counter()
            out["ingest"] = bench.bench_ingest(node, bench.make_frames(args.frames), query_during=False)
            out["ingest_s"] = round(time.perf_counter() - t, 2)
            with node.client(timeout_s=600.0, retries=0) as client:
                out["settle_s"] = bench.wait_until_settled(client)
                out["segment_points"] = bench.bench_segment(client, args.points, 2)
                out["query_points"] = bench.bench_query_points(client, root / "maps", [args.points], 5, 30)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
