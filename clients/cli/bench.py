"""``govnesf bench``: start a real node (subprocess) and measure it; write JSON + Markdown.

What is measured (docs/results.md explains each number and the targets):

* machine: CPU model, cores, RAM, Python, torch / numpy / pyzmq versions;
* ``startup_s``: process spawn to the first ``status`` reply;
* ``ingest``: 160x120 frames with depth and 384-d ``ov`` (20x15 cells, ``minilm-l6-v2``), pipelined,
  acks/s; keyframe integration p50 / p95 (the node's status); while a planner asks
  ``query_points`` back to back on a second connection: its answers/s;
* ``segment_points``: per method (``average``, ``average_depth``, ``govnesf``), seconds for the
  points (back-projected depth pixels of the stream), and per 100k points, once the node has
  settled after the stream (``settle_s``: its ``status`` shows no integrator backlog and no
  pending work in the model or the background workers): the first call (``first_s``; the learned
  model's includes applying the window's last changes) and the median of the repeats after it
  (``per_100k_s``, the steady cost of the query);
* ``render``: 160x120 and 320x240 (rgb, depth, label), the node's stage timings;
* ``status_during_render``: ``status`` and ``query_points`` latency p50 / p95 while a 320x240
  render is in flight (``query_points``: a new question each time, computed; ``_repeat``: the same
  question, from the node's answer cache);
* ``query_points`` on synthetic 10k / 100k / 1M-point maps (``mapper.bench.synthetic_maps`` writes
  them into the node's map directory, the bench ``load``s them): first query after the map changed,
  cached (map unchanged, answer computed), a new text, the same question repeated (the answer
  cache), p50 / p95, and the ratio to the floor (the bare fp32 matrix product of the same size:
  N x 384 by 384 x 7, one text and six negatives, measured here with numpy);
* ``rss``: the node's RSS (status) along a long stream (frames 1000 ... 5000 by default);
* ``floor``: a simulated floor's tour streamed into a second node with its default settings
  (``--floor-rooms``, ``--floor-frames``; `clients.cli.bench_floor`): map points, pruned points,
  RSS, ack and integration p95 of the first and last frames, ``query_points`` over the floor and
  with a ``region``, save and load times.

``--quick`` runs everything tiny (smoke test: the command runs and writes valid JSON with the
expected keys). The bench runs the node and the map writer (``python -m
mapper.bench.synthetic_maps``, :data:`MAP_WRITER`) with its own Python (``sys.executable``): both
ship in the package, so an installed ``govnesf`` runs it as a checkout does.

    govnesf bench --out out/bench/node            # the full run (about half an hour on 2 cores)
    govnesf bench --quick --out /tmp/bench        # smoke
    govnesf bench --floor-rooms 5 --floor-frames 2000 --out out/bench/node   # a smaller floor phase
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from clients.cli.args import floor_rooms, positive_int
from clients.cli.bench_common import _pcts, describe_machine, wait_until_settled
from clients.cli.bench_floor import bench_floor, floor_markdown
from clients.client import MapperClient
from clients.harness import REPO_ROOT, NodeProcess, look_at, render_floor
from protocol.errors import RemoteError
from protocol.messages import Frame, Render, encode

OV_SPACE = "minilm-l6-v2"
OV_DIM = 384
OV_CLASSES = ("floor", "chair", "table")
QUERY_TEXTS = ["find the chair"]
NEW_QUERY_TEXTS = [f"find the {t}" for t in (
    "table", "sofa", "bed", "lamp", "desk", "plant", "sink", "toilet", "door", "window", "curtain", "cabinet",
    "bookshelf", "picture", "counter", "refrigerator", "bathtub", "television", "pillow", "shelf",
)]  # fmt: skip
"""Questions asked once each (``query_points`` ``new_text``: the full scoring product and clustering)."""
SEGMENT_METHODS = ("average", "average_depth", "govnesf")
MAP_WRITER = "mapper.bench.synthetic_maps"
"""The module (run with ``python -m``, the bench never imports ``mapper``) that writes the maps of
the ``query_points`` phase."""
SEGMENT_TEXTS = ["floor", "chair", "table", "wall"]


# -- machine -------------------------------------------------------------------------------------


# -- helpers -------------------------------------------------------------------------------------


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _class_embeddings() -> np.ndarray:
    """(C, 384) unit embeddings of OV_CLASSES (the simulator's text encoder, same space)."""
    from clients.sim.text import get_text_encoder

    return np.asarray(get_text_encoder().encode(list(OV_CLASSES)), np.float32)


def make_frames(n: int, width: int = 160, height: int = 120, seed: int = 0) -> list[bytes]:
    """``n`` encoded frames of a loop around a checkered floor: rgb8, depth, 384-d ov on a 1/8 grid
    (floor cells as "floor" / "table", sky as "chair", plus noise). Pre-encoded, as a robot sends."""
    rng = np.random.default_rng(seed)
    emb = _class_embeddings()
    out = []
    for seq in range(n):
        angle = 2.0 * math.pi * seq / 60.0  # 60 frames a loop; later loops re-observe the same floor
        eye = np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 1.5 + 0.2 * math.sin(seq / 7.0)])
        pose = look_at(eye, np.array([0.0, 0.0, 0.3]))
        K = np.array([0.9 * width, 0.9 * width, width / 2.0, height / 2.0])
        rgb, depth, parity = render_floor(width, height, K, pose)
        small = parity[4::8, 4::8]
        cls = np.where(small < 0, 1, np.where(small == 0, 0, 2))
        ov = emb[cls] + 0.05 * rng.standard_normal((*cls.shape, OV_DIM)).astype(np.float32)
        ov /= np.linalg.norm(ov, axis=-1, keepdims=True)
        frame = Frame(
            seq=seq,
            stamp_ns=1_000_000_000 + seq * 33_333_333,
            width=width,
            height=height,
            K=K,
            world_from_cam=pose,
            rgb=rgb,
            depth_m=depth,
            ov=ov.astype(np.float16),
            ov_space=OV_SPACE,
            id=seq + 1,
        )
        out.append(encode(frame))
    return out


def stream_points(n: int, width: int = 160, height: int = 120) -> np.ndarray:
    """(n, 3) float32 world points on surfaces the stream sees (its depth pixels back-projected)."""
    pts = []
    total, seq = 0, 0
    while total < n:
        angle = 2.0 * math.pi * seq / 60.0
        eye = np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 1.5 + 0.2 * math.sin(seq / 7.0)])
        pose = look_at(eye, np.array([0.0, 0.0, 0.3]))
        K = np.array([0.9 * width, 0.9 * width, width / 2.0, height / 2.0])
        _, depth, _ = render_floor(width, height, K, pose)
        jj, ii = np.nonzero(depth > 0)
        z = depth[jj, ii].astype(np.float64)
        cam = np.stack([(ii + 0.5 - K[2]) / K[0] * z, (jj + 0.5 - K[3]) / K[1] * z, z], axis=1)
        pts.append(cam @ pose[:3, :3].T + pose[:3, 3])
        total += cam.shape[0]
        seq += 7
    return np.concatenate(pts)[:n].astype(np.float32)


# -- phases --------------------------------------------------------------------------------------


def bench_ingest(
    node: NodeProcess, frames: list[bytes], query_during: bool, window: int = 8
) -> dict[str, Any]:
    """Acks/s of a pipelined stream, with a planner asking back to back on another connection."""
    stop = threading.Event()
    answers: list[float] = []
    ages: list[float] = []  # seconds: how old each answer's map snapshot was (the node's answer cache)
    errors: dict[str, int] = {}

    def planner() -> None:
        with node.client(timeout_s=60.0, retries=0) as c:
            while not stop.is_set():
                t0 = time.perf_counter()
                try:
                    reply = c.query_points(QUERY_TEXTS, max_points=100)
                    answers.append(time.perf_counter() - t0)
                    ages.append(reply.timing_ms.get("answer_age_ms", 0.0) / 1e3)
                except RemoteError as exc:  # not_ready before the first features
                    errors[exc.code] = errors.get(exc.code, 0) + 1
                    time.sleep(0.05)

    thread = threading.Thread(target=planner, daemon=True)
    statuses: dict[str, int] = {}
    latencies: list[float] = []
    with node.client(timeout_s=120.0, retries=0) as client:
        if query_during:
            thread.start()
        t0 = time.perf_counter()
        for result in client.send_frames(frames, window=window):
            status = getattr(result.reply, "status", None) or f"error:{getattr(result.reply, 'code', '?')}"
            statuses[status] = statuses.get(status, 0) + 1
            latencies.append(result.latency_s)
        elapsed = time.perf_counter() - t0
        stop.set()
        if query_during:
            thread.join(timeout=120)
        st = client.status()
    return {
        "frames": len(frames),
        "seconds": round(elapsed, 3),
        "acks_per_s": round(len(frames) / elapsed, 2),
        "acks": statuses,
        "ack_latency": _pcts(latencies),
        "pipeline_window": window,
        "integrate_ms_p50": st.extra.get("global_integrate_ms_p50"),
        "integrate_ms_p95": st.extra.get("global_integrate_ms_p95"),
        "integrate_ms_mean": st.extra.get("global_integrate_ms_mean"),
        "planner": {
            "answers": len(answers),
            "answers_per_s": round(len(answers) / elapsed, 2),
            "latency": _pcts(answers),
            "answer_age": _pcts(ages),
            "errors": errors,
        }
        if query_during
        else None,
        "map_points": st.extra.get("global_points"),
    }


def bench_segment(client: MapperClient, n_points: int, repeats: int) -> dict[str, Any]:
    """Per method: the first call (after the stream), then ``repeats`` more; the per-100k figure
    is the repeats' median (the first when there are none)."""
    xyz = stream_points(n_points)
    out: dict[str, Any] = {"points": n_points}
    for method in SEGMENT_METHODS:
        times, timing, err = [], {}, None
        for _ in range(repeats + 1):
            try:
                s, reply = _timed(lambda m=method: client.segment_points(xyz, SEGMENT_TEXTS, method=m))  # type: ignore[misc]
            except RemoteError as exc:
                err = f"{exc.code}: {exc.message}"
                break
            times.append(s)
            timing = reply.timing_ms
        steady = times[1:] or times
        med = statistics.median(steady) if steady else None
        out[method] = {
            "first_s": times[0] if times else None,
            "seconds": steady,
            "per_100k_s": None if med is None else round(med * 1e5 / n_points, 3),
            "node_timing_ms": timing,
            "error": err,
        }
    return out


def _render_msg(width: int, height: int) -> Render:
    pose = look_at(np.array([3.0, 0.0, 1.5]), np.array([0.0, 0.0, 0.3]))
    K = np.array([0.9 * width, 0.9 * width, width / 2.0, height / 2.0])
    return Render(
        width=width,
        height=height,
        K=K,
        world_from_cam=pose,
        outputs=["rgb", "depth", "label"],
        texts=SEGMENT_TEXTS,
    )


def bench_render(client: MapperClient, sizes: list[tuple[int, int]], repeats: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for w, h in sizes:
        times, timing, err = [], {}, None
        for _ in range(repeats):
            s, reply = _timed(lambda w=w, h=h: client.request(_render_msg(w, h), timeout_s=600.0))  # type: ignore[misc]
            if getattr(reply, "code", None):
                err = f"{reply.code}: {reply.message}"
                break
            times.append(s)
            timing = reply.timing_ms
        out[f"{w}x{h}"] = {
            "seconds": times,
            "median_s": statistics.median(times) if times else None,
            "node_timing_ms": timing,
            "error": err,
        }
    return out


def bench_status_during_render(node: NodeProcess, size: tuple[int, int], min_samples: int) -> dict[str, Any]:
    """``status`` and ``query_points`` latency on one connection while another renders."""
    done = threading.Event()
    render_s: list[float] = []

    def renderer() -> None:
        with node.client(timeout_s=600.0, retries=0) as c:
            s, _ = _timed(lambda: c.request(_render_msg(*size), timeout_s=600.0))
            render_s.append(s)
        done.set()

    thread = threading.Thread(target=renderer, daemon=True)
    status_s: list[float] = []
    query_s: list[float] = []
    repeat_s: list[float] = []
    with node.client(timeout_s=120.0, retries=0) as client:
        thread.start()
        time.sleep(0.3)  # let the render reach the worker
        while not done.is_set() or len(status_s) < min_samples:
            status_s.append(_timed(client.status)[0])
            try:  # a new question each time (computed), then the same again (the answer cache)
                ask = functools.partial(client.query_points, QUERY_TEXTS, max_points=100 + len(query_s))
                query_s.append(_timed(ask)[0])
                repeat_s.append(_timed(lambda: client.query_points(QUERY_TEXTS, max_points=100))[0])
            except RemoteError:
                pass
            if done.is_set() and len(status_s) >= min_samples:
                break
        thread.join(timeout=600)
    return {
        "render": f"{size[0]}x{size[1]}",
        "render_s": render_s[0] if render_s else None,
        "status": _pcts(status_s),
        "query_points": _pcts(query_s),
        "query_points_repeat": _pcts(repeat_s),
    }


def matmul_floor_s(n: int, repeats: int) -> float:
    """Seconds of the bare (n, 384) @ (384, 7) fp32 product (the scoring floor): the fastest of
    ``repeats`` (the machine is shared; the fastest run is the least disturbed one)."""
    rng = np.random.default_rng(0)
    feats = rng.standard_normal((n, OV_DIM), dtype=np.float32)
    texts = rng.standard_normal((7, OV_DIM), dtype=np.float32)
    times = [_timed(lambda: feats @ texts.T)[0] for _ in range(repeats)]
    return float(min(times))


def write_synthetic_maps(map_dir: Path, sizes: list[int]) -> None:
    """``points_<N>.govmap`` for each size in ``map_dir``, by :data:`MAP_WRITER` in a child process
    (this tree first on its path, as :class:`~clients.harness.NodeProcess` runs the node)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    subprocess.run(
        [sys.executable, "-m", MAP_WRITER, str(map_dir), *map(str, sizes)],
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
    )


def bench_query_points(
    client: MapperClient, map_dir: Path, sizes: list[int], first_repeats: int, cached_repeats: int
) -> dict[str, Any]:
    """Per map size: ``first`` (right after the ``load``: every cache cold), ``cached`` (the map
    unchanged, a new question each time by its ``max_points``: computed, the per-block labels
    reused), ``new_text`` (another text each time: text encoding, the scoring product and the
    clustering), ``repeat`` (the same question again: the node's answer cache)."""
    write_synthetic_maps(map_dir, sizes)
    out: dict[str, Any] = {}
    for n in sizes:
        first, cached, new_text, repeat, node_timing = [], [], [], [], {}
        for _ in range(first_repeats):
            client.load(f"points_{n}", timeout_s=300.0)  # a new map version: caches start cold
            first.append(_timed(lambda: client.query_points(QUERY_TEXTS, timeout_s=300.0))[0])
        for i in range(cached_repeats):
            ask = functools.partial(client.query_points, QUERY_TEXTS, max_points=10**6 + i, timeout_s=300.0)
            s, reply = _timed(ask)
            cached.append(s)
            node_timing = reply.timing_ms
            repeat.append(_timed(lambda: client.query_points(QUERY_TEXTS, timeout_s=300.0))[0])
        for text in NEW_QUERY_TEXTS[: max(1, cached_repeats)]:
            new_text.append(_timed(functools.partial(client.query_points, [text], timeout_s=300.0))[0])
        floor = matmul_floor_s(n, 20)
        c50 = float(np.percentile(cached, 50)) if cached else math.nan
        n50 = float(np.percentile(new_text, 50)) if new_text else math.nan
        out[str(n)] = {
            "first": _pcts(first),
            "cached": _pcts(cached),
            "new_text": _pcts(new_text),
            "repeat": _pcts(repeat),
            "floor_ms": round(1e3 * floor, 3),
            "cached_p50_over_floor": round(c50 / floor, 2) if floor > 0 else None,
            "new_text_p50_over_floor": round(n50 / floor, 2) if floor > 0 else None,
            "node_timing_ms": node_timing,
        }
    return out


def bench_rss(node: NodeProcess, total: int, every: int, frames_per_loop: list[bytes]) -> dict[str, Any]:
    """RSS (status) every ``every`` frames of a ``total``-frame stream (the loop's frames repeated,
    with fresh seq numbers and stamps, so later loops re-observe the same floor)."""
    from protocol.messages import decode

    samples: list[dict[str, Any]] = []
    base = [decode(f, direction="request") for f in frames_per_loop]

    def frames() -> Any:
        for i in range(total):
            f = base[i % len(base)]
            assert isinstance(f, Frame)
            f.seq, f.stamp_ns, f.id = 10_000_000 + i, 5_000_000_000 + i * 33_333_333, f"rss{i}"
            yield encode(f)

    t0 = time.perf_counter()
    with node.client(timeout_s=120.0, retries=0) as client:
        for k, _ in enumerate(client.send_frames(frames(), window=8), start=1):
            if k % every == 0 or k == total:
                st = client.status()
                samples.append(
                    {
                        "frame": k,
                        "rss_bytes": st.extra.get("rss_bytes"),
                        "memory_bytes": st.memory_bytes,
                        "global_points": st.extra.get("global_points"),
                        "s": round(time.perf_counter() - t0, 1),
                    }
                )
    growth = None
    by_frame = {s["frame"]: s["rss_bytes"] for s in samples}
    if 1000 in by_frame and total in by_frame and by_frame[1000]:
        growth = round(100.0 * (by_frame[total] - by_frame[1000]) / by_frame[1000], 2)
    return {"frames": total, "samples": samples, "growth_pct_from_1000": growth}


# -- report --------------------------------------------------------------------------------------

EXPECTED_KEYS = (
    "machine",
    "settings",
    "startup_s",
    "ingest",
    "segment_points",
    "render",
    "status_during_render",
    "query_points",
    "rss",
    "floor",
)


def to_markdown(r: dict[str, Any]) -> str:
    m = r["machine"]
    lines = [
        f"# govnesf bench ({'quick' if r['settings']['quick'] else 'full'})",
        "",
        f"Machine: {m['cpu_model']}, {m['cpus_usable']} usable of {m['cpu_count']} CPUs, "
        f"{(m['ram_bytes'] or 0) / 2**30:.1f} GiB RAM, Python {m['python']}, torch {m['torch']}, "
        f"numpy {m['numpy']}, load {m['load_avg_1m']}.",
        "",
        f"Node start-up: {r['startup_s']:.2f} s.",
        "",
    ]
    ing = r["ingest"]
    lines += [
        "## Ingest",
        "",
        f"{ing['frames']} frames 160x120 rgb8 + depth + 384-d ov: **{ing['acks_per_s']} acks/s** "
        f"({ing['acks']}), ack latency p50 {ing['ack_latency']['p50_ms']} ms / "
        f"p95 {ing['ack_latency']['p95_ms']} ms; "
        f"keyframe integration p50 {ing['integrate_ms_p50']} ms / p95 {ing['integrate_ms_p95']} ms.",
    ]
    if ing.get("planner"):
        p = ing["planner"]
        lines.append(
            f"Planner asking `query_points` back to back during the stream: {p['answers_per_s']} answers/s "
            f"(p50 {p['latency']['p50_ms']} ms, p95 {p['latency']['p95_ms']} ms); the answers' age "
            f"p50 {p['answer_age']['p50_ms']} ms, p95 {p['answer_age']['p95_ms']} ms."
        )
    seg = r["segment_points"]
    lines += [
        "",
        f"## segment_points ({seg['points']} points; the node settled {seg.get('settle_s', '-')} s "
        "after the stream)",
        "",
        "| method | s per 100k points (median of the repeats) | first call after the stream, s | error |",
        "|---|---|---|---|",
    ]
    for method in SEGMENT_METHODS:
        s = seg[method]
        first = "-" if s.get("first_s") is None else f"{s['first_s']:.3f}"
        lines.append(f"| {method} | {s['per_100k_s']} | {first} | {s['error'] or ''} |")
    lines += ["", "## render", "", "| size | median s | node stages (ms) | error |", "|---|---|---|---|"]
    for size, s in r["render"].items():
        stages = ", ".join(f"{k} {v:.0f}" for k, v in s["node_timing_ms"].items())
        med = "-" if s["median_s"] is None else f"{s['median_s']:.2f}"
        lines.append(f"| {size} | {med} | {stages} | {s['error'] or ''} |")
    sd = r["status_during_render"]
    lines += [
        "",
        f"## Light requests while a {sd['render']} render is in flight",
        "",
        f"status p50 {sd['status']['p50_ms']} ms / p95 {sd['status']['p95_ms']} ms (n={sd['status']['n']}); "
        f"query_points (computed) p50 {sd['query_points']['p50_ms']} ms / "
        f"p95 {sd['query_points']['p95_ms']} ms; "
        f"repeated (answer cache) p50 {sd['query_points_repeat']['p50_ms']} ms / "
        f"p95 {sd['query_points_repeat']['p95_ms']} ms; the render took {sd['render_s']} s.",
    ]
    lines += [
        "",
        "## query_points",
        "",
        "| map points | first p50 / p95 ms | cached p50 / p95 ms | new text p50 / p95 ms "
        "| repeat p50 / p95 ms | floor ms | cached / floor | new text / floor |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, q in r["query_points"].items():
        lines.append(
            f"| {int(n):,} | {q['first']['p50_ms']} / {q['first']['p95_ms']} | {q['cached']['p50_ms']} / "
            f"{q['cached']['p95_ms']} | {q['new_text']['p50_ms']} / {q['new_text']['p95_ms']} | "
            f"{q['repeat']['p50_ms']} / {q['repeat']['p95_ms']} | {q['floor_ms']} | "
            f"{q['cached_p50_over_floor']} | {q['new_text_p50_over_floor']} |"
        )
    rss = r["rss"]
    lines += [
        "",
        f"## RSS over a {rss['frames']}-frame stream",
        "",
        "| frame | RSS MB | map points |",
        "|---|---|---|",
    ]
    for s in rss["samples"]:
        lines.append(f"| {s['frame']} | {(s['rss_bytes'] or 0) / 1e6:.0f} | {s['global_points']} |")
    lines.append(f"\nGrowth from frame 1000 to the end: {rss['growth_pct_from_1000']} %.")
    if r.get("floor"):
        lines += floor_markdown(r["floor"])
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> dict[str, Any]:
    quick = args.quick
    settings = {
        "quick": quick,
        "ingest_frames": 12 if quick else args.frames,
        "segment_points": 500 if quick else 100_000,
        "render_sizes": [(16, 12), (20, 15)] if quick else [(160, 120), (320, 240)],
        "render_repeats": 1 if quick else 2,
        "query_sizes": [1_000] if quick else [10_000, 100_000, 1_000_000],
        "rss_frames": 10 if quick else args.rss_frames,
        "rss_every": 5 if quick else 1000,
        "floor_rooms": 2 if quick else args.floor_rooms,
        "floor_frames": 40 if quick else args.floor_frames,
        "floor_queries": 3 if quick else 30,
        "node_args": [
            "--set",
            "global_map.max_points=2000000",
            "--set",
            "poll_interval_s=0.02",
            *args.node_arg,
        ],
    }
    result: dict[str, Any] = {"machine": describe_machine(), "settings": settings}
    with tempfile.TemporaryDirectory(prefix="govnesf-bench-") as tmp:
        root = Path(tmp)
        node = NodeProcess(root / "maps", log_path=root / "node.log", extra_args=settings["node_args"])
        t0 = time.perf_counter()
        with node:
            node.wait_ready(timeout_s=120.0)
            result["startup_s"] = round(time.perf_counter() - t0, 3)
            frames = make_frames(settings["ingest_frames"])
            print(f"bench: node up in {result['startup_s']:.2f} s; ingest {len(frames)} frames", flush=True)
            result["ingest"] = bench_ingest(node, frames, query_during=True)
            with node.client(timeout_s=600.0, retries=0) as client:
                settle_s = wait_until_settled(client)
                print(f"bench: segment_points (node settled {settle_s:.1f} s after the stream)", flush=True)
                result["segment_points"] = bench_segment(
                    client, settings["segment_points"], 1 if quick else 3
                )
                result["segment_points"]["settle_s"] = settle_s
                print("bench: render", flush=True)
                result["render"] = bench_render(client, settings["render_sizes"], settings["render_repeats"])
            print("bench: status during a render", flush=True)
            result["status_during_render"] = bench_status_during_render(
                node, settings["render_sizes"][-1], 3 if quick else 20
            )
            print("bench: RSS over a long stream", flush=True)
            result["rss"] = bench_rss(node, settings["rss_frames"], settings["rss_every"], frames[:60])
            with node.client(timeout_s=600.0, retries=0) as client:
                print("bench: query_points on synthetic maps", flush=True)
                result["query_points"] = bench_query_points(
                    client, root / "maps", settings["query_sizes"], 1 if quick else 5, 3 if quick else 30
                )
            if node.signal() != 0:
                print(f"bench: the node exited non-zero; log {root / 'node.log'}", file=sys.stderr)
        result["floor"] = None
        if settings["floor_rooms"]:
            print(f"bench: a floor of {settings['floor_rooms']} rooms, {settings['floor_frames']} frames, "
                  "into a node with default settings", flush=True)
            result["floor"] = bench_floor(root, settings["floor_rooms"], settings["floor_frames"],
                                          settings["floor_queries"], list(args.node_arg))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="govnesf bench", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--out", type=Path, default=Path("out/bench/node"), help="output stem (.json and .md)"
    )
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run of every phase")
    parser.add_argument("--frames", type=positive_int, default=300, help="frames of the ingest phase")
    parser.add_argument(
        "--rss-frames", type=positive_int, default=5000, help="frames of the long stream (RSS)"
    )
    parser.add_argument(
        "--floor-rooms", type=floor_rooms, default=20,
        help="rooms of the floor phase's simulated floor (2..30; 0 leaves the phase out; default 20)",
    )
    parser.add_argument(
        "--floor-frames", type=positive_int, default=20_000, help="frames of the floor phase's tour"
    )
    parser.add_argument(
        "--node-arg",
        action="append",
        default=[],
        help="extra argument for `govnesf serve` (repeat; e.g. --node-arg=--set --node-arg=...)",
    )
    args = parser.parse_args(argv)
    try:  # before the run (minutes): an unwritable --out fails now, not after it
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=args.out.parent):
            pass
    except OSError as exc:
        print(f"govnesf bench: cannot write --out {args.out}: {exc}", file=sys.stderr)
        return 2
    result = run(args)
    json_path, md_path = args.out.with_suffix(".json"), args.out.with_suffix(".md")
    json_path.write_text(json.dumps(result, indent=1))
    md_path.write_text(to_markdown(result))
    print(f"bench: wrote {json_path} and {md_path}")
    return 0
