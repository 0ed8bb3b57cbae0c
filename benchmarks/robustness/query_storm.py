"""Ingest rate under a query storm vs solo (the storm must leave >= 50 % of the solo rate).

Two runs, each on a fresh ``govnesf serve`` subprocess (``serve_model=false``, loopback):

1. **solo**: stream ``--frames`` pre-encoded frames (160x120 rgb8 + depth + a 384-d
   ``minilm-l6-v2`` OV map at 1/8 resolution whose features are the text embeddings of "floor",
   "rug" and "wall", so semantic queries find real points), ``--window`` in flight;
2. **storm**: the same stream while ``--storm-clients`` closed-loop clients (separate processes,
   like planners) each send, as fast as
   the node answers, a rotation of ``query_points`` ("rug", objects on), ``status`` and
   ``segment_points`` (method ``average``, 2,000 points).

Reports ingest acks/s in both, their ratio, and the storm's answers (by kind, errors by code,
latency percentiles). Writes ``query_storm.json`` and ``query_storm.md`` to ``--out``.

    .venv/bin/python benchmarks/robustness/query_storm.py                     # 300 frames, 4 storm clients
    .venv/bin/python benchmarks/robustness/query_storm.py --frames 100 --storm-clients 2 --out /tmp/storm
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import platform
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from clients.harness import NodeProcess, synthetic_frame  # noqa: E402
from protocol.errors import RemoteError  # noqa: E402
from protocol.messages import Ack, encode  # noqa: E402

WORDS = ("wall", "floor", "rug")
"""Text embeddings used as the OV features of sky (-1), dark (0) and light (1) checker cells."""


def semantic_frames(n: int, width: int, height: int) -> list[bytes]:
    """``n`` encoded frames of the harness camera loop with minilm-l6-v2 OV features."""
    from mapper.ov.encoders import get_text_encoder

    emb = get_text_encoder("minilm-l6-v2").encode(list(WORDS)).astype(np.float16)  # (3, 384)
    out = []
    for seq in range(n):
        frame = synthetic_frame(seq, n, width, height, with_ov=True)
        assert frame.ov is not None
        cls = np.argmax(frame.ov[..., :3].astype(np.float32), axis=-1)  # (h, w) 0 sky, 1 dark, 2 light
        frame.ov = emb[cls]  # (h, w, 384)
        frame.ov_space = "minilm-l6-v2"
        out.append(encode(frame))
    return out


def stream(node: NodeProcess, payloads: list[bytes], window: int) -> dict[str, Any]:
    statuses: Counter[str] = Counter()
    with node.client(timeout_s=30.0, retries=0) as client:
        client.status()
        started = time.perf_counter()
        for result in client.send_frames(payloads, window=window):
            reply = result.reply
            statuses[reply.status if isinstance(reply, Ack) else f"error:{reply.code}"] += 1
        elapsed = time.perf_counter() - started
    return {"frames": len(payloads), "seconds": elapsed, "acks_per_s": len(payloads) / elapsed,
            "acks": dict(statuses)}  # fmt: skip


def storm_client(ingest: str, query: str, stop: Any, out: Any, seed: int) -> None:
    """One storm client, in its own process (planners are other processes: their decoding must not
    share the streaming client's GIL); puts ``(answers, latencies)`` on ``out`` when ``stop`` is set."""
    from clients.client import MapperClient

    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-3, 3, (2000, 3)).astype(np.float32)
    xyz[:, 2] = 0.0
    answers: Counter[str] = Counter()
    latencies: dict[str, list[float]] = {}
    kinds = ("query_points", "status", "segment_points")
    with MapperClient(ingest, query, timeout_s=30.0, retries=0) as client:
        i = seed
        while not stop.is_set():
            kind = kinds[i % len(kinds)]
            i += 1
            t = time.perf_counter()
            try:
                if kind == "query_points":
                    client.query_points(["rug"], objects=True)
                elif kind == "status":
                    client.status()
                else:
                    client.segment_points(xyz, list(WORDS), method="average")
                answers[kind] += 1
            except RemoteError as exc:
                answers[f"{kind}:error:{exc.code}"] += 1
            except TimeoutError:
                answers[f"{kind}:timeout"] += 1
            latencies.setdefault(kind, []).append(time.perf_counter() - t)
    out.put((dict(answers), latencies))


def run_phase(
    payloads: list[bytes], window: int, storm_clients: int, tmp: Path, name: str, node_set: list[str]
) -> dict[str, Any]:
    args = ["--set", "serve_model=false", "--set", "autosave_name=", "--set", "save_on_exit=false"]
    for item in node_set:
        args += ["--set", item]
    with NodeProcess(
        tmp / f"maps-{name}", log_path=tmp / f"{name}.log", extra_args=args, events=False
    ) as node:
        node.wait_ready(timeout_s=120)
        with node.client(timeout_s=120.0, retries=0) as client:  # warm the text encoder: 1 frame + 1 query
            client.send_frame(payloads[0])
            try:
                client.query_points(["rug"])
            except RemoteError:
                pass
        mp = multiprocessing.get_context("spawn")
        stop = mp.Event()
        results = mp.Queue()
        procs = [
            mp.Process(target=storm_client, args=(node.ingest, node.query, stop, results, k), daemon=True)
            for k in range(storm_clients)
        ]
        for p in procs:
            p.start()
        if procs:
            time.sleep(5.0)  # the storm is raging (processes started and connected) before the stream starts
        result = stream(node, payloads[1:], window)
        stop.set()
        outs = [results.get(timeout=120) for _ in procs]
        for p in procs:
            p.join(timeout=60)
        answers: Counter[str] = Counter()
        lat: dict[str, list[float]] = {}
        for o_answers, o_lat in outs:
            answers.update(o_answers)
            for k, v in o_lat.items():
                lat.setdefault(k, []).extend(v)
        with node.client(timeout_s=30.0, retries=0) as client:
            status = client.status()
        result["storm"] = {
            "clients": storm_clients,
            "answers": dict(answers),
            "latency_ms": {
                k: {"p50": 1e3 * statistics.median(v), "p95": 1e3 * sorted(v)[int(0.95 * (len(v) - 1))],
                    "n": len(v)}
                for k, v in lat.items() if v
            },
        }  # fmt: skip
        result["node"] = {"keyframes": status.keyframes, "global_points": status.extra.get("global_points"),
                          "rss_bytes": status.extra.get("rss_bytes")}  # fmt: skip
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--window", type=int, default=8, help="frames in flight")
    parser.add_argument("--storm-clients", type=int, default=4)
    parser.add_argument(
        "--node-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra node config for both runs, e.g. limits.query_share=1.0 (no ingest-first pacing)",
    )
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench")
    args = parser.parse_args(argv)
    payloads = semantic_frames(args.frames + 1, args.width, args.height)
    with tempfile.TemporaryDirectory(prefix="govnesf-storm-") as tmp:
        solo = run_phase(payloads, args.window, 0, Path(tmp), "solo", args.node_set)
        storm = run_phase(payloads, args.window, args.storm_clients, Path(tmp), "storm", args.node_set)
    ratio = storm["acks_per_s"] / solo["acks_per_s"]
    command = "benchmarks/robustness/query_storm.py " + " ".join(sys.argv[1:] if argv is None else argv)
    data = {
        "benchmark": "query_storm", "command": command.strip(), "machine": platform.machine(),
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "solo": solo, "storm": storm, "ratio": ratio, "target_ratio": 0.5,
    }  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "query_storm.json").write_text(json.dumps(data, indent=1) + "\n")
    lines = [
        "# Ingest under a query storm", "", f"`{data['command']}`", "",
        f"- solo: {solo['acks_per_s']:.1f} acks/s ({solo['frames']} frames in {solo['seconds']:.1f} s)",
        f"- storm ({args.storm_clients} clients): {storm['acks_per_s']:.1f} acks/s "
        f"({storm['frames']} frames in {storm['seconds']:.1f} s)",
        f"- ratio storm / solo: **{ratio:.2f}** (target >= 0.50)",
        f"- storm answers: {storm['storm']['answers']} in {storm['seconds']:.1f} s "
        f"of streaming, +5 s before ({sum(storm['storm']['answers'].values()) / (storm['seconds'] + 5):.1f} "
        "requests/s)",
        f"- node config: {args.node_set or 'defaults'}; keyframes acked solo "
        f"{solo['acks'].get('keyframe', 0)}, storm {storm['acks'].get('keyframe', 0)}", "",
        "| request | n | p50 ms | p95 ms |", "|---|---|---|---|",
    ]  # fmt: skip
    for kind, v in storm["storm"]["latency_ms"].items():
        lines.append(f"| {kind} | {v['n']} | {v['p50']:.1f} | {v['p95']:.1f} |")
    (args.out / "query_storm.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
