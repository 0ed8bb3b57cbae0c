"""Ingest with a planner querying, per node configuration (the ingest phase of ``govnesf bench``).

For each configuration (a list of ``--set KEY=VALUE`` for ``govnesf serve``), starts a real node
(learned model served, as ``govnesf bench`` does), streams the bench's pre-encoded 160x120 frames
(rgb8, depth, 384-d ``ov``, every one a keyframe) pipelined 8 deep while a planner asks
``query_points("find the chair")`` back to back on a second connection, then reads ``status``
(integration p50 / p95, the integrator's backlog and lag), saves, and checks that the saved map
holds every acked keyframe (``keyframes_integrated`` of the saved global map). Unlike
``govnesf bench``, it first sends ``--warm-up`` frames and waits for one answer, so the node's
text-encoder load (seconds) does not count against the planner's rate.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/bench_ingest.py --frames 300 --out out/bench/ingest

Writes ``OUT.json`` and prints one Markdown row per configuration. Timings only; nothing here is
a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.cli.bench import QUERY_TEXTS, bench_ingest, describe_machine, make_frames  # noqa: E402
from clients.harness import NodeProcess  # noqa: E402
from mapper.node.store import MapStore  # noqa: E402
from protocol.errors import RemoteError  # noqa: E402

CONFIGS: dict[str, list[str]] = {
    "inline, share 0.3": ["global_map.integrate_queue=0", "limits.query_share=0.3"],
    "background, share 0.3": ["global_map.integrate_queue=16", "limits.query_share=0.3"],
    "background, share 0.6": ["global_map.integrate_queue=16", "limits.query_share=0.6"],
    "background, share 1.0": ["global_map.integrate_queue=16", "limits.query_share=1.0"],
    "inline, share 1.0": ["global_map.integrate_queue=0", "limits.query_share=1.0"],
    "background, share 0.3, answers up to 1 s": [
        "global_map.integrate_queue=16", "limits.query_share=0.3", "queries.answer_max_age_s=1.0"
    ],
    "background, share 0.3, no learned map features": [
        "global_map.integrate_queue=16", "limits.query_share=0.3", "global_map.learned_features=false"
    ],
    "background, share 1.0, no learned map features": [
        "global_map.integrate_queue=16", "limits.query_share=1.0", "global_map.learned_features=false"
    ],
}


def warm_up(node: NodeProcess, frames: list[bytes]) -> float:
    """Send ``frames`` and ask until ``query_points`` answers (the node loads its text encoder on
    the first keyframe with ``ov``: seconds, which would otherwise count against the planner's rate
    during the stream). Returns the seconds it took."""
    t0 = time.perf_counter()
    with node.client(timeout_s=120.0, retries=0) as client:
        list(client.send_frames(frames, window=2))
        deadline = time.monotonic() + 120.0
        while True:
            try:
                client.query_points(QUERY_TEXTS, max_points=100)
                break
            except RemoteError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
    return time.perf_counter() - t0


def run_one(name: str, sets: list[str], frames: list[bytes], warm: int) -> dict[str, Any]:
    args = ["--set", "global_map.max_points=2000000", "--set", "poll_interval_s=0.02"]
    for item in sets:
        args += ["--set", item]
    with tempfile.TemporaryDirectory(prefix="govnesf-bench-ingest-") as tmp:
        root = Path(tmp)
        node = NodeProcess(root / "maps", log_path=root / "node.log", extra_args=args)
        with node:
            node.wait_ready(timeout_s=120.0)
            warm_s = warm_up(node, frames[:warm]) if warm else None
            load = os.getloadavg()[0]
            result = bench_ingest(node, frames[warm:], query_during=True)
            with node.client(timeout_s=120.0, retries=0) as client:
                after = client.status().extra
                t0 = time.perf_counter()
                client.save("bench")
                save_s = time.perf_counter() - t0
                final = client.status()
            _, manifest = MapStore(root / "maps").load("bench")
    return {
        "name": name,
        "sets": sets,
        "load_1min": round(load, 2),
        "warm_up_frames": warm,
        "warm_up_s": None if warm_s is None else round(warm_s, 3),
        **result,
        "integration_after_stream": after.get("integration"),
        "save_s": round(save_s, 3),
        "keyframes_acked": final.extra.get("frames_keyframe"),
        "saved_keyframes_integrated": manifest["global_map"]["keyframes_integrated"],
    }


def row(r: dict[str, Any]) -> str:
    integ = r.get("integration_after_stream") or {}
    planner = r["planner"] or {}
    ack = r["ack_latency"]
    age = planner.get("answer_age") or {}
    return (
        f"| {r['name']} | {r['acks_per_s']} | {ack.get('p50_ms')} / {ack.get('p95_ms')} "
        f"| {r['integrate_ms_p50']} / {r['integrate_ms_p95']} | {planner.get('answers_per_s')} "
        f"(age p50 {age.get('p50_ms')} / p95 {age.get('p95_ms')} ms) "
        f"| {integ.get('backlog')} (waits {integ.get('backpressure_waits')}, "
        f"lag p95 {integ.get('lag_ms_p95')} ms) "
        f"| {r['saved_keyframes_integrated']} of {r['keyframes_acked']} | {r['load_1min']} |"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--out", default="out/bench/ingest")
    parser.add_argument("--only", action="append", default=[], help="run only these configuration names")
    parser.add_argument("--warm-up", type=int, default=2,
                        help="frames sent (and one answered query) before the measured stream; 0 = none")
    args = parser.parse_args()
    frames = make_frames(args.frames + args.warm_up)
    results = []
    for name, sets in CONFIGS.items():
        if args.only and name not in args.only:
            continue
        print(f"bench_ingest: {name}", flush=True)
        results.append(run_one(name, sets, frames, args.warm_up))
        print(row(results[-1]), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {"machine": describe_machine(), "runs": results}
    out.with_suffix(".json").write_text(json.dumps(report, indent=1))
    print("| configuration | acks/s | ack p50 / p95 ms | integrate p50 / p95 ms "
          "| planner answers/s (answer age) | backlog after the stream "
          "| saved map: keyframes integrated | load |")
    for r in results:
        print(row(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
