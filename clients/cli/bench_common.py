"""What the phases of ``govnesf bench`` (`clients.cli.bench`, `clients.cli.bench_floor`) share: the
machine's description, percentiles, and waiting for a node to settle after a stream."""

from __future__ import annotations

import os
import platform
import time
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from clients.client import MapperClient

__all__ = ["_busy_items", "_pcts", "describe_machine", "wait_until_settled"]


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def describe_machine() -> dict[str, Any]:
    """CPU model, cores, RAM, Python and library versions (no torch import)."""
    cpu = platform.processor() or None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                ram = int(line.split()[1]) * 1024
    except OSError:
        pass
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {
        "cpu_model": cpu,
        "cpu_count": os.cpu_count(),
        "cpus_usable": affinity,
        "ram_bytes": ram,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": _version("torch"),
        "numpy": _version("numpy"),
        "pyzmq": _version("pyzmq"),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "load_avg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


def _pcts(seconds: list[float]) -> dict[str, float | int | None]:
    """p50 / p95 / max in ms, and the count."""
    if not seconds:
        return {"p50_ms": None, "p95_ms": None, "max_ms": None, "n": 0}
    arr = np.asarray(seconds) * 1e3
    return {
        "p50_ms": round(float(np.percentile(arr, 50)), 3),
        "p95_ms": round(float(np.percentile(arr, 95)), 3),
        "max_ms": round(float(arr.max()), 3),
        "n": len(seconds),
    }


def _busy_items(extra: dict[str, Any]) -> int:
    """Work the node still has queued after a stream, from its ``status``: its own ``pending`` (the
    background work on acked keyframes, by source) where it reports that; else the integrator's
    backlog, the model's unapplied window changes and the background workers' pending keyframes.
    (The model applies its window changes when a query or render next needs its volume: not
    background work, so a node reporting ``pending`` leaves them out.)"""
    reported = extra.get("pending")
    if isinstance(reported, dict):
        return sum(int(v) for v in reported.values() if isinstance(v, int) and v > 0)
    busy = int((extra.get("integration") or {}).get("backlog", 0) or 0)
    for key in ("model", "map_features", "evicted_views", "rendered_depth", "triangulation", "ov_backend"):
        stats = extra.get(key)
        if isinstance(stats, dict):
            busy += int(stats.get("pending", 0) or 0)
    return busy


def wait_until_settled(client: MapperClient, timeout_s: float = 60.0, poll_s: float = 0.1) -> float:
    """Seconds until the node's ``status`` shows nothing queued twice in a row (at most
    ``timeout_s``): the heavy queries after a stream are then measured without its catch-up."""
    t0 = time.perf_counter()
    quiet = 0
    while time.perf_counter() - t0 < timeout_s:
        quiet = quiet + 1 if _busy_items(client.status().extra) == 0 else 0
        if quiet >= 2:
            break
        time.sleep(poll_s)
    return round(time.perf_counter() - t0, 3)
