"""A bounded soak run on loopback: hours of robot life squeezed into ``--minutes`` (default 10).

A ``govnesf serve`` subprocess (``serve_model=false``, autosave every ``--autosave-s``) gets:

- a streaming client: the harness camera loop (160x120 rgb8 + depth + ``minilm-l6-v2`` OV
  features, as in ``benchmarks/robustness/query_storm.py``), seq increasing forever, at ``--rate`` Hz with
  4 frames in flight; the client library's retries (``timeout_s`` 1 s, 60 retries) carry it
  over the restart;
- a query client: ``query_points("rug")`` and ``status`` every ``--query-interval-s``;
- one ``kill -9`` at ``--kill-at`` (fraction of the run), then an immediate restart on the same
  endpoints and map directory (the autosave is loaded back).

Sampled every ``--sample-s``: frames acked (by status), errors by kind, restarts, and the node's
RSS (``/proc/PID/status`` VmRSS). At the kill, the last autosave's manifest gives the keyframes
acked before the last save that it must hold (``acked_keyframes_lost`` must be 0). Writes
``soak.json`` and ``soak.png`` (matplotlib) to ``--out``.

    nice -n 10 .venv/bin/python benchmarks/robustness/soak.py --minutes 10
    .venv/bin/python benchmarks/robustness/soak.py --minutes 1 --out /tmp/soak
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks" / "robustness"))

from query_storm import semantic_frames  # noqa: E402

from clients.harness import NodeProcess  # noqa: E402
from mapper.node.store import MapStore  # noqa: E402
from protocol.errors import RemoteError  # noqa: E402
from protocol.messages import Ack, Frame, decode  # noqa: E402


def _rss(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        return None
    return None


class Soak:
    def __init__(self, args: argparse.Namespace, tmp: Path) -> None:
        self.args = args
        self.maps = tmp / "maps"
        self.node_args = [
            "--set", "serve_model=false", "--set", "autosave_name=soak",
            "--set", f"autosave_interval_s={args.autosave_s}", "--set", "window.max_keyframes=60",
        ]  # fmt: skip
        self.logs = tmp
        self.nodes: list[NodeProcess] = [self._node(0)]
        self.stop = threading.Event()
        self.lock = threading.Lock()
        self.acks: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()
        self.restarts = 0
        self.epoch = 0
        self.keyframe_acks: list[tuple[int, int, int]] = []  # (epoch, seq, map_version)
        self.queries: Counter[str] = Counter()
        self.latencies: dict[str, list[float]] = {}
        self.samples: list[dict[str, Any]] = []
        self.kill: dict[str, Any] = {}

    def _node(self, index: int) -> NodeProcess:
        node = NodeProcess(
            self.maps, log_path=self.logs / f"node{index}.log", extra_args=self.node_args, events=False
        )
        if index:
            first = self.nodes[0]
            node.ingest, node.query, node.command = first.ingest, first.query, first.command
        return node

    @property
    def node(self) -> NodeProcess:
        return self.nodes[-1]

    def frames(self, base: list[Frame]) -> Iterator[Frame]:
        for seq in itertools.count():
            frame = copy.copy(base[seq % len(base)])
            frame.seq = seq
            frame.stamp_ns = 1_000_000_000 + seq * 100_000_000
            yield frame

    def streamer(self, base: list[Frame]) -> None:
        frames = self.frames(base)
        while not self.stop.is_set():
            try:
                with self.node.client(timeout_s=1.0, retries=60) as client:
                    source = (f for f in frames if not self.stop.is_set())
                    for result in client.send_frames(source, window=4, rate_hz=self.args.rate):
                        reply = result.reply
                        with self.lock:
                            if isinstance(reply, Ack):
                                self.acks[reply.status] += 1
                                if reply.status == "keyframe":
                                    self.keyframe_acks.append((self.epoch, reply.seq, reply.map_version))
                            else:
                                self.errors[f"ingest:{reply.code}"] += 1
                        if self.stop.is_set():
                            break
            except TimeoutError:
                with self.lock:
                    self.errors["ingest:timeout"] += 1

    def querier(self) -> None:
        # a restarted node loads its text encoder again (tens of seconds on a busy machine): a query
        # waits up to 30 s per try
        with self.node.client(timeout_s=30.0, retries=1) as client:
            while not self.stop.wait(self.args.query_interval_s):
                for kind in ("query_points", "status"):
                    t = time.perf_counter()
                    try:
                        if kind == "query_points":
                            client.query_points(["rug"])
                        else:
                            client.status()
                        with self.lock:
                            self.queries[kind] += 1
                            self.latencies.setdefault(kind, []).append(time.perf_counter() - t)
                    except RemoteError as exc:
                        with self.lock:
                            self.errors[f"{kind}:{exc.code}"] += 1
                    except TimeoutError:
                        with self.lock:
                            self.errors[f"{kind}:timeout"] += 1

    def sample(self, t: float) -> None:
        proc = self.node.process
        rss = _rss(proc.pid) if proc is not None and proc.poll() is None else None
        with self.lock:
            self.samples.append({
                "t_s": t, "acked": sum(self.acks.values()), "keyframes_acked": self.acks["keyframe"],
                "errors": sum(self.errors.values()), "restarts": self.restarts, "rss_bytes": rss,
                "queries": sum(self.queries.values()),
            })  # fmt: skip

    def crash_and_restart(self, t: float) -> None:
        proc = self.node.process
        assert proc is not None
        proc.kill()  # SIGKILL
        proc.wait(timeout=10)
        killed_at = time.monotonic()
        _, manifest = MapStore(self.maps).load("soak")
        saved_version, saved_seqs = manifest["map_version"], {e["seq"] for e in manifest["keyframes"]}
        with self.lock:
            self.epoch += 1
            before = [(s, v) for e, s, v in self.keyframe_acks if e == 0 and v <= saved_version]
        in_window_before = {s for s, v in before}
        # every keyframe adds 1 to map_version (epoch 0 starts empty) and the window keeps the newest
        # 60: those of versions (saved - 60, saved] must be in the save; older ones had left the
        # window for the global map before it, legitimately
        must_hold = {s for s, v in before if v > saved_version - 60}
        lost = sorted(must_hold - saved_seqs)
        node = self._node(len(self.nodes))
        self.nodes.append(node)
        node.start()
        node.wait_ready(timeout_s=120)
        with self.lock:
            self.restarts += 1
        self.kill = {
            "at_s": t, "saved_map_version": saved_version, "saved_keyframes": len(saved_seqs),
            "keyframes_acked_before_save": len(in_window_before), "checked_in_window": len(must_hold),
            "acked_keyframes_lost": len(lost), "lost_seqs": lost[:20],
            "restart_s": time.monotonic() - killed_at,
        }  # fmt: skip

    def run(self) -> dict[str, Any]:
        args = self.args
        base = [decode(b, direction="request") for b in semantic_frames(240, 160, 120)]
        frames = [f for f in base if isinstance(f, Frame)]
        self.node.start()
        self.node.wait_ready(timeout_s=120)
        with self.node.client(timeout_s=120.0, retries=0) as client:  # load the node's text encoder first
            client.send_frame(frames[0])
            client.query_points(["rug"])
        threads = [threading.Thread(target=self.streamer, args=(frames,), daemon=True),
                   threading.Thread(target=self.querier, daemon=True)]  # fmt: skip
        started = time.monotonic()
        for thread in threads:
            thread.start()
        duration = 60.0 * args.minutes
        killed = False
        next_sample = 0.0
        try:
            while (t := time.monotonic() - started) < duration:
                if t >= next_sample:
                    self.sample(t)
                    next_sample += args.sample_s
                if not killed and t >= args.kill_at * duration:
                    killed = True
                    self.crash_and_restart(t)
                time.sleep(0.2)
            self.sample(time.monotonic() - started)
        finally:
            self.stop.set()
            for thread in threads:
                thread.join(timeout=30)
            with self.node.client(timeout_s=5.0, retries=2) as client:
                status = client.status()
            try:  # a clean shutdown: final save, exit code 0
                exit_code: int | None = self.node.signal(timeout_s=120.0)
            except subprocess.TimeoutExpired:
                exit_code = None
            for node in self.nodes:
                node.kill()
        rss = [s["rss_bytes"] for s in self.samples if s["rss_bytes"]]
        return {
            "benchmark": "soak",
            "args": {k: v if not isinstance(v, Path) else str(v) for k, v in vars(args).items()},
            "duration_s": time.monotonic() - started,
            "acks": dict(self.acks), "errors": dict(self.errors), "queries": dict(self.queries),
            "restarts": self.restarts, "kill": self.kill,
            "query_latency_ms": {
                k: {"n": len(v), "p50": 1e3 * statistics.median(v), "max": 1e3 * max(v)}
                for k, v in self.latencies.items() if v
            },
            "final_status": {"map_version": status.map_version, "keyframes": status.keyframes,
                             "frames_received": status.frames_received,
                             "global_points": status.extra.get("global_points"),
                             "replies_dropped": status.extra.get("replies_dropped"),
                             "frames_duplicate": status.extra.get("frames_duplicate")},
            "final_exit_code": exit_code,
            "rss_bytes": {"min": min(rss, default=None), "max": max(rss, default=None),
                          "first": rss[0] if rss else None, "last": rss[-1] if rss else None},
            "samples": self.samples,
        }  # fmt: skip


def plot(data: dict[str, Any], path: Path) -> None:
    from govnesf._extras import require

    matplotlib = require("matplotlib", "bench")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = data["samples"]
    t = [x["t_s"] / 60 for x in s]
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    axes[0].plot(t, [x["acked"] for x in s], label="frames acked")
    axes[0].plot(t, [x["keyframes_acked"] for x in s], label="keyframes acked")
    axes[0].set_ylabel("count")
    axes[0].legend()
    axes[1].plot(t, [x["errors"] for x in s], color="tab:red", label="errors (all kinds)")
    axes[1].plot(t, [x["restarts"] for x in s], color="black", label="restarts")
    axes[1].set_ylabel("count")
    axes[1].legend()
    axes[2].plot(t, [(x["rss_bytes"] or float("nan")) / 2**20 for x in s], color="tab:green")
    axes[2].set_ylabel("node RSS (MiB)")
    axes[2].set_xlabel("minutes")
    if data["kill"]:
        for ax in axes:
            ax.axvline(data["kill"]["at_s"] / 60, color="grey", linestyle="--", linewidth=0.8)
    fig.suptitle(f"soak: {data['args']['minutes']} min, kill -9 + restart at the dashed line")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=10.0, help="frames per second")
    parser.add_argument("--query-interval-s", type=float, default=2.0)
    parser.add_argument("--sample-s", type=float, default=5.0)
    parser.add_argument("--autosave-s", type=float, default=5.0)
    parser.add_argument("--kill-at", type=float, default=0.5, help="fraction of the run")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="govnesf-soak-") as tmp:
        data = Soak(args, Path(tmp)).run()
    data["command"] = "benchmarks/robustness/soak.py " + " ".join(sys.argv[1:] if argv is None else argv)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "soak.json").write_text(json.dumps(data, indent=1) + "\n")
    plot(data, args.out / "soak.png")
    keys = ("duration_s", "acks", "errors", "queries", "query_latency_ms", "restarts", "kill", "rss_bytes")
    summary = {k: data[k] for k in (*keys, "final_status", "final_exit_code")}
    print(json.dumps(summary, indent=1))
    return 0 if data["kill"].get("acked_keyframes_lost", 1) == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
