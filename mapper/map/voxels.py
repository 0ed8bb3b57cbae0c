"""Voxel keys of the global map: a voxel's integer indices packed into one int64, 21 bits per axis.

The packing orders keys by x index, then y, then z, so the voxels of one (x, y) column of the
grid are one run of a sorted key array (:func:`column_runs`): what lets a box of the grid be
looked up with a binary search per column instead of a pass over every voxel.

>>> import numpy as np
>>> keys, ok = voxel_keys(np.array([[0.01, 0.02, 0.03], [0.12, 0.0, -0.01]]), 0.1)
>>> bool(ok.all()), bool(keys[0] < keys[1])
(True, True)
"""

from __future__ import annotations

import numpy as np

__all__ = ["KEY_BITS", "KEY_OFFSET", "box_rows", "column_runs", "pack_indices", "voxel_keys"]

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
"""Voxel indices are packed into one int64 key, 21 bits per axis: |index| < 2**20 voxels per axis
(about +-52 km at 5 cm voxels). Points outside are dropped."""

MAX_BOX_COLUMNS = 1 << 18
""":func:`box_rows` searches per (x, y) column up to this many columns; beyond it per x slab (more
candidates, each still inside the box's x and y extent)."""


def pack_indices(idx: np.ndarray) -> np.ndarray:
    """(N,) int64 keys of (N, 3) int64 voxel indices (each within ``+-(KEY_OFFSET - 1)``)."""
    idx = np.asarray(idx, np.int64) + KEY_OFFSET
    return (idx[:, 0] << (2 * KEY_BITS)) | (idx[:, 1] << KEY_BITS) | idx[:, 2]


def voxel_keys(
    xyz: np.ndarray,  # (N, 3) world metres
    voxel_size_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Packed int64 voxel keys of points, and a (N,) bool mask of the points inside the key range."""
    idx = np.floor(np.asarray(xyz, np.float64) / voxel_size_m)
    ok = np.all(np.abs(idx) < KEY_OFFSET - 1, axis=1) & np.all(np.isfinite(idx), axis=1)
    return pack_indices(np.where(ok[:, None], idx, 0).astype(np.int64)), ok


def column_runs(
    sorted_keys: np.ndarray,  # (n,) int64 ascending
    lo: np.ndarray,  # (3,) int64 lowest voxel index of the box
    hi: np.ndarray,  # (3,) int64 highest voxel index of the box (inclusive)
) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) positions in ``sorted_keys`` of the runs that hold the box's voxels: one run per
    (x, y) column (exactly the box), or, when the box has more than :data:`MAX_BOX_COLUMNS`
    columns, one per x slab from (x, y_lo, z_lo) to (x, y_hi, z_hi) (which also holds voxels of
    the columns in between above and below the box)."""
    xs = np.arange(lo[0], hi[0] + 1, dtype=np.int64)
    if xs.size * (hi[1] - lo[1] + 1) <= MAX_BOX_COLUMNS:
        gx, gy = (a.ravel() for a in np.meshgrid(xs, np.arange(lo[1], hi[1] + 1, dtype=np.int64),
                                                  indexing="ij"))
        first = np.stack([gx, gy, np.full_like(gx, lo[2])], axis=1)
        last = np.stack([gx, gy, np.full_like(gx, hi[2])], axis=1)
    else:
        first = np.stack([xs, np.full_like(xs, lo[1]), np.full_like(xs, lo[2])], axis=1)
        last = np.stack([xs, np.full_like(xs, hi[1]), np.full_like(xs, hi[2])], axis=1)
    start = np.searchsorted(sorted_keys, pack_indices(first), side="left")
    end = np.searchsorted(sorted_keys, pack_indices(last), side="right")
    keep = end > start
    return start[keep], end[keep]


def box_rows(
    sorted_keys: np.ndarray,  # (n,) int64 ascending
    sorted_rows: np.ndarray,  # (n,) int64 the row of each sorted key
    box_min: np.ndarray,  # (3,) world metres
    box_max: np.ndarray,  # (3,) world metres
    voxel_size_m: float,
) -> np.ndarray:
    """The rows (int64, unordered) of the voxels in the axis-aligned box, and possibly some more
    (:func:`column_runs`): the candidates a caller then tests exactly. An empty index or a box
    outside the key range: none."""
    if sorted_keys.shape[0] == 0:
        return np.zeros(0, np.int64)
    lo = np.floor(np.asarray(box_min, np.float64) / voxel_size_m)
    hi = np.floor(np.asarray(box_max, np.float64) / voxel_size_m)
    bound = KEY_OFFSET - 2
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (lo > bound).any() or (hi < -bound).any():
        return np.zeros(0, np.int64)
    lo, hi = np.clip(lo, -bound, bound).astype(np.int64), np.clip(hi, -bound, bound).astype(np.int64)
    start, end = column_runs(sorted_keys, lo, hi)
    lengths = end - start
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    # positions start[r] .. end[r] - 1 of every run, without a Python loop
    offsets = np.repeat(start - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
    return sorted_rows[np.arange(total, dtype=np.int64) + offsets]
