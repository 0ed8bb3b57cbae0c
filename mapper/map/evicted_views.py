"""What keyframes that left the window saw, kept per global-map voxel for the averaging methods.

``segment_points`` with ``average`` (OpenScene-2D averaging) answers a point by the mean of the OV
samples of every window keyframe whose image it falls in; ``average_depth`` only of those whose
depth confirms it. When a keyframe leaves the window (the window is bounded), its views stop
counting, and a stream three times longer than the window answered 1-3 points lower than the same
node with an unbounded window (docs/concepts/window-and-map.md). This module keeps those views' contribution:

* :class:`EvictedViewStore` (numpy, thread-safe; the running means updated in place by one
  compiled kernel, :func:`absorb_rows`): per voxel key, the running mean of the OV samples of the
  keyframes that left and counted for it, and how many did, in two channels, ``all`` (in the
  image, less the border: ``average``) and ``depth`` (also passing the depth test:
  ``average_depth``). Float32 means and counts (queries read the means in place, no copy); saved
  with the global map as they are (maps saved with float16 means load too).
* :class:`mapper.node.workers.evicted_views.EvictedViews`: the node's worker (``mapper-evicted-views``)
  that samples each evicted keyframe's OV map at every global-map voxel and adds the samples here.
* at query time (:class:`mapper.node.backends.average.AveragingBackend`) a point's nearest map
  voxel with a feature within ``queries.map_radius_voxels`` gives its prior: the voxel's mean
  counts as that many more views in the point's average (the ``prior`` of
  :func:`mapper.kernels.average.average_similarities`).
  With uniform view weights this is exactly the average over the window's views and the evicted
  ones (sampled at the voxel's fused position instead of the point).

The learned model's answers do not use it (they get the model's blend written into the map before
eviction instead: :mod:`mapper.node.workers.map_features`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from mapper.map.evicted_frames import EvictedFrameStore

__all__ = ["CHANNELS", "EvictedViewStore", "absorb_rows", "in_image", "warm_up"]

CHANNELS = ("all", "depth")
"""``all``: views whose image a voxel falls in (``average``); ``depth``: those whose depth also
confirms it (``average_depth``)."""


@dataclass
class _Channel:
    mean: np.ndarray  # (cap, D) float32 running mean of the samples
    count: np.ndarray  # (cap,) float32 views behind it


@numba.njit(boundscheck=False, cache=True, nogil=True)
def _absorb_rows(mean, count, rows, feat, at):  # pragma: no cover - compiled
    for i in range(rows.shape[0]):
        r = rows[i]
        src = at[i]
        n = count[r]
        inv = np.float32(1.0) / (n + np.float32(1.0))
        for d in range(mean.shape[1]):
            mean[r, d] += (feat[src, d] - mean[r, d]) * inv
        count[r] = n + np.float32(1.0)


def behind_surface(
    xyz: np.ndarray,  # (N, 3) world metres
    K: np.ndarray,  # (4,) fx, fy, cx, cy of the depth image
    world_from_cam: np.ndarray,  # (4, 4)
    depth_m: np.ndarray,  # (H, W) z-depth, 0 or non-finite = none
    rel_tol: float,
) -> np.ndarray:  # (N,) bool
    """Points a view with depth cannot see: in front of the camera, inside the depth image, and
    more than ``rel_tol`` of the measured depth behind it at their pixel (the nearest pixel, as the
    averaging's depth test reads it). Points at pixels without a depth, behind the camera or outside
    the image are not behind anything.

    >>> depth = np.full((4, 4), 2.0, np.float32)
    >>> pts = np.array([[0.0, 0.0, 2.2], [0.0, 0.0, 2.6], [0.0, 0.0, 9.0], [0.0, 0.0, -3.0]])
    >>> behind_surface(pts, np.array([2.0, 2.0, 2.0, 2.0]), np.eye(4), depth, 0.25).tolist()
    [False, True, True, False]
    """
    pts = np.asarray(xyz, np.float64)
    pose = np.asarray(world_from_cam, np.float64)
    cam = (pts - pose[:3, 3]) @ pose[:3, :3]  # world -> camera: R^T (p - t)
    z = cam[:, 2]
    out = np.zeros(pts.shape[0], bool)
    front = z > 1e-6
    if not front.any():
        return out
    fx, fy, cx, cy = (float(v) for v in np.asarray(K, np.float64).reshape(-1))
    h, w = depth_m.shape
    zf = z[front]
    col = np.floor(cam[front, 0] / zf * fx + cx)
    row = np.floor(cam[front, 1] / zf * fy + cy)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    d = np.zeros(zf.shape[0], np.float64)
    d[inside] = np.asarray(depth_m)[row[inside].astype(np.int64), col[inside].astype(np.int64)]
    d = np.where(np.isfinite(d), d, 0.0)
    out[np.flatnonzero(front)] = (d > 0) & (zf > d * (1.0 + rel_tol))
    return out


def absorb_rows(
    mean: np.ndarray,  # (cap, D) float32 running means, updated in place
    count: np.ndarray,  # (cap,) float32 samples behind each, updated in place
    rows: np.ndarray,  # (m,) int64 distinct rows to update
    feat: np.ndarray,  # (M, D) float32 samples
    at: np.ndarray,  # (m,) int64 the sample of each row: feat[at[i]] goes into row rows[i]
) -> None:
    """One more sample per row: ``mean[r] += (feat[at] - mean[r]) / (count[r] + 1)``, ``count[r] += 1``
    (the running mean, in float32, in place; one pass, no temporaries, the GIL released). A row
    listed twice takes both samples, one after the other."""
    if mean.dtype != np.float32 or count.dtype != np.float32 or feat.dtype != np.float32:
        raise TypeError("absorb_rows: mean, count and feat must be float32")
    if mean.ndim != 2 or feat.ndim != 2 or feat.shape[1] != mean.shape[1]:
        raise ValueError(f"absorb_rows: mean {mean.shape} and feat {feat.shape} must be (., D) of one D")
    rows = np.asarray(rows, np.int64)
    at = np.asarray(at, np.int64)
    if rows.shape != at.shape or rows.ndim != 1:
        raise ValueError(f"absorb_rows: rows {rows.shape} and at {at.shape} must be (m,)")
    if rows.size and (rows.min() < 0 or rows.max() >= mean.shape[0]
                      or at.min() < 0 or at.max() >= feat.shape[0]):
        raise ValueError("absorb_rows: a row or sample index is out of range")
    _absorb_rows(mean, count, rows, np.ascontiguousarray(feat), at)


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`absorb_rows` on a one-row problem."""
    absorb_rows(np.zeros((1, 2), np.float32), np.zeros(1, np.float32), np.zeros(1, np.int64),
                np.ones((1, 2), np.float32), np.zeros(1, np.int64))


class EvictedViewStore:
    """Per voxel key, the running mean OV sample of the evicted views, per channel (module docstring).

    Rows are appended (never reordered except by :meth:`compact`); a sorted index maps keys to rows.
    Every method takes the store's lock."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._reset(None)
        self.frames = EvictedFrameStore()
        """Reduced views of evicted keyframes without input depth (``queries.evicted_frames_mb``;
        :mod:`mapper.map.evicted_frames`): saved, loaded and cleared with these means."""

    def _reset(self, dim: int | None) -> None:
        cap = 0 if dim is None else 1024
        self._dim = dim
        self._n = 0
        self._keys = np.zeros(cap, np.int64)
        self._sorted_keys = np.zeros(0, np.int64)
        self._sorted_rows = np.zeros(0, np.int64)
        self._channels = {name: _Channel(np.zeros((cap, 0), np.float32), np.zeros(cap, np.float32))
                          for name in CHANNELS}  # means allocated when a channel is first written
        self.keyframes = 0
        """Keyframes absorbed since the store was made (or cleared, or restored)."""

    @property
    def dim(self) -> int | None:
        return self._dim

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes of the used rows (means, counts, keys) and the index."""
        with self._lock:
            per_row = 8 + sum(c.mean[:1].nbytes + 4 for c in self._channels.values())
            return int(self._n * per_row + self._sorted_keys.nbytes + self._sorted_rows.nbytes)

    def _rows_for(self, keys: np.ndarray, *, create: bool) -> np.ndarray:
        """Rows of ``keys`` (U,) unique int64; -1 where absent unless ``create`` (lock held)."""
        pos = np.searchsorted(self._sorted_keys, keys)
        inside = pos < self._sorted_keys.shape[0]
        found = np.zeros(keys.shape[0], bool)
        found[inside] = self._sorted_keys[pos[inside]] == keys[inside]
        rows = np.full(keys.shape[0], -1, np.int64)
        rows[found] = self._sorted_rows[pos[found]]
        if create and not found.all():
            new_keys = keys[~found]
            start, n_new = self._n, int(new_keys.shape[0])
            self._grow(start + n_new)
            new_rows = np.arange(start, start + n_new, dtype=np.int64)
            self._keys[new_rows] = new_keys
            rows[~found] = new_rows
            self._n = start + n_new
            order = np.argsort(new_keys, kind="stable")
            at = np.searchsorted(self._sorted_keys, new_keys[order])
            self._sorted_keys = np.insert(self._sorted_keys, at, new_keys[order])
            self._sorted_rows = np.insert(self._sorted_rows, at, new_rows[order])
        return rows

    def _reindex(self) -> None:
        """The sorted key index of the used rows, built anew (lock held)."""
        order = np.argsort(self._keys[: self._n], kind="stable")
        self._sorted_keys = self._keys[: self._n][order].copy()
        self._sorted_rows = order.astype(np.int64)

    def _grow(self, need: int) -> None:
        cap = self._keys.shape[0]
        if need <= cap:
            return
        new_cap = max(need, int(cap * 1.5) + 1024)

        def grown(a: np.ndarray) -> np.ndarray:
            out = np.zeros((new_cap, *a.shape[1:]), a.dtype)
            out[: self._n] = a[: self._n]
            return out

        self._keys = grown(self._keys)
        for ch in self._channels.values():
            ch.count = grown(ch.count)
            if ch.mean.shape[1]:  # a channel never written keeps no means (allocated on first use)
                ch.mean = grown(ch.mean)

    def absorb(
        self,
        keys: np.ndarray,  # (M,) int64 voxel keys (unique)
        samples: dict[str, tuple[np.ndarray, np.ndarray]],  # channel -> ((M, D) float32, counted (M,) bool)
        *,
        new_keyframe: bool = True,
    ) -> int:
        """Add one evicted view's samples: for each channel, each voxel it counted for takes the
        sample into its running mean (count + 1). Returns the voxels touched. ``ValueError`` on a
        shape or dimension mismatch or an unknown channel (nothing changed). ``new_keyframe`` False:
        more samples of the keyframe counted by the previous call (its voxels in chunks)."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        m = keys.shape[0]
        dim = None
        for name, (feat, counted) in samples.items():
            if name not in CHANNELS:
                raise ValueError(f"unknown channel {name!r}; one of {CHANNELS}")
            if feat.ndim != 2 or feat.shape[0] != m or np.shape(counted) != (m,):
                raise ValueError(f"channel {name!r}: samples must be ((M={m}, D), (M,)), got {feat.shape}, "
                                 f"{np.shape(counted)}")
            if dim is not None and feat.shape[1] != dim:
                raise ValueError("channels have different feature dimensions")
            dim = int(feat.shape[1])
        touched = np.zeros(m, bool)
        for _, counted in samples.values():
            touched |= np.asarray(counted, bool)
        with self._lock:
            if dim is None or not touched.any():
                self.keyframes += int(new_keyframe)
                return 0
            if self._dim is None:
                self._reset(dim)
            elif dim != self._dim:
                raise ValueError(f"samples have dimension {dim}, the store's {self._dim}")
            rows = np.full(m, -1, np.int64)
            rows[touched] = self._rows_for(keys[touched], create=True)
            for name, (feat, counted) in samples.items():
                counted = np.asarray(counted, bool)
                if not counted.any():
                    continue
                ch = self._channels[name]
                if ch.mean.shape[1] == 0:
                    ch.mean = np.zeros((self._keys.shape[0], dim), np.float32)
                absorb_rows(ch.mean, ch.count, rows[counted], np.asarray(feat, np.float32),
                            np.flatnonzero(counted))
            self.keyframes += int(new_keyframe)
            return int(touched.sum())

    def lookup(
        self,
        keys: np.ndarray,  # (U,) int64 voxel keys
        channel: str,
    ) -> tuple[np.ndarray, np.ndarray]:  # (U, D) float32 means (zero rows where none), (U,) float32 counts
        """The channel's mean and count per key (0 where the store has none)."""
        if channel not in CHANNELS:
            raise ValueError(f"unknown channel {channel!r}; one of {CHANNELS}")
        keys = np.asarray(keys, np.int64).reshape(-1)
        with self._lock:
            dim = self._dim or 0
            means = np.zeros((keys.shape[0], dim), np.float32)
            counts = np.zeros(keys.shape[0], np.float32)
            if self._n == 0:
                return means, counts
            ch = self._channels[channel]
            if ch.mean.shape[1] == 0:
                return means, counts
            rows = self._rows_for(keys, create=False)
            hit = rows >= 0
            means[hit] = ch.mean[rows[hit]]
            counts[hit] = ch.count[rows[hit]]
            return means, counts

    def cosines(
        self,
        keys: np.ndarray,  # (N,) int64 voxel keys (repeats allowed)
        text_emb: np.ndarray,  # (T, D) float32 unit rows
        min_views: float = 1.0,
        channels: tuple[str, ...] = ("depth", "all"),
    ) -> tuple[np.ndarray, np.ndarray]:  # (N, T) float32, (N,) bool
        """Cosines of each key's channel mean (unit-normalised) with the texts, from the first of
        ``channels`` where the voxel has at least ``min_views`` views, and where one did. Computed
        once per distinct voxel, reading the means in place (no (N, D) copy): a query's points
        share voxels, and the texts are few."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        emb = np.asarray(text_emb, np.float32)
        cos = np.zeros((keys.shape[0], emb.shape[0]), np.float32)
        given = np.zeros(keys.shape[0], bool)
        with self._lock:
            if self._n == 0 or self._dim != emb.shape[1]:
                return cos, given
            rows = self._rows_for(keys, create=False)
            for channel in channels:
                ch = self._channels[channel]
                if ch.mean.shape[1] == 0:
                    continue
                todo = np.flatnonzero((rows >= 0) & ~given)
                if todo.size == 0:
                    break
                take = todo[ch.count[rows[todo]] >= min_views]
                if take.size == 0:
                    continue
                unique, inverse = np.unique(rows[take], return_inverse=True)
                for start in range(0, unique.shape[0], 16384):  # bounded temporaries
                    part = unique[start:start + 16384]
                    m = ch.mean[part]
                    norms = np.maximum(np.linalg.norm(m, axis=1), np.float32(1e-12))
                    block = (m @ emb.T) / norms[:, None]
                    sel = (inverse >= start) & (inverse < start + part.shape[0])
                    cos[take[sel]] = block[inverse[sel] - start]
                given[take] = True
        return cos, given

    def prior(
        self,
        keys: np.ndarray,  # (N,) int64 voxel keys, one per query point (-1 or absent: none)
        channel: str,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The averaging's ``prior`` for points whose nearest voxels have ``keys``: (means (cap, D)
        float32, the channel's table itself, no copy; row (N,) int64, -1 where the voxel has no
        view of this channel; weight (N,) float32, the views behind it when this was called).

        The table is read in place: rows are never moved in it (:meth:`compact` and growth make new
        arrays), but the worker may add a view to a row while a query reads it, so a row read then
        is its mean before or after that view, element by element (both are means of the views; the
        weight is the count at this call)."""
        if channel not in CHANNELS:
            raise ValueError(f"unknown channel {channel!r}; one of {CHANNELS}")
        keys = np.asarray(keys, np.int64).reshape(-1)
        with self._lock:
            ch = self._channels[channel]
            table = ch.mean
            if table.shape[1] == 0:  # never written: no views (count 0 everywhere)
                table = np.zeros((self._n, self._dim or 0), np.float32)
            rows = self._rows_for(keys, create=False) if self._n else np.full(keys.shape[0], -1, np.int64)
            weight = np.zeros(keys.shape[0], np.float32)
            hit = rows >= 0
            weight[hit] = ch.count[rows[hit]]
        rows[hit & ~(weight > 0)] = -1
        return table, rows, weight

    def compact(self, keep_keys: np.ndarray) -> int:
        """Drop the rows whose key is not in ``keep_keys`` (e.g. voxels the map pruned). Returns the
        rows dropped."""
        keep_keys = np.unique(np.asarray(keep_keys, np.int64))
        with self._lock:
            n = self._n
            pos = np.searchsorted(keep_keys, self._keys[:n])
            inside = pos < keep_keys.shape[0]
            keep = np.zeros(n, bool)
            keep[inside] = keep_keys[pos[inside]] == self._keys[:n][inside]
            if keep.all():
                return 0
            rows = np.flatnonzero(keep)
            m = rows.shape[0]
            cap = self._keys.shape[0]

            def kept(a: np.ndarray) -> np.ndarray:  # new arrays: a query may be reading the old ones
                out = np.zeros((cap, *a.shape[1:]), a.dtype)
                out[:m] = a[rows]
                return out

            self._keys = kept(self._keys)
            for ch in self._channels.values():
                ch.count = kept(ch.count)
                if ch.mean.shape[1]:
                    ch.mean = kept(ch.mean)
            self._n = m
            self._reindex()
            return n - m

    def clear(self) -> None:
        with self._lock:
            self._reset(None)
        self.frames.clear()

    def stats(self) -> dict[str, Any]:
        with self._lock:
            n = self._n
            return {
                "voxels": n,
                "keyframes": self.keyframes,
                "views_all": float(self._channels["all"].count[:n].sum()),
                "views_depth": float(self._channels["depth"].count[:n].sum()),
            }

    # -- persistence (with the global map: mapper.map.global_map) ------------------------------

    def to_arrays(self, prefix: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """``({"<prefix>.<field>": array}, manifest)``: a consistent copy."""
        with self._lock:
            n = self._n
            arrays = {f"{prefix}.keys": self._keys[:n].copy()}
            for name, ch in self._channels.items():
                mean = ch.mean[:n].copy() if ch.mean.shape[1] else np.zeros((n, 0), np.float32)
                arrays[f"{prefix}.{name}_mean"] = mean  # (n, 0): a channel never written
                arrays[f"{prefix}.{name}_count"] = ch.count[:n].copy()
            manifest: dict[str, Any] = {"points": n, "dim": self._dim, "keyframes": self.keyframes}
        if len(self.frames):
            frame_arrays, manifest["frames"] = self.frames.to_arrays(f"{prefix}.frames")
            arrays.update(frame_arrays)
        return arrays, manifest

    def restore(self, arrays: dict[str, np.ndarray], manifest: object, prefix: str) -> None:
        """Replace the content with a saved one (inverse of :meth:`to_arrays`); ``ValueError``
        naming the field on a bad array (nothing changed)."""
        if not isinstance(manifest, dict):
            raise ValueError("evicted views section: the manifest must be a table")
        n, dim = manifest.get("points"), manifest.get("dim")
        if not isinstance(n, int) or n < 0 or not (dim is None or (isinstance(dim, int) and dim > 0)):
            raise ValueError("evicted views section: 'points' must be an int >= 0, 'dim' an int > 0 or null")
        spec: dict[str, tuple[str, tuple[int, ...]]] = {"keys": ("int64", (n,))}
        for name in CHANNELS:
            spec[f"{name}_mean"] = ("float32", (n, dim or 0))  # float16: saved before 2026-12-04
            spec[f"{name}_count"] = ("float32", (n,))
        got: dict[str, np.ndarray] = {}
        for field, (dtype, shape) in spec.items():
            arr = arrays.get(f"{prefix}.{field}")
            if field.endswith("_mean") and arr is not None and arr.shape == (n, 0):
                shape = (n, 0)  # a channel never written
            ok_dtype = arr is not None and (arr.dtype == np.dtype(dtype) or (
                field.endswith("_mean") and arr.dtype == np.float16))
            if arr is None or not ok_dtype or arr.shape != shape:
                desc = "missing" if arr is None else f"{arr.dtype} {arr.shape}"
                raise ValueError(f"evicted views section: {field} must be {dtype} {shape}, got {desc}")
            got[field] = arr
        if np.unique(got["keys"]).size != n:
            raise ValueError("evicted views section: keys are not unique")
        for name in CHANNELS:
            if not (np.isfinite(got[f"{name}_count"]).all() and (got[f"{name}_count"] >= 0).all()):
                raise ValueError(f"evicted views section: {name}_count must be finite and >= 0")
            if not np.isfinite(got[f"{name}_mean"]).all():
                raise ValueError(f"evicted views section: {name}_mean must be finite")
        keyframes = manifest.get("keyframes")
        frames = EvictedFrameStore()
        if manifest.get("frames") is not None:  # maps saved before the frames store lack it
            frames.restore(arrays, manifest["frames"], f"{prefix}.frames")
            if frames.dim is not None and dim is not None and frames.dim != dim:
                raise ValueError(f"evicted frames section: dimension {frames.dim}, the views' {dim}")
        self.frames = frames
        with self._lock:
            self._reset(dim)
            if dim is None:
                return
            self._grow(n)
            self._n = n
            self._keys[:n] = got["keys"]
            for name, ch in self._channels.items():
                ch.count[:n] = got[f"{name}_count"]
                if got[f"{name}_mean"].shape[1]:
                    ch.mean = np.zeros((self._keys.shape[0], dim), np.float32)
                    ch.mean[:n] = got[f"{name}_mean"]
            self._reindex()
            self.keyframes = keyframes if isinstance(keyframes, int) else 0


def in_image(
    xyz: np.ndarray,  # (M, 3) float32 world points
    K: np.ndarray,  # (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray,  # (4, 4)
    image_wh: tuple[int, int],
    border_px: float,
) -> np.ndarray:  # (m,) int64 rows
    """Rows of the points in front of the camera whose projection lies inside the image less a
    slightly smaller border than the averaging's (a superset of the points it counts: the kernel
    then applies its exact float32 test)."""
    if xyz.shape[0] == 0:
        return np.zeros(0, np.int64)
    pose = np.asarray(world_from_cam, np.float64)
    rot, t = pose[:3, :3], pose[:3, 3]
    cam = (np.asarray(xyz, np.float64) - t) @ rot  # (M, 3) = R^T (p - t)
    z = cam[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = cam[:, 0] / zs * float(K[0]) + float(K[2])
    v = cam[:, 1] / zs * float(K[1]) + float(K[3])
    margin = border_px - 1.0
    width, height = image_wh
    ok = front & (u >= margin) & (u <= width - margin) & (v >= margin) & (v <= height - margin)
    return np.flatnonzero(ok)
