"""What keyframes without input depth saw before they left the window, kept as reduced views.

The per-voxel store (:mod:`mapper.map.evicted_views`) keeps an evicted keyframe's OV samples at the
global map's voxels. Without input depth the map has almost no voxels on textureless walls and
floors (nothing is triangulated there), so those samples have nowhere to go and the points there
lose every view that left the window. :class:`EvictedFrameStore` keeps such a keyframe itself, at
reduced size: its pose, intrinsics, image size and its OV map area-averaged to at most
``queries.evicted_frames_cells`` cells (float32, as the averaging kernel reads it in place; 384-d,
1200 cells, a 160 x 120 keyframe's whole 40 x 30 map: 1.8 MB a keyframe). Never the RGB.

At ``segment_points`` time (:meth:`EvictedFrameStore.means`) each point is projected into every kept
view whose frustum meets its block of points (blocks of Z-ordered points, culled against the
frustum planes less the averaging's border), and the views it falls in (inside the image less the
border, the averaging's test) give their bilinear samples of the reduced maps: their mean and how
many. The averaging then counts that mean as that many more views (the kernel's ``prior``), i.e.
as a window that never evicted (up to the reduction of the maps).

Memory is bounded by ``queries.evicted_frames_mb``: beyond it the oldest kept view is dropped (the
worker then adds its samples to the voxel store, as without this store) and counted. Saved and
loaded with the global map, inside the evicted views' section
(:meth:`mapper.map.evicted_views.EvictedViewStore.to_arrays`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["EvictedFrameStore", "KeptFrame", "as_dtype", "merged_prior", "reduce_ov", "reduced_shape"]

_FIELDS = ("cam_from_world", "K", "image_wh", "ov_wh", "order")

OCCLUSION_SIDE = 80
"""The longest side (pixels) of a kept view's z-buffer of a request's points (:meth:`EvictedFrameStore.means`
with an occlusion footprint): the points are splatted at this resolution at most."""


def _area_weights(n_in: int, n_out: int) -> np.ndarray:  # (n_out, n_in) float32 rows summing to 1
    """Area averaging along one axis: output cell i covers ``[i, i + 1) * n_in / n_out`` of the
    input; each input cell weighs by its overlap."""
    edges = np.arange(n_out + 1, dtype=np.float64) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    cells = np.arange(n_in, dtype=np.float64)[None, :]
    overlap = np.clip(np.minimum(hi, cells + 1.0) - np.maximum(lo, cells), 0.0, None)
    return (overlap / (n_in / n_out)).astype(np.float32)


def reduced_shape(h: int, w: int, max_cells: int) -> tuple[int, int]:
    """(h', w') of an (h, w) OV map reduced by :func:`reduce_ov` to at most ``max_cells`` cells."""
    out = reduce_ov(np.zeros((h, w, 1), np.float32), max_cells)
    return int(out.shape[0]), int(out.shape[1])


def as_dtype(a: np.ndarray, dtype: Any) -> np.ndarray:
    """``a`` as a C-contiguous array of ``dtype``. float16 <-> float32 go through OpenCV
    (``cv2.multiply`` by 1 into the other depth: the same values, rounding and Inf as numpy's cast,
    about 3 times as fast on a 640 x 480 frame's 384-d map, which numpy converts one element at a
    time); any other pair, numpy."""
    dtype = np.dtype(dtype)
    pair = {a.dtype.name, dtype.name}
    if a.dtype == dtype or pair != {"float16", "float32"} or a.size == 0 or a.ndim == 0:
        return np.ascontiguousarray(a, dtype)
    import cv2

    flat = np.ascontiguousarray(a).reshape(-1, a.shape[-1])
    depth = cv2.CV_32F if dtype == np.float32 else cv2.CV_16F
    return np.asarray(cv2.multiply(flat, 1.0, dtype=depth)).reshape(a.shape)  # type: ignore[call-overload]


def reduce_ov(ov: np.ndarray, max_cells: int) -> np.ndarray:
    """(h, w, D) OV map -> (h', w', D) float32 area average with ``h' * w' <= max_cells`` (the
    aspect kept; unchanged but float32 when it already fits)."""
    if ov.ndim != 3:
        raise ValueError(f"ov must be (h, w, D), got {ov.shape}")
    if max_cells < 1:
        raise ValueError(f"max_cells must be >= 1, got {max_cells}")
    h, w = int(ov.shape[0]), int(ov.shape[1])
    if h * w <= max_cells:
        return as_dtype(np.asarray(ov), np.float32)
    s = np.sqrt(max_cells / (h * w))
    h2, w2 = max(1, int(np.floor(h * s))), max(1, int(np.floor(w * s)))
    while h2 * w2 > max_cells:  # a side floored at 1 (a very thin map)
        if w2 >= h2:
            w2 -= 1
        else:
            h2 -= 1
    if h % h2 == 0 and w % w2 == 0:  # whole blocks: their mean, the same area average without the weights
        bh, bw = h // h2, w // w2
        blocks = as_dtype(np.asarray(ov), np.float32).reshape(h2, bh, w2, bw, -1)
        acc = np.zeros((h2, w2, blocks.shape[-1]), np.float32)
        for i in range(bh):  # one strided slice per offset in the block
            for j in range(bw):
                acc += blocks[:, i, :, j]
        acc *= np.float32(1.0 / (bh * bw))
        return acc
    feat = as_dtype(np.asarray(ov), np.float32)
    out = np.einsum("ih,hwd,jw->ijd", _area_weights(h, h2), feat, _area_weights(w, w2), optimize=True)
    return np.ascontiguousarray(out, np.float32)


@dataclass(frozen=True)
class KeptFrame:
    """One view the store dropped (to be absorbed elsewhere): the fields of a keyframe the
    evicted-views worker reads (``ov`` reduced, no depth)."""

    ov: np.ndarray  # (h', w', D) float32
    K: np.ndarray  # (4,) float64
    world_from_cam: np.ndarray  # (4, 4) float64
    width: int
    height: int
    depth_m: None = None


class EvictedFrameStore:
    """Reduced views of evicted keyframes in fixed slots of one float32 table (module docstring).
    Every method takes the store's lock (:meth:`means` for its whole computation: a view added
    meanwhile waits, so a query never reads a slot being replaced)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._reset(None, 0)
        self.dropped = 0
        """Views dropped for the memory budget since the store was made."""
        self.added = 0
        """Views added since the store was made (or restored)."""

    def _reset(self, dim: int | None, cells: int) -> None:
        self._dim = dim
        self._cells = cells  # rows per slot
        self._table = np.zeros((0, dim or 0), np.float32)
        self._learned: np.ndarray | None = None  # the learned maps' table (rows as ``_table``), once one came
        self._has_learned = np.zeros(0, bool)
        self._keys: dict[int, Any] = {}  # slot -> the key its view was added with
        self._slots = 0
        self._used = np.zeros(0, bool)
        self._cam_from_world = np.zeros((0, 4, 4), np.float32)
        self._world_from_cam = np.zeros((0, 4, 4), np.float64)
        self._K = np.zeros((0, 4), np.float32)
        self._image_wh = np.zeros((0, 2), np.int64)
        self._ov_wh = np.zeros((0, 2), np.int64)
        self._order = np.zeros(0, np.int64)
        self._next = 0

    @property
    def dim(self) -> int | None:
        return self._dim

    def __len__(self) -> int:
        with self._lock:
            return int(self._used.sum())

    def _frame_bytes(self) -> int:
        tables = 1 if self._learned is None else 2
        return tables * self._cells * (self._dim or 0) * 4 + 4 * 16 + 8 * 16 + 16 + 32 + 8 + 2

    @property
    def nbytes(self) -> int:
        """Bytes of the kept views (their table slots and per-view constants)."""
        with self._lock:
            return int(self._used.sum()) * self._frame_bytes()

    def _grow(self, slots: int) -> None:
        """At least ``slots`` slots (lock held): new arrays, the used ones copied."""
        if slots <= self._slots:
            return
        new = max(slots, 2 * self._slots, 8)
        table = np.zeros((new * self._cells, self._dim or 0), np.float32)
        table[: self._table.shape[0]] = self._table
        self._table = table
        if self._learned is not None:
            learned = np.zeros_like(table)
            learned[: self._learned.shape[0]] = self._learned
            self._learned = learned

        def grown(a: np.ndarray, fill: Any = 0) -> np.ndarray:
            out = np.full((new, *a.shape[1:]), fill, a.dtype)
            out[: a.shape[0]] = a
            return out

        self._used = grown(self._used, False)
        self._has_learned = grown(self._has_learned, False)
        self._cam_from_world = grown(self._cam_from_world)
        self._world_from_cam = grown(self._world_from_cam)
        self._K = grown(self._K)
        self._image_wh = grown(self._image_wh, 1)
        self._ov_wh = grown(self._ov_wh, 1)
        self._order = grown(self._order)
        self._slots = new

    def _take_out(self, slot: int) -> KeptFrame:
        """The view in ``slot`` as a :class:`KeptFrame`, its slot freed (lock held)."""
        w, h = (int(x) for x in self._ov_wh[slot])
        rows = self._table[slot * self._cells: slot * self._cells + w * h]
        frame = KeptFrame(rows.reshape(h, w, -1).copy(), self._K[slot].astype(np.float64),
                          self._world_from_cam[slot].copy(), int(self._image_wh[slot, 0]),
                          int(self._image_wh[slot, 1]))
        self._used[slot] = False
        self._keys.pop(slot, None)
        return frame

    def add(
        self,
        ov: np.ndarray,  # (h, w, D) the keyframe's OV map
        K: np.ndarray,  # (4,) fx, fy, cx, cy of the image
        world_from_cam: np.ndarray,  # (4, 4)
        image_wh: tuple[int, int],
        *,
        max_cells: int,
        budget_bytes: int,
        learned: tuple[np.ndarray, np.ndarray] | None = None,  # (h', w', D) float32, (h', w') bool valid
        key: Any = None,
    ) -> list[KeptFrame]:
        """Keep one evicted view (its OV map reduced to at most ``max_cells`` cells); returns the
        views dropped to stay within ``budget_bytes`` (oldest first), or this view itself when the
        budget holds none. ``learned``: the learned model's features at the reduced grid's cells
        (:func:`reduced_shape`) and where they are valid, kept beside it for the learned method's
        answers (:meth:`means` with ``learned``; its invalid cells take the reduced map's rows),
        now or later by ``key`` (:meth:`set_learned`). ``ValueError`` on bad shapes or another
        dimension (nothing changed)."""
        from mapper.kernels.average import invert_poses

        K = np.asarray(K, np.float64).reshape(-1)
        pose = np.asarray(world_from_cam, np.float64)
        if K.shape != (4,) or pose.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(pose).all()):
            raise ValueError("evicted frame: K must be (4,) and world_from_cam (4, 4), finite")
        if int(image_wh[0]) < 1 or int(image_wh[1]) < 1:
            raise ValueError(f"evicted frame: image size {image_wh} must be positive")
        small = reduce_ov(np.asarray(ov), max_cells)
        h, w, dim = small.shape
        if learned is not None:
            learned = (_learned_rows(learned, small), learned[1])
        with self._lock:
            if self._dim is not None and dim != self._dim and self._used.any():
                raise ValueError(f"evicted frame: dimension {dim}, the store's {self._dim}")
            if not self._used.any() and (self._dim != dim or self._cells != max_cells):
                self._reset(dim, max_cells)
            if h * w > self._cells:  # a store restored with fewer cells: reduced to its own
                small = reduce_ov(small, self._cells)
                learned = None if learned is None else (reduce_ov(learned[0], self._cells), learned[1])
                h, w, dim = small.shape
            if learned is not None and self._learned is None:  # the first learned map: a second table
                self._learned = self._table.copy()
            room = budget_bytes // self._frame_bytes()
            dropped: list[KeptFrame] = []
            while int(self._used.sum()) >= max(room, 1) and self._used.any():
                used = np.flatnonzero(self._used)
                dropped.append(self._take_out(int(used[np.argmin(self._order[used])])))
            if room < 1:  # the budget holds no view: this one is dropped too
                self.dropped += len(dropped) + 1
                return [*dropped, KeptFrame(small, K, pose, int(image_wh[0]), int(image_wh[1]))]
            free = np.flatnonzero(~self._used[: self._slots])
            if free.size == 0:
                self._grow(self._slots + 1)
                free = np.flatnonzero(~self._used)
            slot = int(free[0])
            self._table[slot * self._cells: slot * self._cells + h * w] = small.reshape(h * w, dim)
            if self._learned is not None:
                rows = small if learned is None else learned[0]
                self._learned[slot * self._cells: slot * self._cells + h * w] = rows.reshape(h * w, dim)
            self._has_learned[slot] = learned is not None
            self._keys.pop(slot, None)
            if key is not None:
                self._keys[slot] = key
            self._world_from_cam[slot] = pose
            self._cam_from_world[slot] = invert_poses(pose.astype(np.float32)[None])[0]
            self._K[slot] = K.astype(np.float32)
            self._image_wh[slot] = (int(image_wh[0]), int(image_wh[1]))
            self._ov_wh[slot] = (w, h)
            self._order[slot] = self._next
            self._next += 1
            self._used[slot] = True
            self.added += 1
            self.dropped += len(dropped)
            return dropped

    def set_learned(self, key: Any, learned: tuple[np.ndarray, np.ndarray]) -> bool:
        """Give the view added with ``key`` its learned features (``learned`` as :meth:`add` takes
        it, at the view's reduced grid). Returns False (nothing changed) when no kept view has that
        key (not kept yet, or dropped); ``ValueError`` on bad shapes."""
        with self._lock:
            slot = next((s for s, k in self._keys.items() if k == key), None)
            if slot is None:
                return False
            w, h = (int(x) for x in self._ov_wh[slot])
            base = slot * self._cells
            small = self._table[base: base + w * h].reshape(h, w, -1)
            rows = _learned_rows(learned, small)
            if self._learned is None:
                self._learned = self._table.copy()
            self._learned[base: base + w * h] = rows.reshape(h * w, -1)
            self._has_learned[slot] = True
            return True

    def means(
        self,
        xyz: np.ndarray,  # (N, 3) float32 world points
        *,
        border_px: float = 10.0,
        threads: int = 0,
        block: int = 2048,
        cell_m: float = 0.25,
        occlusion_footprint_m: float = 0.0,
        depth_tol: float = 0.25,
        occluders: np.ndarray | None = None,  # (M, 3) the points splatted (default: ``xyz``)
        learned: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The kept views' samples at the points: (rows (m,) int64 of the points at least one
        view counts for, their mean samples (m, D) float32, their view counts (m,) float32). A view
        counts for a point in front of it and inside its image less ``border_px`` (the
        averaging's test, in the compiled kernel); each point's sample is the bilinear tap of the
        view's reduced map. With ``occlusion_footprint_m`` > 0 a view counts only where no other
        of the points hides the point in it: the points are splatted into each view (each covering
        that footprint, at most :data:`OCCLUSION_SIDE` pixels a side) and a point passes where its
        depth is within ``depth_tol`` of that z-buffer (the test ``average_depth`` makes against the
        request's points for window keyframes without depth). With ``learned``, the views kept with
        the learned model's features (:meth:`add`) are sampled from those."""
        from mapper.kernels import average_kernel as kernel
        from mapper.map.query_kernels import morton_codes

        pts = np.ascontiguousarray(xyz, np.float32)
        n = pts.shape[0]
        empty = (np.zeros(0, np.int64), np.zeros((0, self._dim or 0), np.float32), np.zeros(0, np.float32))
        with self._lock:
            slots = np.flatnonzero(self._used)
            if n == 0 or slots.size == 0:
                return empty
            table = self._learned if learned and self._learned is not None else self._table
            order = np.argsort(morton_codes(pts.astype(np.float64), pts.min(axis=0), cell_m), kind="stable")
            means = np.zeros((n, self._dim or 0), np.float32)
            counts = np.zeros(n, np.float32)
            starts = np.arange(0, n, block)
            visible = self._visible(pts, order, starts, block, slots, border_px)  # (B, S) bool
            occ = None
            if occlusion_footprint_m > 0:
                occ = self._occluders(pts if occluders is None else np.asarray(occluders, np.float32), slots,
                                      np.asarray(visible.any(axis=0), bool), occlusion_footprint_m, threads)
            for b, lo in enumerate(starts):
                vis = slots[visible[b]]
                if vis.size == 0:
                    continue
                idx = order[lo: lo + block]
                right = (self._image_wh[vis, 0] - border_px).astype(np.float64)
                bottom = (self._image_wh[vis, 1] - border_px).astype(np.float64)
                ov_scale = (self._ov_wh[vis] / self._image_wh[vis]).astype(np.float32)
                k = vis.size
                if occ is None:
                    depth = (np.zeros(1, np.float32), np.zeros(k, np.int64), np.ones(k, np.int64),
                             np.ones(k, np.int64), np.ones((k, 2), np.float32))
                else:
                    pos = np.searchsorted(slots, vis)
                    depth = (occ[0], occ[1][pos], occ[2][pos, 0], occ[2][pos, 1], occ[3][pos])
                out, count = kernel.average_kernel(
                    pts[idx], self._cam_from_world[vis], self._K[vis], right, bottom, float(border_px), 1e-6,
                    vis.astype(np.int64) * self._cells, self._ov_wh[vis, 0], self._ov_wh[vis, 1], ov_scale,
                    table, use_depth=occ is not None, has_depth=np.ones(k, bool),
                    depth_flat=depth[0], d_off=depth[1], d_w=depth[2],
                    d_h=depth[3], d_scale=depth[4], depth_tol=float(depth_tol),
                    distance_power=0.0, view_weights=None, texts=None, threads=threads, raw=True)
                means[idx] = out
                counts[idx] = count
        rows = np.flatnonzero(counts > 0)
        return rows, means[rows], counts[rows]

    def _occluders(
        self, pts: np.ndarray, slots: np.ndarray, any_block: np.ndarray, footprint_m: float, threads: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The points' z-buffer in each of ``slots`` whose frustum meets a block (``any_block``
        (S,) bool; the others get an empty 1 x 1 map): (depths flat, offset (S,) int64, size
        (S, 2) int64 w x h, scale (S, 2) float32 from image pixels to the z-buffer's)."""
        from mapper.geometry.splat import occluder_depths

        size = np.ones((slots.shape[0], 2), np.int64)
        scale = np.ones((slots.shape[0], 2), np.float32)
        maps: list[np.ndarray] = [np.zeros(1, np.float32)] * slots.shape[0]
        wh = self._image_wh[slots]
        for w, h in {(int(a), int(b)) for a, b in wh[any_block]}:
            s = min(1.0, OCCLUSION_SIDE / max(w, h))
            zw, zh = max(1, int(round(w * s))), max(1, int(round(h * s)))
            group = np.flatnonzero(any_block & (wh[:, 0] == w) & (wh[:, 1] == h))
            K = self._K[slots[group]].astype(np.float64) * np.array([zw / w, zh / h, zw / w, zh / h])
            z = occluder_depths(pts, K, self._world_from_cam[slots[group]], zw, zh, footprint_m,
                                threads=max(threads, 1))
            for j, g in enumerate(group):
                maps[g] = z[j].reshape(-1)
                size[g] = (zw, zh)
                scale[g] = (zw / w, zh / h)
        offset = np.concatenate([[0], np.cumsum([m.size for m in maps])[:-1]]).astype(np.int64)
        return np.concatenate(maps).astype(np.float32), offset, size, scale

    def _visible(
        self, pts: np.ndarray, order: np.ndarray, starts: np.ndarray, block: int, slots: np.ndarray,
        border_px: float,
    ) -> np.ndarray:  # (B, S) bool
        """Whether each kept view's frustum (less the border) may meet each block's bounding box:
        a view is culled for a block when all eight corners lie behind one of its five planes
        (in front; left, right, top, bottom of the image less the border), a conservative test."""
        sorted_pts = pts[order].astype(np.float64)
        lo = np.minimum.reduceat(sorted_pts, starts, axis=0) - 1e-3
        hi = np.maximum.reduceat(sorted_pts, starts, axis=0) + 1e-3
        bits = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], bool)  # (8, 3)
        corners = np.where(bits[None], hi[:, None, :], lo[:, None, :])  # (B, 8, 3)
        out = np.zeros((starts.shape[0], slots.shape[0]), bool)
        for s0 in range(0, slots.shape[0], 256):  # (B, 256, 8, 3) at a time
            sl = slots[s0: s0 + 256]
            pose = self._cam_from_world[sl].astype(np.float64)  # (S, 4, 4)
            cam = np.einsum("sij,bcj->bsci", pose[:, :3, :3], corners) + pose[None, :, None, :3, 3]
            x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
            fx, fy, cx, cy = (self._K[sl, i].astype(np.float64)[None, :, None] for i in range(4))
            w = self._image_wh[sl, 0].astype(np.float64)[None, :, None]
            h = self._image_wh[sl, 1].astype(np.float64)[None, :, None]
            b = float(border_px)
            planes = (z, fx * x + (cx - b) * z, (w - b - cx) * z - fx * x, fy * y + (cy - b) * z,
                      (h - b - cy) * z - fy * y)
            culled = np.zeros(out[:, s0: s0 + 256].shape, bool)
            for p in planes:
                culled |= (p <= 0).all(axis=2)
            out[:, s0: s0 + 256] = ~culled
        return out

    def clear(self) -> None:
        with self._lock:
            self._reset(None, 0)

    def stats(self) -> dict[str, Any]:
        """``status`` figures; without the lock (a query may hold it for its whole computation and
        ``status`` runs under the node's state lock): counts read as they are."""
        kept = int(self._used.sum())
        return {"frames": kept, "frames_learned": int((self._used & self._has_learned).sum()),
                "frames_bytes": kept * self._frame_bytes(),
                "frames_dropped": self.dropped, "frames_added": self.added, "frame_cells": self._cells}

    # -- persistence (inside the evicted views' section of the global map) ----------------------

    def to_arrays(self, prefix: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """``({"<prefix>.<field>": array}, manifest)`` of the kept views, oldest first."""
        with self._lock:
            used = np.flatnonzero(self._used)
            used = used[np.argsort(self._order[used])]
            dim = self._dim or 0
            ov = np.zeros((used.shape[0], self._cells, dim), np.float32)
            for i, s in enumerate(used):
                ov[i] = self._table[s * self._cells: (s + 1) * self._cells]
            arrays = {f"{prefix}.ov": ov, f"{prefix}.world_from_cam": self._world_from_cam[used].copy(),
                      f"{prefix}.K": self._K[used].astype(np.float64),
                      f"{prefix}.image_wh": self._image_wh[used].copy(),
                      f"{prefix}.ov_wh": self._ov_wh[used].copy()}
            if self._learned is not None:
                learned = np.zeros_like(ov)
                for i, s in enumerate(used):
                    learned[i] = self._learned[s * self._cells: (s + 1) * self._cells]
                arrays[f"{prefix}.learned"] = learned
                arrays[f"{prefix}.has_learned"] = self._has_learned[used].copy()
            return arrays, {"frames": int(used.shape[0]), "dim": self._dim, "cells": self._cells,
                            "learned": self._learned is not None}

    def restore(self, arrays: dict[str, np.ndarray], manifest: object, prefix: str) -> None:
        """Replace the content with a saved one (inverse of :meth:`to_arrays`); ``ValueError``
        naming the field on a bad array (nothing changed)."""
        if not isinstance(manifest, dict):
            raise ValueError("evicted frames section: the manifest must be a table")
        n, dim, cells = manifest.get("frames"), manifest.get("dim"), manifest.get("cells")
        if not (isinstance(n, int) and n >= 0 and isinstance(cells, int) and cells >= 0
                and (dim is None or (isinstance(dim, int) and dim > 0))):
            raise ValueError("evicted frames section: 'frames' and 'cells' must be ints >= 0, "
                             "'dim' an int > 0 or null")
        spec = {"ov": ("float32", (n, cells, dim or 0)), "world_from_cam": ("float64", (n, 4, 4)),
                "K": ("float64", (n, 4)), "image_wh": ("int64", (n, 2)), "ov_wh": ("int64", (n, 2))}
        got = {}
        for field, (dtype, shape) in spec.items():
            arr = arrays.get(f"{prefix}.{field}")
            if arr is None or arr.dtype != np.dtype(dtype) or arr.shape != shape:
                desc = "missing" if arr is None else f"{arr.dtype} {arr.shape}"
                raise ValueError(f"evicted frames section: {field} must be {dtype} {shape}, got {desc}")
            if not np.isfinite(arr).all():
                raise ValueError(f"evicted frames section: {field} must be finite")
            got[field] = arr
        if n and ((got["image_wh"] < 1).any() or (got["ov_wh"] < 1).any()
                  or (got["ov_wh"].prod(axis=1) > cells).any()):
            raise ValueError("evicted frames section: image_wh and ov_wh must be >= 1, ov_wh within 'cells'")
        learned = manifest.get("learned", False) is True  # maps saved before the learned table: none
        if learned:
            table, has = arrays.get(f"{prefix}.learned"), arrays.get(f"{prefix}.has_learned")
            if table is None or table.dtype != np.float32 or table.shape != got["ov"].shape \
                    or not np.isfinite(table).all() or has is None or has.dtype != bool or has.shape != (n,):
                raise ValueError(f"evicted frames section: learned must be finite float32 {got['ov'].shape} "
                                 f"and has_learned bool ({n},)")
        from mapper.kernels.average import invert_poses

        with self._lock:
            self._reset(dim if n else None, cells if n else 0)
            if not n:
                return
            self._grow(n)
            self._table[: n * cells] = got["ov"].reshape(n * cells, -1)
            if learned:
                self._learned = np.zeros_like(self._table)
                self._learned[: n * cells] = arrays[f"{prefix}.learned"].reshape(n * cells, -1)
                self._has_learned[:n] = arrays[f"{prefix}.has_learned"]
            self._world_from_cam[:n] = got["world_from_cam"]
            self._cam_from_world[:n] = invert_poses(got["world_from_cam"].astype(np.float32))
            self._K[:n] = got["K"].astype(np.float32)
            self._image_wh[:n] = got["image_wh"]
            self._ov_wh[:n] = got["ov_wh"]
            self._order[:n] = np.arange(n)
            self._next = n
            self._used[:n] = True


def _learned_rows(learned: tuple[np.ndarray, np.ndarray], small: np.ndarray) -> np.ndarray:
    """(h', w', D) float32: the learned features where valid, the reduced map ``small`` elsewhere;
    ``ValueError`` unless they are finite at ``small``'s shape with an (h', w') mask."""
    feats, valid = np.asarray(learned[0], np.float32), np.asarray(learned[1], bool)
    if feats.shape != small.shape or valid.shape != small.shape[:2] or not np.isfinite(feats).all():
        raise ValueError(f"evicted frame: learned features must be finite {small.shape} with a "
                         f"{small.shape[:2]} mask, got {feats.shape} and {valid.shape}")
    return np.where(valid[..., None], feats, small).astype(np.float32)


def merged_prior(
    n: int,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None,  # the voxels' (table, row (n,), weight (n,))
    rows: np.ndarray,  # (m,) int64 points the kept views count for (EvictedFrameStore.means)
    mean: np.ndarray,  # (m, D) float32 their mean samples
    count: np.ndarray,  # (m,) float32 their views
    dim: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The averaging's ``prior`` of ``n`` points from both stores: each point's mean over the
    voxel's evicted views (``prior``) and the kept views' samples, weighted by their counts
    (table (n, D) float32, row ``arange`` or -1 where neither has a view, weight the views), or
    None when neither has any."""
    table = np.zeros((n, dim), np.float32)
    weight = np.zeros(n, np.float32)
    if prior is not None:
        p_tab, p_row, p_w = prior
        hit = (p_row >= 0) & (p_w > 0)
        table[hit] = p_tab[p_row[hit]] * p_w[hit, None]
        weight[hit] = p_w[hit]
    table[rows] += mean * count[:, None]
    weight[rows] += count
    ok = weight > 0
    if not ok.any():
        return None
    table[ok] /= weight[ok, None]
    return table, np.where(ok, np.arange(n), -1).astype(np.int64), weight
