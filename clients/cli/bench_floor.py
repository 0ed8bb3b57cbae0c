"""``govnesf bench``'s floor phase: a tour of a simulated floor of rooms streamed into a node with
its default settings (docs/results.md, "A floor of rooms").

The simulator (`clients.sim`, a floor of ``rooms`` rooms, `floor_tour`: every room, then the first
two again) renders ``frames`` frames of 160x120 rgb8 with depth and SimLSeg's 384-d ``ov`` while
they are streamed (pipelined, 8 in flight). Measured:

* ``global_points``, ``global_points_pruned`` (and ``global_points_total`` where the node reports
  it) from ``status`` at the end;
* RSS (``status``) every ``every`` frames;
* ack latency p50 / p95 of the first and of the last ``window`` frames (1000, or half the frames
  when fewer), and the node's keyframe integration p50 / p95 after the first ``window`` frames and
  at the end (``status``: its last 1000 keyframes);
* ``query_points`` ("find the chair") once the node has settled (or after a minute:
  ``busy_after_settle`` counts what it still had queued): the first answer (``first_ms``:
  the node builds what its answers share), then p50 / p95 over the whole floor and with a
  ``region`` (the first room's box), each a new question (its ``max_points``), so computed, not
  from the answer cache;
* ``save`` and ``load`` of the map, seconds.

The phase alone (the rest of ``govnesf bench`` left out)::

    python -m clients.cli.bench_floor --rooms 5 --frames 2000 --out out/bench/floor
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from clients.cli.bench_common import _busy_items, _pcts, describe_machine, wait_until_settled
from clients.harness import NodeProcess

FLOOR_QUERY = ["find the chair"]
SETTLE_TIMEOUT_S = 60.0
"""The longest wait for the node to settle after the stream (its ``status`` ``pending`` empty twice
in a row, :func:`clients.cli.bench_common.wait_until_settled`)."""


def bench_floor(root: Path, rooms: int, frames: int, queries: int, node_args: list[str],
                seed: int = 0) -> dict[str, Any]:
    """Start a node (default settings plus ``node_args``) with its maps under ``root``, stream the
    tour, measure (see the module's docstring); the node is stopped at the end."""
    from clients.sim.export import RecordConfig, SimStream

    config = RecordConfig(seed=seed, floor_rooms=rooms, frames=frames, width=160, height=120, depth=True,
                          ov=True)
    t0 = time.perf_counter()
    stream = SimStream.build(config)
    assert stream.floor is not None and stream.tour is not None
    build_s = time.perf_counter() - t0
    window = min(1000, max(1, frames // 2))
    every = 1000 if frames >= 4000 else max(1, frames // 4)
    node = NodeProcess(root / "floor_maps", log_path=root / "floor_node.log", extra_args=node_args)
    with node:
        node.wait_ready(timeout_s=180.0)
        with node.client(timeout_s=300.0, retries=0) as client:
            latencies: list[float] = []
            samples: list[dict[str, Any]] = []
            statuses: dict[str, int] = {}
            integrate_first: dict[str, Any] = {}
            t_stream = time.perf_counter()
            for k, res in enumerate(client.send_frames(_frames(stream), window=8), start=1):
                status = getattr(res.reply, "status", None) or f"error:{getattr(res.reply, 'code', '?')}"
                statuses[status] = statuses.get(status, 0) + 1
                latencies.append(res.latency_s)
                if k % every == 0 or k == frames or k == window:
                    st = client.status()
                    if k == window:
                        integrate_first = _integrate(st.extra)
                    if k % every == 0 or k == frames:
                        samples.append({"frame": k, "rss_bytes": st.extra.get("rss_bytes"),
                                        "global_points": st.extra.get("global_points"),
                                        "s": round(time.perf_counter() - t_stream, 1)})
                        print(f"bench floor: frame {k}/{frames}, {samples[-1]['s']} s, RSS "
                              f"{(st.extra.get('rss_bytes') or 0) / 1e6:.0f} MB, "
                              f"{st.extra.get('global_points')} map points", flush=True)
            stream_s = time.perf_counter() - t_stream
            settle_s = wait_until_settled(client, timeout_s=SETTLE_TIMEOUT_S)
            st = client.status()
            extra = st.extra
            busy = _busy_items(extra)
            room0 = stream.floor.rooms[0]
            box = (np.array([*room0.lo, -0.5]), np.array([*room0.hi, float(room0.size[2]) + 0.5]))
            first_ms = round(1e3 * _seconds(lambda: client.query_points(FLOOR_QUERY, timeout_s=300.0)), 3)
            whole, region = _queries(client, queries, None), _queries(client, queries, box)
            save_s = _seconds(lambda: client.save("floor", timeout_s=600.0))
            load_s = _seconds(lambda: client.load("floor", timeout_s=600.0))
        node.signal()
    return {
        "rooms": rooms, "frames": frames, "seed": seed, "node_args": node_args,
        "tour": {"visits": stream.tour.visits, "step_m": round(stream.tour.step_m, 4),
                 "loop_share": round(stream.tour.loop_share, 3), "build_s": round(build_s, 2)},
        "stream_s": round(stream_s, 1), "frames_per_s": round(frames / max(stream_s, 1e-9), 2),
        "acks": statuses, "settle_s": settle_s, "busy_after_settle": busy,
        "global_points": extra.get("global_points"),
        "global_points_pruned": extra.get("global_points_pruned"),
        "global_points_total": extra.get("global_points_total"),
        "global_max_points": extra.get("global_max_points"),
        "keyframes_integrated": extra.get("global_keyframes_integrated"),
        "rss": samples,
        "window": window,
        "ack_first": _pcts(latencies[:window]), "ack_last": _pcts(latencies[-window:]),
        "integrate_first": integrate_first, "integrate_last": _integrate(extra),
        "query_points": {"first_ms": first_ms, "whole": _pcts(whole), "region": _pcts(region),
                         "region_box": [box[0].tolist(), box[1].tolist()]},
        "save_s": round(save_s, 3), "load_s": round(load_s, 3),
    }


def _frames(stream: Any) -> Iterator[Any]:
    for k, (frame, _) in enumerate(stream.frames()):
        frame.id = k + 1
        yield frame


def _integrate(extra: dict[str, Any]) -> dict[str, Any]:
    return {"p50_ms": extra.get("global_integrate_ms_p50"), "p95_ms": extra.get("global_integrate_ms_p95"),
            "keyframes": extra.get("global_keyframes_integrated")}


def _seconds(fn: Any) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _queries(client: Any, n: int, region: tuple[np.ndarray, np.ndarray] | None) -> list[float]:
    """Seconds of ``n`` computed answers (a new ``max_points`` each: not the answer cache)."""
    out = []
    for i in range(n):
        ask = functools.partial(client.query_points, FLOOR_QUERY, max_points=1000 + i + (0 if region is None
                                                                                          else 500_000),
                                region=region, timeout_s=300.0)
        out.append(_seconds(ask))
    return out


def _pair(p: dict[str, Any]) -> str:
    return f"{p.get('p50_ms')} / {p.get('p95_ms')}"


def floor_markdown(r: dict[str, Any]) -> list[str]:
    """The floor phase's section of the bench report."""
    mb = [f"{s['frame']}: {(s['rss_bytes'] or 0) / 1e6:.0f}" for s in r["rss"]]
    q = r["query_points"]
    return [
        "",
        f"## A floor of {r['rooms']} rooms ({r['frames']} frames, 160x120 + depth + 384-d ov; node defaults "
        f"{' '.join(r['node_args']) or ''})",
        "",
        f"Streamed in {r['stream_s']} s ({r['frames_per_s']} frames/s, the simulator rendering as it goes; "
        f"acks {r['acks']}); global_points {r['global_points']}, pruned {r['global_points_pruned']}, "
        f"total {r['global_points_total']} (max_points {r['global_max_points']}).",
        "",
        "| | first frames | last frames |",
        "|---|---|---|",
        f"| ack p50 / p95 ms ({r['window']} frames) | {_pair(r['ack_first'])} | {_pair(r['ack_last'])} |",
        f"| integration p50 / p95 ms | {_pair(r['integrate_first'])} | {_pair(r['integrate_last'])} |",
        "",
        f"query_points: the first answer {q['first_ms']} ms; p50 / p95: whole floor {_pair(q['whole'])} ms, "
        f"with a region (the first room) {_pair(q['region'])} ms; "
        f"save {r['save_s']} s, load {r['load_s']} s.",
        "",
        "RSS MB by frame: " + ", ".join(mb) + ".",
    ]


def main(argv: list[str] | None = None) -> int:
    """The floor phase alone: JSON and Markdown at ``--out`` (.json, .md)."""
    import argparse
    import json
    import tempfile

    from clients.cli.args import floor_rooms, positive_int

    parser = argparse.ArgumentParser(prog="python -m clients.cli.bench_floor",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--rooms", type=floor_rooms, default=20, help="rooms (2..30; default 20)")
    parser.add_argument("--frames", type=positive_int, default=20_000, help="tour frames (default 20000)")
    parser.add_argument("--queries", type=positive_int, default=30, help="query_points repeats (default 30)")
    parser.add_argument("--out", type=Path, default=Path("out/bench/floor"), help="output stem (.json, .md)")
    parser.add_argument("--node-arg", action="append", default=[], help="extra argument for `govnesf serve`")
    args = parser.parse_args(argv)
    if args.rooms == 0:
        parser.error("--rooms must be 2..30 here")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="govnesf-bench-floor-") as tmp:
        result = {"machine": describe_machine(),
                  "floor": bench_floor(Path(tmp), args.rooms, args.frames, args.queries, list(args.node_arg))}
    args.out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    args.out.with_suffix(".md").write_text("\n".join(floor_markdown(result["floor"])).lstrip() + "\n")
    print(f"bench floor: wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
