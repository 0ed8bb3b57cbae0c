"""Paged tiles of the global map: an SQLite file that holds the voxels the map moved out of memory.

The global map (:mod:`mapper.map.global_map`) keeps at most ``global_map.max_points`` voxels in
memory. Beyond it, whole spatial tiles (cubes of ``global_map.tile_m`` metres, aligned to the voxel
grid) that were least recently observed are written here and dropped from memory; they come back
when an observation touches them, when a ``segment_points`` asks about points in them, and
``query_points`` reads the tiles that may match without making them resident.

One row per tile, its voxels' arrays as BLOBs of raw little-endian bytes whose dtypes the schema
fixes (``keys`` int64, ``xyz`` float32 (n, 3), ``weight`` / ``feat_norm`` / ``feat_weight``
float32, ``hits`` int32, ``last_seen_ns`` / ``last_seen_kf`` int64, ``learned`` uint8, ``feat``
float16 (n, dim) or NULL without features) and the tile's feature summary (:func:`tile_summary`).
Every write is one transaction; the file is opened in WAL mode (readers in other processes see the
last committed state while this process writes). The file is the node's scratch space: a saved map
(``save``) holds the paged tiles too, and the file is deleted with its map.

Why SQLite (zarr, LanceDB and LMDB compared in docs/concepts/map-paging.md): it is in Python's
standard library (no new dependency), transactional, one writer with several reader processes in
WAL mode, and a tile is one row looked up by its integer key.

Example::

    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> store = TileStore(Path(tempfile.mkdtemp()) / "tiles.sqlite3")
    >>> part = {"keys": np.arange(3, dtype=np.int64), "xyz": np.zeros((3, 3), np.float32)}
    >>> part.update({name: np.ones(3, dtype) for name, dtype in SCALAR_FIELDS.items() if name not in part})
    >>> store.put([7], [part], [np.zeros((0, 3), np.float32)], [np.zeros(0, np.float32)], [(0, 0, 0)], [5])
    >>> store.points, store.take([7], dim=None)["keys"].tolist(), store.points
    (3, [0, 1, 2], 0)
    >>> store.destroy()
"""

from __future__ import annotations

import logging
import os
import sqlite3
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapper.map.voxels import KEY_BITS, KEY_OFFSET, pack_indices

log = logging.getLogger("mapper.map.tile_store")

__all__ = [
    "SCALAR_FIELDS",
    "TileInfo",
    "TileStore",
    "centroids_may_match",
    "cone_may_match",
    "key_indices",
    "tile_ids",
    "tile_summary",
]

SCALAR_FIELDS: dict[str, type] = {
    "keys": np.int64,
    "weight": np.float32,
    "feat_norm": np.float32,
    "feat_weight": np.float32,
    "hits": np.int32,
    "last_seen_ns": np.int64,
    "last_seen_kf": np.int64,
    "learned": np.uint8,
}
"""The per-voxel (n,) arrays a tile holds besides ``xyz`` (n, 3) float32 and ``feat`` (n, dim) float16."""

_FIELDS = ("xyz", *SCALAR_FIELDS, "feat")
_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS tiles (tile INTEGER PRIMARY KEY, points INTEGER NOT NULL, "
    "dim INTEGER, " + ", ".join(f"{name} BLOB" for name in _FIELDS) + ")"
)
_MATCH_EPS = 1e-3
"""Margin of :func:`cone_may_match` on cosines: float32 rounding of the query's products is far below it."""


def key_indices(keys: np.ndarray) -> np.ndarray:
    """(n, 3) int64 voxel indices of packed voxel keys (inverse of :func:`mapper.map.voxels.pack_indices`)."""
    keys = np.asarray(keys, np.int64)
    mask = (1 << KEY_BITS) - 1
    packed = np.stack([(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask], axis=1)
    return packed - KEY_OFFSET


def tile_ids(keys: np.ndarray, tile_voxels: int) -> np.ndarray:
    """(n,) int64 packed tile index of each voxel key: tiles are cubes of ``tile_voxels`` voxels."""
    return pack_indices(np.floor_divide(key_indices(keys), tile_voxels))


def tile_summary(unit: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """A tile's feature summary: ``k`` (at most) unit centroids (k, D) float32 of its voxels' unit
    features ``unit`` (m, D) (spherical k-means, farthest-point seeding, deterministic) and per
    centroid the least cosine of its voxels to it (k,) float32: every voxel's feature lies in the cone
    of one centroid, which is what :func:`cone_may_match` needs to skip a tile exactly."""
    unit = np.asarray(unit, np.float32)
    if unit.shape[0] == 0:
        return np.zeros((0, unit.shape[1]), np.float32), np.zeros(0, np.float32)
    sample = unit[:: max(1, unit.shape[0] // 2048)]
    centres = [sample[0]]
    best = sample @ sample[0]
    while len(centres) < k and best.min() < 0.999:
        far = int(np.argmin(best))
        centres.append(sample[far])
        best = np.maximum(best, sample @ sample[far])
    cent = np.stack(centres)
    for _ in range(4):  # spherical Lloyd iterations on the sample
        assign = np.argmax(sample @ cent.T, axis=1)
        for c in range(cent.shape[0]):
            mean = sample[assign == c].sum(axis=0)
            norm = float(np.linalg.norm(mean))
            if norm > 1e-12:
                cent[c] = mean / norm
    cos = unit @ cent.T
    assign = np.argmax(cos, axis=1)
    least = np.ones(cent.shape[0], np.float32)
    np.minimum.at(least, assign, cos[np.arange(unit.shape[0]), assign])
    used = np.bincount(assign, minlength=cent.shape[0]) > 0
    return cent[used].astype(np.float32), least[used]


def cone_may_match(
    centroids: np.ndarray,  # (k, D) float32 unit centroids of a tile (tile_summary)
    least_cos: np.ndarray,  # (k,) float32 the least cosine of a voxel to its centroid
    text_emb: np.ndarray,  # (T, D) float32 the query's texts
    neg_emb: np.ndarray,  # (Q, D) float32 its negatives (a subset of them is safe too)
    min_score: float | None,
) -> bool:
    """Whether a voxel of the tile may be a ``query_points`` match: its best text's cosine beats
    every negative and ``min_score``. Exact in one direction: False only when no voxel can match
    (each voxel's feature lies within angle ``acos(least_cos)`` of its centroid, which bounds its
    cosine to every text from above and to every negative from below)."""
    if centroids.shape[0] == 0:
        return False  # no voxel with a feature
    theta = np.arccos(np.clip(least_cos.astype(np.float64), -1.0, 1.0))[:, None]

    def angles(emb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        norm = np.linalg.norm(np.asarray(emb, np.float64), axis=1)
        cos = centroids.astype(np.float64) @ np.asarray(emb, np.float64).T / np.maximum(norm, 1e-12)
        return np.arccos(np.clip(cos, -1.0, 1.0)), norm

    alpha_t, norm_t = angles(text_emb)
    upper = np.cos(np.maximum(alpha_t - theta, 0.0)) * norm_t  # (k, T) >= any voxel's cosine
    floor = np.full(centroids.shape[0], -np.inf)
    if neg_emb.shape[0]:
        alpha_q, norm_q = angles(neg_emb)
        floor = (np.cos(np.minimum(alpha_q + theta, np.pi)) * norm_q).max(axis=1)  # <= best negative
    may = upper + _MATCH_EPS > floor[:, None]
    if min_score is not None:
        may &= upper + _MATCH_EPS >= min_score
    return bool(may.any())


def centroids_may_match(
    centroids: np.ndarray,  # (k, D) float32 unit centroids of a tile (tile_summary)
    text_emb: np.ndarray,  # (T, D) float32 the query's texts
    neg_emb: np.ndarray,  # (Q, D) float32 its negatives
    min_score: float | None,
) -> bool:
    """Whether a centroid of the tile, scored as a map point, would match (its best text's cosine
    beats every negative and ``min_score``): an approximate test (a match among the voxels around a
    centroid that does not match is missed). False wherever :func:`cone_may_match` is (a centroid
    lies in its own cone)."""
    if centroids.shape[0] == 0:
        return False
    cent = centroids.astype(np.float64)
    best = (cent @ np.asarray(text_emb, np.float64).T).max(axis=1)
    may = np.ones(cent.shape[0], bool)
    if neg_emb.shape[0]:
        may &= best > (cent @ np.asarray(neg_emb, np.float64).T).max(axis=1)
    if min_score is not None:
        may &= best >= min_score
    return bool(may.any())


@dataclass(frozen=True)
class TileInfo:
    """What the store keeps in memory about one paged tile (the rest is on disk)."""

    points: int
    last_seen_kf: int
    """The latest keyframe that observed a voxel of the tile (the paging order)."""
    index: tuple[int, int, int]
    """The tile's integer index (its lowest corner is ``index * tile_m``)."""
    centroids: np.ndarray  # (k, D) float32
    least_cos: np.ndarray  # (k,) float32


class TileStore:
    """The paged tiles of one map (module docstring): an SQLite file created when the first tile is
    written, deleted by :meth:`destroy`. Not thread-safe on its own: the map calls it under its lock."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._db: sqlite3.Connection | None = None
        self.info: dict[int, TileInfo] = {}
        """Tile id -> what is known about it without reading the file."""
        self.points = 0
        """Voxels held in the file."""

    def __len__(self) -> int:
        return len(self.info)

    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            for suffix in ("", "-wal", "-shm"):  # a file left by an earlier process of the same id
                Path(f"{self.path}{suffix}").unlink(missing_ok=True)
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute(_SCHEMA)
        return self._db

    @property
    def disk_bytes(self) -> int:
        """Bytes of the file and its write-ahead log (0 before the first tile)."""
        return sum(os.path.getsize(p) for p in (self.path, Path(f"{self.path}-wal")) if p.exists())

    def put(
        self,
        tiles: Sequence[int],
        parts: Sequence[dict[str, np.ndarray]],  # per tile: the _FIELDS arrays ("feat" optional)
        centroids: Sequence[np.ndarray],
        least_cos: Sequence[np.ndarray],
        index: Sequence[tuple[int, int, int]],
        last_seen_kf: Sequence[int],
    ) -> None:
        """Write tiles (replacing any of the same id) in one transaction."""
        rows: list[tuple[Any, ...]] = []
        counts = []
        for tile, part in zip(tiles, parts, strict=True):
            feat = part.get("feat")
            blobs: list[bytes | None] = [np.ascontiguousarray(part["xyz"], np.float32).tobytes()]
            blobs += [np.ascontiguousarray(part[name], t).tobytes() for name, t in SCALAR_FIELDS.items()]
            blobs.append(None if feat is None else np.ascontiguousarray(feat, np.float16).tobytes())
            dim = None if feat is None else int(feat.shape[1])
            counts.append(int(part["keys"].shape[0]))
            rows.append((int(tile), counts[-1], dim, *blobs))
        db = self._conn()
        marks = ", ".join("?" * (3 + len(_FIELDS)))
        with _transaction(db):
            db.executemany(f"INSERT OR REPLACE INTO tiles VALUES ({marks})", rows)
        for i, tile in enumerate(tiles):
            old = self.info.get(int(tile))
            self.points += counts[i] - (old.points if old is not None else 0)
            x, y, z = (int(v) for v in index[i])
            self.info[int(tile)] = TileInfo(counts[i], int(last_seen_kf[i]), (x, y, z), centroids[i],
                                            least_cos[i])

    def read(self, tiles: Sequence[int], dim: int | None) -> dict[str, np.ndarray]:
        """The voxels of ``tiles`` (those paged), concatenated: ``{field: array}`` with ``feat``
        (n, dim) float16 when ``dim`` (zeros for tiles paged before the map had features)."""
        wanted = [int(t) for t in tiles if int(t) in self.info]
        parts: list[dict[str, np.ndarray]] = []
        if wanted:
            db = self._conn()
            for lo in range(0, len(wanted), 500):  # SQLite's bound on parameters
                chunk = wanted[lo: lo + 500]
                cur = db.execute(f"SELECT points, dim, {', '.join(_FIELDS)} FROM tiles WHERE tile IN "
                                 f"({', '.join('?' * len(chunk))})", chunk)
                parts += [_decoded(row, dim) for row in cur.fetchall()]
        return _concatenated(parts, dim)

    def read_geometry(self, tiles: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """(xyz (n, 3) float32, keys (n,) int64) of the voxels of ``tiles`` (only those columns read)."""
        wanted = [int(t) for t in tiles if int(t) in self.info]
        xyz, keys = [np.zeros((0, 3), np.float32)], [np.zeros(0, np.int64)]
        for lo in range(0, len(wanted), 500):
            chunk = wanted[lo: lo + 500]
            for blob_xyz, blob_keys in self._conn().execute(
                    f"SELECT xyz, keys FROM tiles WHERE tile IN ({', '.join('?' * len(chunk))})", chunk):
                xyz.append(np.frombuffer(blob_xyz, np.float32).reshape(-1, 3))
                keys.append(np.frombuffer(blob_keys, np.int64))
        return np.concatenate(xyz), np.concatenate(keys)

    def keys(self) -> np.ndarray:
        """(n,) int64 voxel keys of every paged voxel (only that column is read)."""
        if not self.info:
            return np.zeros(0, np.int64)
        blobs = self._conn().execute("SELECT keys FROM tiles").fetchall()
        return np.concatenate([np.frombuffer(b[0], np.int64) for b in blobs])

    def take(self, tiles: Sequence[int], dim: int | None) -> dict[str, np.ndarray]:
        """:meth:`read` the tiles and delete them from the file (one transaction)."""
        wanted = [int(t) for t in tiles if int(t) in self.info]
        out = self.read(wanted, dim)
        if wanted:
            db = self._conn()
            with _transaction(db):
                db.executemany("DELETE FROM tiles WHERE tile = ?", [(t,) for t in wanted])
            for tile in wanted:
                self.points -= self.info.pop(tile).points
        return out

    def select(
        self,
        tile_m: float,
        region: tuple[np.ndarray, np.ndarray] | None = None,
        may_match: Callable[[TileInfo], bool] | None = None,
    ) -> list[int]:
        """The paged tiles that intersect ``region`` (a world box, faces included) and for which
        ``may_match`` (e.g. :func:`cone_may_match` on the tile's summary) is true."""
        out = []
        for tile, info in self.info.items():
            if region is not None:
                low = np.asarray(info.index, np.float64) * tile_m
                if np.any(low > region[1]) or np.any(low + tile_m < region[0]):
                    continue
            if may_match is not None and not may_match(info):
                continue
            out.append(tile)
        return out

    def clear(self) -> None:
        """Delete every tile (the file stays)."""
        if self._db is not None and self.info:
            with _transaction(self._db):
                self._db.execute("DELETE FROM tiles")
        self.info.clear()
        self.points = 0

    def destroy(self) -> None:
        """Close and delete the file (a later write creates it again)."""
        if self._db is not None:
            self._db.close()
            self._db = None
        for suffix in ("", "-wal", "-shm"):
            try:
                Path(f"{self.path}{suffix}").unlink(missing_ok=True)
            except OSError as exc:  # a finaliser at exit must not raise
                log.debug("tile store: could not delete %s%s: %s", self.path, suffix, exc)
        self.info.clear()
        self.points = 0


class _transaction:
    """``BEGIN IMMEDIATE`` ... ``COMMIT`` (``ROLLBACK`` on error) on an autocommit connection."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self.db = db

    def __enter__(self) -> None:
        self.db.execute("BEGIN IMMEDIATE")

    def __exit__(self, kind: object, value: object, trace: object) -> None:
        self.db.execute("COMMIT" if kind is None else "ROLLBACK")


def _decoded(row: tuple[Any, ...], dim: int | None) -> dict[str, np.ndarray]:
    """One tile's arrays from its SQLite row ``(points, dim, *_FIELDS)``."""
    n, tile_dim = int(row[0]), row[1]
    blobs: dict[str, Any] = dict(zip(_FIELDS, row[2:], strict=True))
    out: dict[str, np.ndarray] = {"xyz": np.frombuffer(blobs["xyz"], np.float32).reshape(n, 3)}
    for name, dtype in SCALAR_FIELDS.items():
        out[name] = np.frombuffer(blobs[name], dtype)
    if dim is not None:
        if blobs["feat"] is None or tile_dim != dim:
            out["feat"] = np.zeros((n, dim), np.float16)
        else:
            out["feat"] = np.frombuffer(blobs["feat"], np.float16).reshape(n, dim)
    return out


def _concatenated(parts: list[dict[str, np.ndarray]], dim: int | None) -> dict[str, np.ndarray]:
    """The tiles' arrays joined (writable copies); empty arrays of the right shapes for no tile."""
    names = ["xyz", *SCALAR_FIELDS] + (["feat"] if dim is not None else [])
    if not parts:
        empty: dict[str, np.ndarray] = {name: np.zeros(0, dtype) for name, dtype in SCALAR_FIELDS.items()}
        empty["xyz"] = np.zeros((0, 3), np.float32)
        if dim is not None:
            empty["feat"] = np.zeros((0, dim), np.float16)
        return empty
    return {name: np.concatenate([p[name] for p in parts]) for name in names}
