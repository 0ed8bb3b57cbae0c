"""The keyframe integrator: fuses each acked keyframe into the global map shortly after its ack.

A bounded queue (``global_map.integrate_queue``) feeds one thread (``mapper-integrator``), in ack
order. When the queue is full the ingest thread waits for room before the next ack (backpressure,
counted), so nothing acked is dropped. With a queue of 0, or when the thread is not running, the
keyframe is integrated on the calling thread (counted as ``inline``). ``save`` drains it first;
``status`` reports it (``integration``).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mapper.map.global_map import GlobalSemanticMap
from mapper.map.window import Keyframe
from mapper.node.config import NodeConfig
from mapper.node.state import MapState

__all__ = ["IntegrateJob", "Integrator"]

log = logging.getLogger("mapper.node.integration")


@dataclass(frozen=True)
class IntegrateJob:
    """One acked keyframe waiting for the integrator: the map it goes into (the one current when it
    was acked: a ``load`` in between leaves the new map alone), its map version and ov space."""

    target: GlobalSemanticMap
    keyframe: Keyframe
    map_version: int
    ov_space: str | None
    submitted: float  # time.monotonic() at the ack


class Integrator:
    """The integrator queue, its thread and its counters.

    ``listeners`` are the node's keyframe listeners (called after each integration, outside the
    state lock, in ack order); ``warm_encoder(space)`` loads the text encoder of a keyframe's OV
    space in the background once."""

    def __init__(
        self,
        config: NodeConfig,
        state: MapState,
        listeners: list[Callable[[Keyframe, int], None]],
        warm_encoder: Callable[[str], None],
    ) -> None:
        self.config = config
        self.state = state
        self.listeners = listeners
        self.warm_encoder = warm_encoder
        self._jobs: queue.Queue[IntegrateJob] = queue.Queue(maxsize=max(config.global_map.integrate_queue, 1))
        """Keyframes acked but not yet integrated into the global map (``global_map.integrate_queue``)."""
        self._cond = threading.Condition()
        """Guards the counters below (never held while taking the state lock)."""
        self.submitted = 0
        """Keyframes handed to integration so far (written under the *state* lock, with the window add)."""
        self._done = 0
        self._errors = 0
        self._waits = 0
        self._wait_s = 0.0
        self._inline = 0
        self._lag_s: deque[float] = deque(maxlen=1000)
        """Ack-to-integrated seconds of recent keyframes (status ``integration.lag_ms_*``)."""
        self._thread: threading.Thread | None = None
        self._inline_lock = threading.RLock()
        """Serialises integrations done outside the integrator thread (they keep ack order)."""

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self, stop: threading.Event) -> threading.Thread | None:
        """Start the integrator thread (``global_map.integrate_queue`` > 0); it finishes its queue
        once ``stop`` is set. Returns the thread, or None when integration is inline."""
        if self.config.global_map.integrate_queue <= 0:
            return None
        self._thread = threading.Thread(target=self._loop, args=(stop,), name="mapper-integrator",
                                        daemon=True)
        self._thread.start()
        return self._thread

    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- submitting ---------------------------------------------------------------------------

    def submit(self, job: IntegrateJob) -> None:
        """Queue an acked keyframe for the integrator. When ``global_map.integrate_queue``
        keyframes are already waiting, wait for room (backpressure: the ack waits; counted), so
        nothing acked is dropped. Inline when the queue is off or the integrator is not running."""
        if self.config.global_map.integrate_queue == 0 or not self.alive():
            self._integrate_now(job)
            return
        try:
            self._jobs.put_nowait(job)
            return
        except queue.Full:
            pass
        started = time.monotonic()
        while True:
            try:
                self._jobs.put(job, timeout=self.config.poll_interval_s)
                break
            except queue.Full:
                if not self.alive():  # stopped meanwhile: do its work here, in order
                    self._integrate_now(job)
                    break
        with self._cond:
            self._waits += 1
            self._wait_s += time.monotonic() - started

    def _integrate(self, job: IntegrateJob) -> None:
        """Fuse one acked keyframe into its global map, then tell the keyframe listeners (not when a
        ``load`` replaced that map meanwhile). Never raises: a failure is logged and counted in
        status ``integration.errors``."""
        keyframe = job.keyframe
        try:
            stats = job.target.integrate(keyframe, map_version=job.map_version)
            log.debug("frame seq %d: %d points into the global map (%d new voxels) in %.1f ms%s",
                      keyframe.seq, stats.points, stats.voxels_new, 1e3 * stats.seconds,
                      f" ({stats.skipped})" if stats.skipped else "")
            if keyframe.ov is not None and job.ov_space is not None:
                self.warm_encoder(job.ov_space)
            if job.target is not self.state.global_map:
                return  # a ``load`` replaced the map (and the window) since this keyframe's ack
            for listener in self.listeners:
                listener(keyframe, job.map_version)
        except Exception:
            log.error("integrating keyframe seq %d failed:\n%s", keyframe.seq, traceback.format_exc())
            with self._cond:
                self._errors += 1
        finally:
            with self._cond:
                self._done += 1
                self._lag_s.append(time.monotonic() - job.submitted)
                self._cond.notify_all()

    def _integrate_now(self, job: IntegrateJob) -> None:
        """Integrate on the calling thread (counted as ``inline``), after anything a stopped
        integrator left in the queue."""
        with self._inline_lock:
            self._integrate_pending_inline()
            with self._cond:
                self._inline += 1
            self._integrate(job)

    def _integrate_pending_inline(self) -> None:
        """Integrate whatever waits in the queue on the calling thread (only when the integrator is
        not running: it and this must not both take jobs)."""
        with self._inline_lock:
            while not self.alive():
                try:
                    job = self._jobs.get_nowait()
                except queue.Empty:
                    return
                self._integrate(job)

    def _loop(self, stop: threading.Event) -> None:
        """The integrator thread: fuse queued keyframes in ack order until stopped and the queue is
        empty (so the final save holds everything acked)."""
        while True:
            try:
                job = self._jobs.get(timeout=self.config.poll_interval_s)
            except queue.Empty:
                if stop.is_set():
                    return
                continue
            self._integrate(job)

    # -- waiting and reporting ----------------------------------------------------------------

    def backlog(self) -> int:
        """Keyframes acked and not yet integrated into the global map (no lock needed: a read of
        two counters, exact or one keyframe off)."""
        with self._cond:
            done = self._done
        return max(self.submitted - done, 0)

    def drain(self) -> None:
        """Return once every keyframe acked so far is integrated into the global map (``save`` does
        this first). Waits for the integrator, or does its work here when it is not running."""
        with self.state.lock:
            target = self.submitted
        self.wait_integrated(target)

    def wait_integrated(self, target: int) -> None:
        """Until ``target`` keyframes are integrated (the rest may be in the queue, or being
        integrated inline by the ingest thread right now)."""
        while True:
            if not self.alive():
                self._integrate_pending_inline()
            with self._cond:
                if self._done >= target:
                    return
                self._cond.wait(self.config.poll_interval_s)

    def stats(self) -> dict[str, Any]:
        """For ``status`` (``integration``): ``background`` (False: inline, before the ack),
        ``queue_length`` (``global_map.integrate_queue``), ``backlog`` (acked keyframes not yet in
        the global map), ``integrated``, ``errors``, ``backpressure_waits`` / ``backpressure_s``
        (acks that waited for room in the queue), ``inline`` (integrated on the ingest thread) and
        ``lag_ms_p50`` / ``lag_ms_p95`` (ack to integrated, recent keyframes). Called with the
        state lock held."""
        submitted = self.submitted
        with self._cond:
            lags = sorted(self._lag_s)
            done = self._done

            def pct(q: float) -> float | None:
                return round(1e3 * lags[min(len(lags) - 1, int(q * len(lags)))], 3) if lags else None

            return {
                "background": self.alive(),
                "queue_length": self.config.global_map.integrate_queue,
                "backlog": max(submitted - done, 0),
                "integrated": done,
                "errors": self._errors,
                "backpressure_waits": self._waits,
                "backpressure_s": round(self._wait_s, 3),
                "inline": self._inline,
                "lag_ms_p50": pct(0.5),
                "lag_ms_p95": pct(0.95),
            }
