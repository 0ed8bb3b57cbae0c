"""A read-only node that follows another node's saved map (``follow_map``).

One node writes the map (the robot's: it takes the frames and saves with ``autosave_name`` and
``autosave_interval_s``); any number of other nodes, a planner's for example, serve queries from
copies of it. A follower loads the map ``follow_map`` from its ``map_dir`` at start and again
whenever the file changes (its size or modification time, checked every ``follow_interval_s``).
The writer's saves are atomic (a temporary file renamed over the old one,
:class:`mapper.node.store.MapStore`), so a follower never reads half a save: it loads the previous
file or the new one. A load that fails (a damaged file) leaves the follower serving the copy it
has and is counted; the next change of the file is tried again.

A follower rejects frames (acked ``rejected`` with the reason: send them to the writer) and
refuses ``save`` and ``load``; queries (``query_points``, ``segment_points``, ``render``,
``status``) are answered from its latest copy. ``status`` reports it under ``follow``: the map
followed, its loads, failures, the last error, the map version loaded and how old the copy is.

Example (two processes on one machine, sharing ``maps/``)::

    govnesf serve --set autosave_name=latest --set autosave_interval_s=5          # the writer
    govnesf serve --ingest tcp://127.0.0.1:6555 --query tcp://127.0.0.1:6556 \\
        --events "" --set follow_map=latest                                       # a follower

The design for more than one machine (maps sharded by region, the store on shared or object
storage): docs/concepts/map-paging.md, "Several processes, several machines".
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from mapper.node.answers.persistence import Persistence
from mapper.node.context import NodeContext
from mapper.node.store import StoreError
from protocol.errors import ProtocolError

__all__ = ["MapFollower", "install_follower"]

log = logging.getLogger("mapper.node.follower")


class MapFollower:
    """Loads ``config.follow_map`` whenever its file changes (:meth:`poll_once`; the worker
    ``mapper-map-follower`` calls it every ``follow_interval_s``)."""

    def __init__(self, ctx: NodeContext, persistence: Persistence) -> None:
        name = ctx.config.follow_map
        if not name:
            raise ValueError("MapFollower needs config.follow_map")
        self.ctx = ctx
        self.persistence = persistence
        self.name: str = name
        self._seen: tuple[int, int] | None = None
        """(size, mtime_ns) of the file last tried: a file is loaded once per change."""
        self._poll = threading.Lock()
        """One poll (and load) at a time."""
        self._lock = threading.Lock()
        """Guards the counters only, never held across a load: ``status`` reads them while it holds
        the node's state lock, which a load takes."""
        self.loads = 0
        self.failed = 0
        self.last_error = ""
        self.loaded_version = -1
        self._loaded_mtime_ns = 0

    def poll_once(self) -> bool:
        """Load the followed map when its file changed since the last try; True when loaded.
        Never raises: a missing file is waited for, a failed load is counted and reported."""
        with self._poll:
            try:
                stat = self.ctx.store.path_for(self.name).stat()
            except (OSError, StoreError):
                return False  # not written yet (or gone): keep what we have
            seen = (int(stat.st_size), int(stat.st_mtime_ns))
            if seen == self._seen:
                return False
            self._seen = seen
            try:
                note = self.persistence.load_map(self.name)
            except Exception as exc:  # a damaged file (ProtocolError) or a bug: keep the old copy
                message = exc.message if isinstance(exc, ProtocolError) else f"{type(exc).__name__}: {exc}"
                with self._lock:
                    self.failed += 1
                    self.last_error = message
                if isinstance(exc, ProtocolError):
                    log.warning("following map %r: %s (serving the copy loaded before)", self.name, message)
                else:
                    log.exception("following map %r failed", self.name)
                return False
            version = self.ctx.state.map_version
            with self._lock:
                self.loads += 1
                self.last_error = ""
                self.loaded_version = version
                self._loaded_mtime_ns = seen[1]
            log.info("following map %r: %s", self.name, note)
            return True

    def run(self, stop: threading.Event) -> None:
        """Worker loop: :meth:`poll_once` every ``follow_interval_s`` until ``stop``."""
        while not stop.is_set():
            self.poll_once()
            stop.wait(self.ctx.config.follow_interval_s)

    def stats(self) -> dict[str, Any]:
        """``status`` key ``follow``."""
        with self._lock:
            age = (time.time() - self._loaded_mtime_ns / 1e9) if self.loads else None
            return {"map": self.name, "loads": self.loads, "failed": self.failed,
                    "last_error": self.last_error, "loaded_map_version": self.loaded_version,
                    "copy_age_s": None if age is None else round(age, 3)}


def install_follower(ctx: NodeContext, persistence: Persistence) -> MapFollower | None:
    """With ``follow_map`` set: the follower, its worker and its ``status`` entry (None otherwise).
    The node's ``start`` makes the first load (once every stage listens to loads)."""
    if not ctx.config.follow_map:
        return None
    follower = MapFollower(ctx, persistence)
    ctx.workers.append(("map-follower", follower.run))
    ctx.status_providers["follow"] = follower.stats
    return follower
