"""Point clouds as binary PLY files (numpy only; no Open3D needed to write them).

``govnesf query --out F.ply`` writes the matching points with :func:`write_points_ply`::

    ply
    format binary_little_endian 1.0
    comment govnesf query points: score = cosine similarity of the point's feature to the query
    element vertex N
    property float x
    property float y
    property float z
    property float score
    property uchar red
    property uchar green
    property uchar blue
    end_header
    N records of 3 x float32, float32, 3 x uint8 (19 bytes each, little-endian)

``x, y, z`` are world coordinates in metres (float32), ``score`` the point's score as the node
returned it (float32), and the colour is viridis over the scores' min..max range (dark = low,
yellow = high; :func:`clients.colors.score_colours`). Open3D's tensor I/O reads the score as a
point attribute (``o3d.t.io.read_point_cloud(path).point.score``, shape (N, 1) float32), its
legacy reader the points and colours; any PLY reader (numpy, trimesh, CloudCompare, MeshLab)
reads the same header.

An empty answer (N = 0) is written as a valid PLY with ``element vertex 0`` and the same
properties, so scripts that always read the file work; readers then return no points.

>>> import tempfile, pathlib
>>> p = write_points_ply(pathlib.Path(tempfile.mkdtemp()) / "a.ply", np.zeros((2, 3)), np.array([0.1, 0.9]))
>>> read_points_ply(p)["score"].tolist() == [np.float32(0.1), np.float32(0.9)]
True
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from clients.colors import score_colours

__all__ = ["PLY_VERTEX_DTYPE", "PlyError", "read_points_ply", "write_points_ply"]

PLY_VERTEX_DTYPE = np.dtype(
    [
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("score", "<f4"),
        ("red", "u1"), ("green", "u1"), ("blue", "u1"),
    ]
)  # fmt: skip
"""One vertex record as written (19 bytes, packed, little-endian)."""

_PLY_TYPES = {"<f4": "float", "u1": "uchar"}


class PlyError(ValueError):
    """Points that cannot be written (bad shapes, non-finite values), or a file that is not our PLY."""


def _header(n: int, comment: str) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {line}" for line in comment.splitlines() if line.strip()]
    lines.append(f"element vertex {n}")
    for name in PLY_VERTEX_DTYPE.names or ():
        lines.append(f"property {_PLY_TYPES[PLY_VERTEX_DTYPE[name].str.replace('|', '')]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_points_ply(
    path: str | Path,
    xyz: np.ndarray,
    score: np.ndarray,
    colours: np.ndarray | None = None,
    comment: str = "govnesf query points: score = cosine similarity of the point's feature to the query",
) -> Path:
    """Write points (N, 3) with scores (N,) as a binary PLY (float32 xyz, float32 ``score``,
    uchar RGB); returns the path.

    ``colours`` (N, 3) float in [0, 1] defaults to viridis over the scores. N = 0 writes a valid
    empty PLY. The file is written to ``path + ".partial"`` and renamed, so a failure leaves no
    half-written file; the parent folder is created.

    Raises:
        PlyError: shapes that disagree, or non-finite coordinates / scores (named, with counts).
        OSError: the folder or file cannot be written (the message names the path).
    """
    xyz = np.asarray(xyz)
    score = np.asarray(score)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise PlyError(f"xyz must be (N, 3), got shape {xyz.shape}")
    n = xyz.shape[0]
    if score.shape != (n,):
        raise PlyError(f"score must be ({n},) to match xyz, got shape {score.shape}")
    for name, arr in (("xyz", xyz), ("score", score)):
        bad = int(np.count_nonzero(~np.isfinite(arr.astype(np.float64))))
        if bad:
            raise PlyError(f"{name} has {bad} non-finite value(s); a PLY point cloud needs finite numbers")
    if colours is None:
        colours = score_colours(score)
    colours = np.asarray(colours, np.float64)
    if colours.shape != (n, 3):
        raise PlyError(f"colours must be ({n}, 3), got shape {colours.shape}")
    vertices = np.empty(n, PLY_VERTEX_DTYPE)
    vertices["x"], vertices["y"], vertices["z"] = (xyz[:, i].astype(np.float32) for i in range(3))
    vertices["score"] = score.astype(np.float32)
    rgb = np.clip(np.rint(colours * 255.0), 0, 255).astype(np.uint8)
    vertices["red"], vertices["green"], vertices["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    try:
        with open(partial, "wb") as f:
            f.write(_header(n, comment))
            f.write(vertices.tobytes())
        os.replace(partial, path)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise OSError(f"cannot write PLY {str(path)!r}: {exc.strerror or exc}") from exc
    return path


def read_points_ply(path: str | Path) -> np.ndarray:
    """(N,) records of :data:`PLY_VERTEX_DTYPE` from a file :func:`write_points_ply` wrote.

    Raises:
        PlyError: not a PLY of exactly this layout, or cut short.
    """
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise PlyError(f"{str(path)!r} is not a PLY file (no 'ply' / 'end_header')")
    header = data[: end + len(b"end_header\n")]
    lines = [line for line in header.decode("ascii").splitlines() if not line.startswith("comment ")]
    try:
        n = int(next(line for line in lines if line.startswith("element vertex ")).split()[2])
    except (StopIteration, ValueError, IndexError):
        raise PlyError(f"{str(path)!r}: no valid 'element vertex N' line") from None
    expected = [line for line in _header(n, "").decode("ascii").splitlines()]
    if lines != expected:
        raise PlyError(f"{str(path)!r}: header differs from govnesf's point layout: {lines}")
    body = data[len(header) :]
    if len(body) != n * PLY_VERTEX_DTYPE.itemsize:
        raise PlyError(
            f"{str(path)!r}: {len(body)} data bytes, expected {n} x {PLY_VERTEX_DTYPE.itemsize}"
        )
    return np.frombuffer(body, PLY_VERTEX_DTYPE, count=n)
