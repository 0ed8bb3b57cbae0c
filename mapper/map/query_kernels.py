"""Compiled (numba) kernels of the node's queries: the map rows' cosines with the texts, computed
the same way for every row (so a cache can rescore a block's changed rows only and get the bits
that scoring the whole block gives), the radius components behind ``query_points``' object
clusters, and the nearest map point within a radius (:class:`NearestGrid`, the whole-map answers
of ``segment_points`` and ``render``).

All are CPU functions of numpy arrays; :func:`warm_up` compiles them (or loads them from numba's
on-disk cache) on one-row problems, which the node does in its warm-up thread.
"""

from __future__ import annotations

import itertools

import numba
import numpy as np

from mapper.kernels.average_kernel import dot, launch

__all__ = ["NearestGrid", "component_cells", "morton_codes", "row_cosines", "warm_up"]

_ROWS_PER_TASK = 256
_HALF_OFFSETS = np.array(
    [d for d in itertools.product(range(-2, 3), repeat=3) if d > (0, 0, 0)], np.int64
)
"""The 62 cell offsets in [-2, 2]^3 after (0, 0, 0) in lexicographic order, nearest first: cells of
side r / sqrt(3) up to 2 apart per axis can hold points within r (3 apart cannot), and each
unordered pair of cells is visited once."""
_HALF_OFFSETS = _HALF_OFFSETS[np.argsort((_HALF_OFFSETS**2).sum(axis=1), kind="stable")]
_DENSE_TABLE_ENTRIES = 1 << 22
"""Key grids up to this many cells (or 8x the occupied cells) find neighbours in a dense table."""


@numba.njit(parallel=True, boundscheck=False, cache=True)
def _row_cosines(feat, emb, rows, out, block):  # pragma: no cover - compiled
    n = rows.shape[0]
    m = emb.shape[0]
    for task in numba.prange((n + block - 1) // block):
        for i in range(task * block, min(n, (task + 1) * block)):
            row = feat[rows[i]]
            for t in range(m):
                out[i, t] = dot(row, emb[t])


def row_cosines(
    feat: np.ndarray,  # (N, D) float32 unit rows
    emb: np.ndarray,  # (M, D) float32 unit rows
    rows: np.ndarray | None = None,  # (K,) int row indices; None: every row
    *,
    threads: int = 0,
) -> np.ndarray:
    """(K, M) float32 ``feat[rows] @ emb.T``, each row's M dot products in one fixed order (the
    same bits whichever other rows are computed with it, unlike a BLAS product whose kernels
    depend on the matrix's shape). ``threads`` 0: numba's default."""
    feat = np.ascontiguousarray(feat, np.float32)
    emb = np.ascontiguousarray(emb, np.float32)
    if feat.ndim != 2 or emb.ndim != 2 or feat.shape[1] != emb.shape[1]:
        raise ValueError(f"feat (N, D) and emb (M, D) must share D, got {feat.shape} and {emb.shape}")
    idx = np.arange(feat.shape[0], dtype=np.int64) if rows is None else np.ascontiguousarray(rows, np.int64)
    out = np.empty((idx.shape[0], emb.shape[0]), np.float32)
    if out.size == 0:
        return out
    with launch(threads):
        _row_cosines(feat, emb, idx, out, _ROWS_PER_TASK)
    return out


@numba.njit(boundscheck=False, cache=True)
def _find(parent, a):  # pragma: no cover - compiled
    root = a
    while parent[root] != root:
        root = parent[root]
    while parent[a] != root:  # path compression
        nxt = parent[a]
        parent[a] = root
        a = nxt
    return root


@numba.njit(boundscheck=False, cache=True)
def _cells_linked(pts, start_a, count_a, start_b, count_b, r2):  # pragma: no cover - compiled
    """Some point of one cell (rows start_a .. of ``pts``, grouped by cell) within sqrt(r2) of some
    point of the other; the cells' first points are tested first."""
    for i in range(start_a, start_a + count_a):
        for j in range(start_b, start_b + count_b):
            dx = pts[i, 0] - pts[j, 0]
            dy = pts[i, 1] - pts[j, 1]
            dz = pts[i, 2] - pts[j, 2]
            if dx * dx + dy * dy + dz * dz <= r2:
                return True
    return False


@numba.njit(boundscheck=False, cache=True)
def _hash_slot(key, mask):  # pragma: no cover - compiled
    """A slot for an int64 key: the splitmix64 finaliser (every key bit moves the low bits)."""
    h = np.uint64(key)
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    h = h ^ (h >> np.uint64(31))
    return np.int64(h & np.uint64(mask))


@numba.njit(boundscheck=False, cache=True)
def _build_table(keys, mask):  # pragma: no cover - compiled
    """Open-addressing table (mask + 1 slots) of the distinct ascending ``keys``: slot -> index."""
    table = np.full(mask + 1, -1, np.int64)
    for c in range(keys.shape[0]):
        h = _hash_slot(keys[c], mask)
        while table[h] >= 0:
            h = (h + 1) & mask
        table[h] = c
    return table


@numba.njit(boundscheck=False, cache=True)
def _lookup(table, keys, mask, key):  # pragma: no cover - compiled
    h = _hash_slot(key, mask)
    while table[h] >= 0:
        if keys[table[h]] == key:
            return table[h]
        h = (h + 1) & mask
    return -1


@numba.njit(boundscheck=False, cache=True)
def _component_cells(pts, keys, starts, counts, deltas, dense_entries, r2):  # pragma: no cover - compiled
    n_cells = keys.shape[0]
    dense = dense_entries > 0
    # cell key -> cell index: a dense table over the key range, or an open-addressing hash
    if dense:
        table = np.full(dense_entries, -1, np.int64)
        for c in range(n_cells):
            table[keys[c]] = c
        mask = 0
    else:
        cap = 1
        while cap < 2 * n_cells:
            cap *= 2
        mask = cap - 1
        table = _build_table(keys, mask)
    parent = np.arange(n_cells)
    for c in range(n_cells):
        for o in range(deltas.shape[0]):
            target = keys[c] + deltas[o]
            d = -1
            if dense:
                if 0 <= target < dense_entries:
                    d = table[target]
            else:
                d = _lookup(table, keys, mask, target)
            if d < 0:
                continue
            ra, rb = _find(parent, c), _find(parent, d)
            if ra == rb:
                continue
            if _cells_linked(pts, starts[c], counts[c], starts[d], counts[d], r2):
                if ra < rb:
                    parent[rb] = ra
                else:
                    parent[ra] = rb
    # labels 0 .. n-1 in order of each component's first cell
    label = np.full(n_cells, -1, np.int64)
    n_comp = 0
    for c in range(n_cells):
        root = _find(parent, c)
        if label[root] < 0:
            label[root] = n_comp
            n_comp += 1
        label[c] = label[root]
    return n_comp, label


def component_cells(
    pts_by_cell: np.ndarray,  # (N, 3) float64 points, grouped by cell
    keys: np.ndarray,  # (C,) int64 ascending cell keys ((x * dims[1] + y) * dims[2] + z)
    dims: np.ndarray,  # (3,) int64 key grid; every cell coordinate in [2, dims - 3]
    starts: np.ndarray,  # (C,) int64 first row of each cell in ``pts_by_cell``
    counts: np.ndarray,  # (C,) int64 points per cell
    radius_m: float,
) -> tuple[int, np.ndarray]:
    """Connected components of the cells (cubes of side ``radius_m / sqrt(3)``: every point of a
    cell is within the radius of every other) when two cells are joined by any pair of their
    points at most ``radius_m`` apart: (count, (C,) int64 label, numbered in order of each
    component's first cell). Union-find; each cell's neighbours up to two cells apart per axis,
    nearest first, found in a dense table of the key grid (a hash when the grid is large) and
    tested point pair by point pair only while the two cells are in different components."""
    if keys.shape[0] == 0:
        return 0, np.zeros(0, np.int64)
    d1, d2 = int(dims[1]), int(dims[2])
    deltas = (_HALF_OFFSETS[:, 0] * d1 + _HALF_OFFSETS[:, 1]) * d2 + _HALF_OFFSETS[:, 2]
    entries = int(np.prod(dims.astype(np.float64)))
    dense_entries = entries if entries <= max(_DENSE_TABLE_ENTRIES, 8 * keys.shape[0]) else 0
    n, label = _component_cells(
        np.ascontiguousarray(pts_by_cell, np.float64), np.ascontiguousarray(keys, np.int64),
        np.ascontiguousarray(starts, np.int64), np.ascontiguousarray(counts, np.int64),
        deltas.astype(np.int64), dense_entries, float(radius_m) * float(radius_m),
    )
    return int(n), label


_GRID_MAX_CELLS = 1 << 24
"""A :class:`NearestGrid` holds at most this many cells (or 8x its points): 64 MB of int32 starts."""


@numba.njit(boundscheck=False, cache=True, inline="always")
def _scan_cells(q, pts, order, starts, dims, lo, hi, best_d2, best):  # pragma: no cover - compiled
    """The nearest of the points in the cells lo .. hi (inclusive, clipped to the grid) to q, if
    nearer than best_d2 (of equidistant points the lower ``order``): returns (d2, sorted index)."""
    for cx in range(max(lo[0], 0), min(hi[0], dims[0] - 1) + 1):
        for cy in range(max(lo[1], 0), min(hi[1], dims[1] - 1) + 1):
            base = (cx * dims[1] + cy) * dims[2]
            for cz in range(max(lo[2], 0), min(hi[2], dims[2] - 1) + 1):
                c = base + cz
                for j in range(starts[c], starts[c + 1]):
                    dx, dy, dz = q[0] - pts[j, 0], q[1] - pts[j, 1], q[2] - pts[j, 2]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < best_d2 or (d2 == best_d2 and order[j] < order[best]):
                        best_d2, best = d2, j
    return best_d2, best


@numba.njit(parallel=True, boundscheck=False, cache=True)
def _grid_nearest(queries, pts, order, starts, dims, origin, cell, radius, out, block):  # pragma: no cover
    n = queries.shape[0]
    r2 = radius * radius
    sure2 = (cell * (1.0 - 1e-9)) ** 2  # a nearest point this close is nearer than any outside the 3^3 cells
    for task in numba.prange((n + block - 1) // block):
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        for i in range(task * block, min(n, (task + 1) * block)):
            q = queries[i]
            for a in range(3):
                g = np.floor((q[a] - origin[a]) / cell)
                g = min(max(g, -4.0e18), 4.0e18)
                lo[a] = np.int64(g) - 1
                hi[a] = np.int64(g) + 1
            best_d2, best = _scan_cells(q, pts, order, starts, dims, lo, hi, np.inf, np.int64(-1))
            if not (best >= 0 and best_d2 < sure2):  # every cell the radius reaches
                for a in range(3):
                    lo[a] = np.int64(min(max(np.floor((q[a] - radius - origin[a]) / cell), -4.0e18), 4.0e18))
                    hi[a] = np.int64(min(max(np.floor((q[a] + radius - origin[a]) / cell), -4.0e18), 4.0e18))
                best_d2, best = _scan_cells(q, pts, order, starts, dims, lo, hi, best_d2, best)
            out[i] = best if (best >= 0 and best_d2 < r2) else -1


class NearestGrid:
    """The nearest of a fixed point set within a radius, for many queries: the points bucketed in a
    dense grid of cubes of side ``cell_m`` over their bounding box (a CSR of int32 cell starts). A
    query scans its own cell and the 26 around it; a point found nearer than one cell side is the
    nearest of all (every point outside those cells is at least that far), else it scans every cell
    the radius reaches. The answers of a k-d tree query with ``distance_upper_bound`` (the nearest
    point strictly within the radius, distances in float64), except that of equidistant points
    this takes the lowest index (a k-d tree takes any).

    :meth:`build` returns None when the grid would exceed ``_GRID_MAX_CELLS`` cells (and 8x the
    points): a sparse map over a large extent, where a k-d tree is the better index. A query that
    finds nothing within one cell scans (2 r / cell + 1)^3 cells; beyond ``MAX_REACH_CELLS`` cells
    of radius a k-d tree is the better index too."""

    MAX_REACH_CELLS = 4.0
    """The largest radius, in cells, the grid should answer (``GlobalMapSnapshot`` takes a k-d
    tree beyond it): a miss then scans at most 10^3 cells."""

    def __init__(self, pts: np.ndarray, starts: np.ndarray, dims: np.ndarray, origin: np.ndarray,
                 cell_m: float, order: np.ndarray) -> None:
        self.pts = pts  # (P, 3) float64, sorted by cell
        self.starts = starts  # (cells + 1,) int32
        self.dims = dims  # (3,) int64
        self.origin = origin  # (3,) float64
        self.cell_m = cell_m
        self.order = order  # (P,) int64: the given index of each sorted point

    @classmethod
    def build(cls, points: np.ndarray, cell_m: float) -> NearestGrid | None:
        """Index ``points`` (P, 3) (finite) with cubes of side ``cell_m`` > 0; None if too large."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if not cell_m > 0:
            raise ValueError(f"cell_m must be > 0, got {cell_m}")
        if pts.shape[0] == 0:
            return cls(pts, np.zeros(2, np.int32), np.ones(3, np.int64), np.zeros(3), float(cell_m),
                       np.zeros(0, np.int64))
        origin = pts.min(axis=0)
        span = np.floor((pts.max(axis=0) - origin) / cell_m) + 1.0
        if float(np.prod(span)) > max(_GRID_MAX_CELLS, 8 * pts.shape[0]) or pts.shape[0] >= 2**31:
            return None
        dims = span.astype(np.int64)
        idx = np.minimum(np.floor((pts - origin) / cell_m).astype(np.int64), dims - 1)
        lin = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        order = np.argsort(lin, kind="stable")
        counts = np.bincount(lin, minlength=int(np.prod(dims)))
        starts = np.zeros(counts.shape[0] + 1, np.int32)
        np.cumsum(counts, out=starts[1:])
        return cls(np.ascontiguousarray(pts[order]), starts, dims, origin, float(cell_m), order)

    def nearest(self, queries: np.ndarray, radius_m: float, *, threads: int = 0) -> np.ndarray:
        """(N,) int64 index (into the built points) of each query's nearest point strictly within
        ``radius_m``, -1 where there is none. ``queries`` (N, 3) must be finite (the caller's
        check: the node validates request points at the boundary)."""
        q = np.ascontiguousarray(np.asarray(queries, np.float64).reshape(-1, 3))
        out = np.full(q.shape[0], -1, np.int64)
        if q.shape[0] == 0 or self.order.shape[0] == 0 or not radius_m > 0:
            return out
        with launch(threads):
            _grid_nearest(q, self.pts, self.order, self.starts, self.dims, self.origin, self.cell_m,
                          float(radius_m), out, _ROWS_PER_TASK)
        hit = out >= 0
        out[hit] = self.order[out[hit]]
        return out


@numba.njit(boundscheck=False, cache=True, inline="always")
def _spread_bits(v):  # pragma: no cover - compiled
    """The 21 low bits of the uint64 ``v`` moved to every third bit (bit i -> bit 3i)."""
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    return (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)


@numba.njit(boundscheck=False, cache=True)
def _morton_codes(pts, origin, cell, out):  # pragma: no cover - compiled
    top = np.float64(2**21 - 1)
    for i in range(pts.shape[0]):
        code = np.uint64(0)
        for a in range(3):
            c = min(max(np.floor((pts[i, a] - origin[a]) / cell), 0.0), top)
            code |= _spread_bits(np.uint64(c)) << np.uint64(a)
        out[i] = code


def morton_codes(
    pts: np.ndarray,  # (N, 3) finite world metres
    origin: np.ndarray,  # (3,) the grid's corner
    cell_m: float,
) -> np.ndarray:  # (N,) uint64
    """Each point's Z-order (Morton) code: its cell ``floor((p - origin) / cell_m)``, clipped to
    [0, 2^21 - 1] per axis, with the bits of x, y and z interleaved (x lowest)."""
    if not cell_m > 0:
        raise ValueError(f"cell_m must be > 0, got {cell_m}")
    out = np.empty(pts.shape[0], np.uint64)
    _morton_codes(np.ascontiguousarray(pts, np.float64), np.asarray(origin, np.float64), float(cell_m), out)
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels now, on one-row problems."""
    row_cosines(np.ones((1, 2), np.float32), np.ones((1, 2), np.float32), threads=1)
    cell = np.array([62], np.int64)  # cell (2, 2, 2) of a 5 x 5 x 5 grid
    one = np.ones(1, np.int64)
    component_cells(np.zeros((1, 3)), cell, np.full(3, 5, np.int64), one - 1, one, 0.1)
    grid = NearestGrid.build(np.zeros((1, 3)), 0.1)
    assert grid is not None
    grid.nearest(np.zeros((1, 3)), 0.1, threads=1)
    morton_codes(np.zeros((1, 3)), np.zeros(3), 0.1)
