"""The window's views and their incremental cost volume: :class:`WindowVolume`.

Streaming updates:

* The window's ``on_add`` / ``on_evict`` callbacks run under the node's state lock, on the ingest
  thread. They only RECORD the change (O(1), a dict entry), so ingest is never slowed down by the
  model. A keyframe added and evicted before anything used it cancels out, so the record holds at
  most one entry per keyframe of the window plus the evictions not yet applied.
* The next query (or :meth:`WindowVolume.sync`) APPLIES the recorded changes incrementally: each
  new keyframe is encoded once (:func:`~mapper.runtime.entries.encode_keyframes`) and its features
  are added to the :class:`~mapper.model.ops.cost_volume.CostVolume` with ``add_view`` (only the
  voxels it sees); an evicted keyframe is removed with ``remove_view``.
* The volume's bounds follow what the window observed: every keyframe contributes extent points
  (its depth back-projected when it has depth, else its camera frustum up to ``max_range_m``, or
  the points :meth:`WindowVolume.set_view_extent` gave it: RGB-only keyframes get their
  triangulated points, :mod:`mapper.node.workers.triangulation`).
  When a new keyframe's points leave the current bounds (more than ``rebuild_outside_fraction`` of
  them outside), the bounds are recomputed from the whole window (recentred / grown, or moved with
  the robot) and the volume is rebuilt from the stored views. This is the ONE non-incremental step;
  it is counted in :attr:`WindowVolume.rebuilds`.
* Everything derived from the volume (3D U-Net output, stacked view tensors) is computed at query
  time by :meth:`WindowVolume.prepare` and cached per version (+1 per applied change).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Hashable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mapper.errors import RuntimeNotReady
from mapper.model.ops.cost_volume import CostVolume, VolumeBounds, bounds_from_points
from mapper.runtime.entries import (
    ViewEntry,
    encode_keyframes,
    extent_points,
    keyframe_key,
    prior_at_working_size,
    render_extents,
)
from mapper.runtime.loading import LoadedModel
from mapper.runtime.prepared import Prepared, stack_views

log = logging.getLogger("mapper.runtime.model_runtime")  # the runtime's one logger, whichever part logs

Key = tuple[str, int, int]
"""A keyframe's ``(camera, seq, stamp_ns)`` (:func:`~mapper.runtime.entries.keyframe_key`)."""


class WindowVolume:
    """The window's keyframes as :class:`~mapper.runtime.entries.ViewEntry` and their cost volume,
    kept in step with the window incrementally, and the per-version :class:`Prepared` cache.

    Thread safety: the window callbacks and the ``set_view_*`` setters may run on any thread (they
    take a short private lock); everything else runs under :attr:`lock`, which the runtime's queries
    hold too.
    """

    def __init__(self, loaded: LoadedModel) -> None:
        self.loaded = loaded
        self.lock = threading.RLock()
        """Serialises applying changes and every query of the runtime (never the node's lock)."""
        self._pending_lock = threading.Lock()
        self._pending: dict[Hashable, tuple[str, Any]] = {}  # key -> ("add", keyframe) | ("evict", None)
        self.entries: dict[Hashable, ViewEntry] = {}
        """The applied window: keyframe -> its view (read under :attr:`lock`)."""
        self._volume: CostVolume | None = None
        self._prepared: Prepared | None = None
        self.version = 0
        """+1 whenever an applied change altered the views or the volume."""
        self.rebuilds = 0
        """How often the volume was rebuilt on new bounds (the one non-incremental step)."""
        self.bounds_outliers = 0
        """Keyframes left out of the volume's bounds (``bounds_outlier_m``), each counted once."""
        self._bounds_outliers_logged: set[Key] = set()
        self.views_added = 0
        self.views_removed = 0
        self.view_extents: dict[Key, Tensor] = {}
        """set_view_extent's points by keyframe (under the pending lock)."""
        self._extents_changed: set[Key] = set()
        self.depth_priors: dict[Key, Tensor] = {}
        """set_view_depth_prior's priors by keyframe (under the pending lock)."""
        self._priors_changed: set[Key] = set()

    # -- window callbacks (under the node's state lock: O(1), no model work) ---------------------

    def on_add(self, keyframe: Any) -> None:
        """Record that ``keyframe`` entered the window (applied by the next :meth:`sync`)."""
        with self._pending_lock:
            previous = self._pending.get(keyframe)
            if previous is not None and previous[0] == "evict":
                del self._pending[keyframe]  # evicted and re-added before anything was applied
            else:
                self._pending[keyframe] = ("add", keyframe)

    def on_evict(self, keyframe: Any) -> None:
        """Record that ``keyframe`` left the window."""
        with self._pending_lock:
            previous = self._pending.get(keyframe)
            if previous is not None and previous[0] == "add":
                del self._pending[keyframe]  # never applied: nothing to undo
            else:
                self._pending[keyframe] = ("evict", None)

    @property
    def pending(self) -> int:
        """Window changes recorded but not applied yet."""
        with self._pending_lock:
            return len(self._pending)

    # -- applying changes ---------------------------------------------------------------------

    @torch.no_grad()
    def sync(self) -> int:
        """Apply the recorded window changes to the views and the cost volume (incrementally).

        Returns the number of changes applied. Raises :class:`RuntimeNotReady` without a model.
        """
        model = self.loaded.require_model()
        with self._pending_lock:
            pending, self._pending = self._pending, {}
            extents_changed, self._extents_changed = self._extents_changed, set()
            priors_changed, self._priors_changed = self._priors_changed, set()
        if not pending:
            if not extents_changed and not priors_changed:
                return 0
            return self._apply_view_extents(extents_changed) + self._apply_depth_priors(priors_changed)
        with self.lock:
            removed = [key for key, (op, _) in pending.items() if op == "evict"]
            added = [(key, kf) for key, (op, kf) in pending.items() if op == "add"]
            for key in removed:
                if key in self.entries:
                    del self.entries[key]
                    if self._volume is not None:
                        self._volume.remove_view(key)
                    self.views_removed += 1
            if not self.entries:
                self._volume = None  # window emptied (e.g. a map load): start from fresh bounds
            keyframes = [kf for _, kf in added]
            with self._pending_lock:  # set_view_extent's points and set_view_depth_prior's priors
                observed = [self.view_extents.get(keyframe_key(kf)) for kf in keyframes]
                priors = [self.depth_priors.get(keyframe_key(kf)) for kf in keyframes]
            new_entries = encode_keyframes(self.loaded, model, keyframes, observed, priors)
            for (key, _), entry in zip(added, new_entries, strict=True):
                self.entries[key] = entry
            changed = self._refresh_extents(extents_changed)
            self._refresh_depth_priors(priors_changed)
            self._update_bounds([*new_entries, *changed], evicted=bool(removed) or bool(changed))
            assert self._volume is not None or not self.entries
            if self._volume is not None:
                for (key, _), entry in zip(added, new_entries, strict=True):
                    if key not in self._volume.view_ids:
                        self._volume.add_view(
                            key, entry.features, entry.K, entry.world_from_cam, self.loaded.image_wh
                        )
            self.views_added += len(added)
            self.version += 1
            self._prepared = None
            return len(pending)

    # -- view extents (bounds that follow the room without depth) --------------------------------

    def set_view_extent(self, key: Key, points_m: np.ndarray | None) -> None:
        """Give the keyframe ``key = (camera, seq, stamp_ns)`` the world points it observed,
        ``points_m`` (N, 3) metres, N >= 1 (None: back to its frustum up to ``max_range_m``).

        For keyframes without depth only: the volume's bounds then cover these points (and the
        camera) instead of the frustum up to the fixed ``max_range_m``, so the volume follows what
        the sparse geometry (:mod:`mapper.node.workers.triangulation`) found, growing with the
        room within the voxel budget. Thread-safe; applied by the next :meth:`sync`, which re-checks
        the bounds and rebuilds the volume when they moved. Extents of keyframes that left the
        window are dropped at the next change. Raises ``ValueError`` (nothing changed) on a bad array."""
        pts = None
        if points_m is not None:
            arr = np.asarray(points_m, np.float64)
            if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1 or not np.isfinite(arr).all():
                raise ValueError(f"points_m must be a finite (N >= 1, 3) array, got shape {arr.shape}")
            pts = torch.tensor(arr, dtype=torch.float32, device=self.loaded.device)
        self._set_pending(self.view_extents, self._extents_changed, key, pts)

    def _refresh_extents(self, keys: set[Key]) -> list[ViewEntry]:
        """Recompute the extent of the depth-less entries whose observed points changed."""
        if not keys:
            return []
        observed = self._take_pending(self.view_extents, keys)
        changed = []
        for entry in self.entries.values():
            if entry.key in observed and entry.depth_m is None and observed[entry.key] is not entry.observed:
                entry.observed = observed[entry.key]
                entry.extent = extent_points(self.loaded, entry.K, entry.world_from_cam, None, entry.observed)
                changed.append(entry)
        return changed

    def set_view_depth_prior(self, key: Key, depth_m: np.ndarray | None) -> None:
        """Give the keyframe ``key = (camera, seq, stamp_ns)`` a sparse z-depth prior ``depth_m``
        (H, W) metres, 0 = none, any size covering the image (None: remove it).

        For keyframes without depth only, and only for Depth Guided Masking (``segment_points``
        with ``use_depth``): a view is masked for a point where the prior exists and disagrees
        with the point's depth, and kept where it has no prior, as DGM treats a depth map's holes.
        Resized to the working size with nearest lookup. Thread-safe; applied by the next
        :meth:`sync`. Raises ``ValueError`` (nothing changed) on a bad array."""
        prior = None
        if depth_m is not None:
            arr = np.asarray(depth_m, np.float32)
            if arr.ndim != 2 or arr.size == 0 or not np.isfinite(arr).all() or (arr < 0).any():
                raise ValueError(f"depth_m must be a finite, non-negative (H, W) array, got {arr.shape}")
            prior = torch.tensor(arr, device=self.loaded.device)
        self._set_pending(self.depth_priors, self._priors_changed, key, prior)

    def _set_pending(self, store: dict[Key, Tensor], changed: set[Key], key: Key, value: Tensor | None
                     ) -> None:
        """Set (or with None remove) ``store[key]`` and mark ``key`` changed for the next sync."""
        with self._pending_lock:
            if value is None:
                store.pop(key, None)
            else:
                store[key] = value
            changed.add(key)

    def _take_pending(self, store: dict[Key, Any], keys: set[Key]) -> dict[Key, Any]:
        """``{key: store.get(key)}`` for the changed ``keys``, under the pending lock; entries of
        keyframes that left the window (and did not just change) are dropped from ``store``."""
        live = {e.key for e in self.entries.values()}
        with self._pending_lock:
            taken = {k: store.get(k) for k in keys}
            for k in list(store):
                if k not in live and k not in keys:
                    del store[k]
        return taken

    def _refresh_depth_priors(self, keys: set[Key]) -> int:
        """Set the depth prior of the depth-less entries whose prior changed; returns how many."""
        if not keys:
            return 0
        priors = self._take_pending(self.depth_priors, keys)
        changed = 0
        for entry in self.entries.values():
            if entry.key in priors and entry.depth_m is None:
                entry.depth_prior = prior_at_working_size(self.loaded, priors[entry.key])
                changed += 1
        return changed

    def _apply_depth_priors(self, keys: set[Key]) -> int:
        """:meth:`sync` without window changes: new depth priors change the cached views."""
        with self.lock:
            changed = self._refresh_depth_priors(keys)
            if changed:
                self.version += 1
                self._prepared = None
            return changed

    @torch.no_grad()
    def _apply_view_extents(self, keys: set[Key]) -> int:
        """:meth:`sync` without window changes: new view extents may move the bounds."""
        with self.lock:
            changed = self._refresh_extents(keys)
            if not changed or self._volume is None:
                return len(changed)
            rebuilds = self.rebuilds
            self._update_bounds(changed, evicted=True)
            if self.rebuilds != rebuilds:
                self.version += 1
                self._prepared = None
            elif self._prepared is not None:  # same views and volume: only the render volumes' bounds move
                self._prepared.extents = render_extents(self.entries.values())
                self._prepared.render_volumes.clear()
            return len(changed)

    def _target_bounds(self) -> VolumeBounds:
        model = self.loaded.require_model()
        points = torch.cat([e.extent for e in self._bounds_entries()])
        vcfg = model.cfg.volume
        return bounds_from_points(
            points.cpu(),
            max_voxels=self.loaded.config.max_voxels or vcfg.max_voxels,
            min_voxel_size_m=self.loaded.config.voxel_size_m or vcfg.min_voxel_size_m,
            margin_m=self.loaded.config.bounds_margin_m,
        )

    def _bounds_entries(self) -> list[ViewEntry]:
        """The window's keyframes whose extent is within ``config.bounds_outlier_m`` of the others'
        (the median of their median points); all of them when that would leave none."""
        entries = [e for e in self.entries.values() if e.extent.shape[0]]
        if len(entries) < 3:
            return entries or list(self.entries.values())
        centres = torch.stack([e.extent.median(dim=0).values for e in entries]).to(torch.float64)  # (E, 3)
        centre = centres.median(dim=0).values
        far = torch.linalg.vector_norm(centres - centre, dim=1) > self.loaded.config.bounds_outlier_m
        if not bool(far.any()) or bool(far.all()):
            return entries
        outliers = far.tolist()
        for e, out in zip(entries, outliers, strict=True):
            if out and e.key not in self._bounds_outliers_logged:
                self._bounds_outliers_logged.add(e.key)
                self.bounds_outliers += 1
                log.warning("keyframe %s (seq %d): what it observed lies more than %.0f m from the window's "
                            "other keyframes; left out of the model's volume bounds (a wrong pose?)",
                            e.key[0] or "-", e.seq, self.loaded.config.bounds_outlier_m)
        return [e for e, out in zip(entries, outliers, strict=True) if not out]

    def _update_bounds(self, new_entries: Sequence[ViewEntry], evicted: bool) -> None:
        """Create the volume, or move it (recentre / grow / shrink) + rebuild when the window's
        observations no longer fit it.

        Grow: a new view has more than ``rebuild_outside_fraction`` of its extent points outside
        the current box. Shrink (only checked after evictions): the box the window needs now has at
        most half the current box's volume (the robot left an area). Either way the new bounds are
        ``bounds_from_points`` over the whole window and the volume is rebuilt from the stored views.
        """
        model = self.loaded.require_model()
        if not self.entries:
            return
        if self._volume is None:
            feature_dim = model.cfg.encoder.feature_dim
            self._volume = CostVolume(self._target_bounds(), feature_dim, self.loaded.device)
            return
        bounds = self._volume.bounds
        lo = torch.tensor(bounds.origin_m, device=self.loaded.device)
        hi = torch.tensor(bounds.max_corner_m, device=self.loaded.device)
        grow = any(
            float(((e.extent < lo) | (e.extent > hi)).any(dim=-1).float().mean())
            > self.loaded.config.rebuild_outside_fraction
            for e in new_entries
        )
        if not grow and not evicted:
            return
        target = self._target_bounds()
        if target == bounds:
            return

        def box_volume(b: VolumeBounds) -> float:
            return float(np.prod([n * b.voxel_size_m for n in b.dims]))

        if grow or box_volume(target) <= 0.5 * box_volume(bounds):
            log.info(
                "cost volume moves: origin %s dims %s voxel %.3f m -> origin %s dims %s voxel %.3f m",
                tuple(round(o, 2) for o in bounds.origin_m), bounds.dims, bounds.voxel_size_m,
                tuple(round(o, 2) for o in target.origin_m), target.dims, target.voxel_size_m,
            )  # fmt: skip
            self._volume.rebuild(target)
            self.rebuilds += 1

    @property
    def bounds(self) -> VolumeBounds | None:
        """Current cost-volume bounds (None before the first keyframe)."""
        return None if self._volume is None else self._volume.bounds

    @property
    def cost_volume(self) -> CostVolume | None:
        """The incremental cost volume (read it under no concurrent :meth:`sync`)."""
        return self._volume

    def __len__(self) -> int:
        return len(self.entries)

    def memory_bytes(self) -> int:
        """Bytes held: per-view caches, cost-volume sums, and the cached query tensors."""
        total = sum(e.nbytes for e in list(self.entries.values()))  # may race with sync()
        if self._volume is not None:
            total += self._volume.bounds.num_voxels * (1 + 2 * self._volume.feature_dim) * 8
        prep = self._prepared
        if prep is not None:
            for t in (prep.volume, prep.rgb, prep.features, prep.ov, prep.depth_m):
                if t is not None:
                    total += t.numel() * t.element_size()
        return total

    @torch.no_grad()
    def prepare(self) -> Prepared:
        """Sync, then the per-version cache (stacked views, 3D U-Net output). Call with :attr:`lock` held."""
        model = self.loaded.require_model()
        self.sync()
        if self._prepared is not None and self._prepared.version == self.version:
            return self._prepared
        if not self.entries or self._volume is None:
            raise RuntimeNotReady("no keyframes in the window yet: stream frames to the node first")
        entries = list(self.entries.values())
        self._prepared = stack_views(self.loaded, model, entries, self._volume, self.version)
        return self._prepared
