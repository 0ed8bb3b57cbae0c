"""What the node knows, behind one lock: the keyframe window, the global map, the map version, the
map's open-vocabulary space and the request counters (:class:`MapState`), and the immutable view of
it that ``save`` writes (:class:`MapSnapshot`)."""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mapper.map.global_map import GlobalSemanticMap
from mapper.map.robot_windows import RobotWindows
from mapper.map.window import Keyframe
from mapper.node.config import NodeConfig

__all__ = ["MapSnapshot", "MapState"]


@dataclass(frozen=True)
class MapSnapshot:
    """An immutable view of the map for saving (taken under the lock, written outside it)."""

    map_version: int
    keyframes: tuple[Keyframe, ...]
    ov_space: str | None
    ov_dim: int | None


class MapState:
    """Everything the node knows, behind :attr:`lock`. Counters are part of the state."""

    def __init__(self, config: NodeConfig) -> None:
        self.lock = threading.Lock()
        self.config = config
        self.window = RobotWindows(config.window)
        """The keyframe windows, one per robot (``window.max_robots``); ``keyframes`` are all of them."""
        self.global_map = GlobalSemanticMap(config.global_map, tile_dir=Path(config.map_dir) / ".tiles")
        """Global semantic point map (own lock; kept when keyframes leave the window; tiles beyond
        ``global_map.max_points`` page out to ``<map_dir>/.tiles``)."""
        self.map_version = 0
        self.ov_space: str | None = config.ov_space
        """Embedding space of the map (pinned by config, else set by the first keyframe with ov)."""
        self.ov_dim: int | None = None
        """Feature dimension of that space, learned from the first keyframe with ov."""
        self.frames_received = 0
        self.frames_rejected = 0
        self.ack_counts: Counter[str] = Counter()
        self.error_counts: Counter[str] = Counter()
        self.requests_by_type: Counter[str] = Counter()
        self.keyframes_evicted = 0
        self.last_save: dict[str, Any] | None = None
        self.started_monotonic = time.monotonic()

    # -- called with the lock held ------------------------------------------------------------

    def memory_bytes(self) -> int:
        """Bytes of map data held: keyframe arrays plus the global map's arrays (later stages add
        their volumes and caches)."""
        return self.window.nbytes + self.global_map.nbytes

    def snapshot(self) -> MapSnapshot:
        return MapSnapshot(self.map_version, self.window.keyframes, self.ov_space, self.ov_dim)

    def summary_line(self) -> str:
        """One line for the log: version, keyframes, frames received / rejected, memory."""
        return (
            f"map_version {self.map_version}, keyframes {len(self.window)}, frames received "
            f"{self.frames_received} (rejected {self.frames_rejected}), "
            f"memory {self.memory_bytes() / 1e6:.1f} MB"
        )
