"""``status``: what the node holds and how it is doing, for operators and planners.

The fixed fields (map version, keyframes, frames, memory, uptime) and ``extra``: counters, the
integrator, the query pool, the answer cache, security, the global map's statistics, whatever the
registered ``status_providers`` report (the model, the background workers), ``pending`` (background
work on acked keyframes, by source) and ``settled`` (none pending)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from mapper.node.context import NodeContext
from protocol.messages import Message, Status

__all__ = ["StatusAnswers", "rss_bytes"]


def rss_bytes() -> int | None:
    """Resident set size of this process (Linux), for operators; None where unavailable."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


class StatusAnswers:
    """The ``status`` handler. ``transport()`` adds what only the transport knows (``serving``,
    ``segment_methods``, ``query_pool``, ``answers``, ``security``); it is called with the state
    lock held and must not take it."""

    def __init__(self, ctx: NodeContext, transport: Callable[[], dict[str, Any]]) -> None:
        self.ctx = ctx
        self.transport = transport

    def handle(self, msg: Message) -> Status:
        ctx = self.ctx
        config, state = ctx.config, ctx.state
        with state.lock:
            extra: dict[str, Any] = {
                "max_keyframes": config.window.max_keyframes,
                "max_robots": config.window.max_robots,
                "robots": state.window.counts(),
                "frames_keyframe": state.ack_counts["keyframe"],
                "frames_accepted": state.ack_counts["accepted"],
                "frames_rejected_ack": state.ack_counts["rejected"],
                "keyframes_evicted": state.keyframes_evicted,
                "errors": dict(state.error_counts),
                "requests": dict(state.requests_by_type),
                "ov_dim": state.ov_dim,
                "last_save": state.last_save,
                "endpoints": {
                    "ingest": config.ingest_endpoint,
                    "query": config.query_endpoint,
                    "events": config.events_endpoint,
                },
                "map_dir": os.path.abspath(config.map_dir),
                "pid": os.getpid(),
                "rss_bytes": rss_bytes(),
                **self.transport(),
                "limits": {
                    "sndhwm": config.limits.sndhwm,
                    "rcvhwm": config.limits.rcvhwm,
                    "events_queue_max": config.limits.events_queue_max,
                },
                "events_dropped": ctx.events.dropped,
                "frames_duplicate": ctx.frames_duplicate,
                "frames_downscaled": ctx.frames_downscaled,
                "replies_dropped": dict(ctx.replies_dropped),
                "integration": ctx.integration.stats(),
                "pending": ctx.pending_work(),
                **state.global_map.stats(),
            }
            for key, provider in ctx.status_providers.items():
                extra[key] = provider()
            extra["settled"] = not any(extra["pending"].values())
            return Status(
                map_version=state.map_version,
                keyframes=len(state.window),
                frames_received=state.frames_received,
                frames_rejected=state.frames_rejected,
                ov_space=state.ov_space,
                memory_bytes=ctx.memory_bytes(),
                uptime_s=time.monotonic() - state.started_monotonic,
                extra=extra,
                id=getattr(msg, "id", None),
            )
