"""Common ground for the dataset importers: the frame record, the reader interface, small helpers.

Every reader turns one dataset layout into a stream of :class:`ImportedFrame` records in the
project's conventions (see ``docs/how-to/import.md``):

- camera frame OpenCV optical (+x right, +y down, +z forward), poses ``world_from_cam``
  (camera-to-world, metres), world frame as the dataset defines it (not re-aligned);
- ``K = [fx, fy, cx, cy]`` for the image as imported, with pixel (col i, row j) centred at
  (i + 0.5, j + 0.5). Datasets publish intrinsics in the OpenCV convention where pixel centres
  sit at integers; :func:`half_pixel_K` converts them (cx, cy + 0.5);
- depth in metres as float32, 0 where the sensor has no measurement.
"""

from __future__ import annotations

import math
import re
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

NS_PER_S = 1_000_000_000


class ImporterError(ValueError):
    """A dataset folder cannot be imported as asked (missing file, bad layout, bad option).

    The message says what was wrong, with the value received and what was expected.
    """


@dataclass(frozen=True)
class ImportedFrame:
    """One posed RGB(-D) frame in project conventions, ready to become a protocol ``Frame``."""

    rgb: np.ndarray
    """(H, W, 3) uint8, R,G,B."""
    depth_m: np.ndarray | None
    """(H, W) float32 metres, same size as ``rgb``; 0 = no measurement. None when not imported."""
    K: np.ndarray
    """(4,) float64 [fx, fy, cx, cy] in pixels for ``rgb`` as stored here, half-pixel centres."""
    world_from_cam: np.ndarray
    """(4, 4) float64 camera-to-world, OpenCV optical camera frame, metres, in the dataset's world
    frame (``convert`` applies :attr:`DatasetReader.world_from_dataset` when writing)."""
    stamp_ns: int
    """Capture time in nanoseconds (synthesised from the frame index where the dataset has none)."""
    source: str
    """Where the frame came from (file or index), for messages."""
    ov: np.ndarray | None = None
    """(h, w, d) float16/float32 precomputed open-vocabulary features (only ``sim`` carries them)."""
    ov_space: str | None = None
    """Embedding space of ``ov``."""


@dataclass(frozen=True)
class SkippedFrame:
    """A source frame that is left out, with a short reason used as a summary key."""

    source: str
    reason: str


@dataclass
class ReaderOptions:
    """Options shared by all readers (the CLI fills them from its flags)."""

    K: tuple[float, float, float, float] | None = None
    """Intrinsics override [fx, fy, cx, cy] in the dataset's own convention (pixel centres at
    integers, as printed in dataset papers and config files); None = the reader's default."""
    load_depth: bool = True
    """Read depth images (False: frames carry no depth and depth files are not opened)."""
    fps: float = 30.0
    """Frame rate used to synthesise ``stamp_ns`` for datasets without timestamps."""
    up_axis: str | None = None
    """Which axis of the dataset's world frame points up (one of :data:`UP_AXES`); the import
    rotates the world so that it becomes +z. None = the reader's default."""


# dataset world axis pointing up -> rotation (3, 3) taking it to +z (a proper rotation)
UP_AXES: dict[str, tuple[tuple[float, ...], ...]] = {
    "z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-z": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "y": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "-y": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "x": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    "-x": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),
}


def world_from_dataset(up_axis: str) -> np.ndarray:
    """(4, 4) float64 rotation taking the dataset world's ``up_axis`` to +z."""
    if up_axis not in UP_AXES:
        raise ImporterError(f"--up-axis must be one of {', '.join(UP_AXES)}, got {up_axis!r}")
    matrix = np.eye(4)
    matrix[:3, :3] = np.asarray(UP_AXES[up_axis], dtype=np.float64)
    return matrix


class DatasetReader(ABC):
    """A dataset folder opened for import.

    Construction validates the layout (folders, counts, intrinsics) and raises
    :class:`ImporterError` on anything wrong, before a single frame is written. Frames are then
    decoded one at a time by :meth:`iter_frames`.
    """

    format_name: ClassVar[str]
    """Name used on the command line (``govnesf import <format_name> ...``)."""
    description: ClassVar[str]
    """One line for ``--help``."""
    default_up_axis: ClassVar[str] = "z"
    """Axis of the dataset's world frame that points up (rotated to +z on import)."""

    def __init__(self, root: Path | str, options: ReaderOptions | None = None) -> None:
        self.root = Path(root)
        self.options = options or ReaderOptions()
        if not self.root.exists():
            raise ImporterError(f"{self.format_name}: dataset path {str(self.root)!r} does not exist")
        if self.options.fps <= 0 or not math.isfinite(self.options.fps):
            raise ImporterError(f"fps must be a positive number, got {self.options.fps}")
        self.up_axis = self.options.up_axis or self.default_up_axis
        self.world_from_dataset = world_from_dataset(self.up_axis)
        """(4, 4) rotation applied to every pose on import (identity for up_axis "z")."""

    @abstractmethod
    def __len__(self) -> int:
        """Number of source frames (before stride, including frames that will be skipped)."""

    @abstractmethod
    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        """Decode source frame ``index`` (0 <= index < len(self))."""

    def iter_frames(self, indices: Iterable[int]) -> Iterator[ImportedFrame | SkippedFrame]:
        """Decode the given source frames in order (readers over streams override this)."""
        for index in indices:
            yield self.read(index)

    def meta(self) -> dict[str, Any]:
        """Facts about the source to store in the recording's ``meta`` (JSON-like values only)."""
        return {}

    def warnings(self) -> list[str]:
        """Things the user should know about this import (printed with the summary)."""
        return []

    def stamp_from_index(self, index: int) -> int:
        """Synthesised capture time for datasets without timestamps: index / fps."""
        return int(round(index * NS_PER_S / self.options.fps))


@dataclass
class ImportSummary:
    """What an import did."""

    out_path: Path
    format_name: str
    frames_written: int = 0
    frames_considered: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    width: int = 0
    height: int = 0
    warnings: list[str] = field(default_factory=list)

    def format(self) -> str:
        lines = [
            f"import {self.format_name}: wrote {self.frames_written} frames "
            f"({self.width}x{self.height}) to {self.out_path}",
            f"  considered {self.frames_considered} source frames after stride",
        ]
        if self.skipped:
            lines.append(f"  skipped {sum(self.skipped.values())}:")
            for reason, count in sorted(self.skipped.items(), key=lambda kv: -kv[1]):
                lines.append(f"    {count:>6}  {reason}")
        else:
            lines.append("  skipped 0")
        lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Intrinsics


def parse_K(text: str) -> tuple[float, float, float, float]:
    """Parse ``"fx,fy,cx,cy"`` (commas or spaces) into four positive finite floats."""
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    if len(parts) != 4:
        raise ImporterError(f"--K wants 4 numbers fx,fy,cx,cy, got {len(parts)} in {text!r}")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise ImporterError(f"--K wants 4 numbers fx,fy,cx,cy, got {text!r}") from None
    fx, fy, cx, cy = values
    if not all(math.isfinite(v) for v in values) or fx <= 0 or fy <= 0:
        raise ImporterError(f"--K needs finite values with fx, fy > 0, got {text!r}")
    return fx, fy, cx, cy


def half_pixel_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(4,) float64: dataset intrinsics (pixel centres at integers) in the project's convention
    (pixel centres at integer + 0.5): the principal point moves by half a pixel."""
    return np.array([fx, fy, cx + 0.5, cy + 0.5], dtype=np.float64)


def scale_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """(4,) -> (4,): intrinsics (half-pixel convention) of the image resized by (sx, sy).

    With pixel centres at integer + 0.5 a resize maps continuous coordinates u -> sx * u exactly,
    so every entry scales (no -0.5 correction as in the integer-centre convention).
    """
    return np.array([K[0] * sx, K[1] * sy, K[2] * sx, K[3] * sy], dtype=np.float64)


def K_from_matrix(matrix: np.ndarray, path: Path) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy from a 3x3 or 4x4 intrinsic matrix read from ``path``."""
    if matrix.shape not in ((3, 3), (4, 4)) or not np.all(np.isfinite(matrix[:3, :3])):
        raise ImporterError(
            f"{path}: expected a finite 3x3 or 4x4 intrinsic matrix, got shape {matrix.shape}"
        )
    fx, fy, cx, cy = float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]), float(matrix[1, 2])
    if fx <= 0 or fy <= 0:
        raise ImporterError(f"{path}: focal lengths must be > 0, got fx={fx} fy={fy}")
    return fx, fy, cx, cy


# ---------------------------------------------------------------------------------------------
# Files


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise ImporterError(f"missing {what}: folder {str(path)!r} does not exist")
    return path


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise ImporterError(f"missing {what}: file {str(path)!r} does not exist")
    return path


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 R,G,B from a JPEG/PNG file; ImporterError if missing or undecodable."""
    require_file(path, "colour image")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ImporterError(f"unreadable colour image {str(path)!r}: not a decodable JPEG/PNG")
    return np.ascontiguousarray(image[:, :, ::-1])


def read_depth_png(path: Path, units_per_m: float, invalid_value: int | None = None) -> np.ndarray:
    """(H, W) float32 metres from a 16-bit PNG storing depth * units_per_m; 0 (and
    ``invalid_value``) become 0 = no measurement."""
    require_file(path, "depth image")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImporterError(f"unreadable depth image {str(path)!r}: not a decodable PNG")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ImporterError(
            f"depth image {str(path)!r} must be single-channel uint16, got {raw.dtype} shape {raw.shape}"
        )
    depth_m = raw.astype(np.float32) / np.float32(units_per_m)
    if invalid_value is not None:
        depth_m[raw == invalid_value] = 0.0
    return depth_m


def read_depth_sized(
    path: Path,
    units_per_m: float,
    size_wh: tuple[int, int],
    *,
    against: str,
    invalid_value: int | None = None,
) -> np.ndarray:
    """:func:`read_depth_png`, then check the depth is ``size_wh`` (W, H): (H, W) float32 metres.

    ``against`` names what the size must match in the error, e.g. ``"colour is"``.
    """
    depth_m = read_depth_png(path, units_per_m, invalid_value=invalid_value)
    if (depth_m.shape[1], depth_m.shape[0]) != tuple(size_wh):
        raise ImporterError(
            f"depth image {str(path)!r} is {depth_m.shape[1]}x{depth_m.shape[0]}, "
            f"{against} {size_wh[0]}x{size_wh[1]}"
        )
    return depth_m


def read_matrix_txt(path: Path, what: str) -> np.ndarray:
    """A whitespace-separated numeric matrix (e.g. a 4x4 pose) as float64; 'inf'/'nan' allowed."""
    require_file(path, what)
    try:
        matrix = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise ImporterError(f"{what} {str(path)!r} is not a numeric matrix: {exc}") from None
    return matrix


def pose_problem(world_from_cam: np.ndarray) -> str | None:
    """None if ``world_from_cam`` (4, 4) is a finite rigid transform, else a short reason."""
    if world_from_cam.shape != (4, 4):
        return f"pose has shape {world_from_cam.shape}, expected (4, 4)"
    if not np.all(np.isfinite(world_from_cam)):
        return "invalid pose (non-finite values)"
    if not np.allclose(world_from_cam[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return "invalid pose (last row is not 0 0 0 1)"
    rot = world_from_cam[:3, :3]
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-3) or np.linalg.det(rot) < 0:
        return "invalid pose (rotation not orthonormal)"
    return None


def natural_index(stem: str, pattern: re.Pattern[str]) -> int | None:
    """The integer captured by ``pattern`` (group 1) in ``stem``, or None if it does not match."""
    match = pattern.fullmatch(stem)
    return int(match.group(1)) if match else None


def describe_missing(ids: Sequence[int], limit: int = 5) -> str:
    shown = ", ".join(str(i) for i in list(ids)[:limit])
    more = f" and {len(ids) - limit} more" if len(ids) > limit else ""
    return f"{shown}{more}"


# ---------------------------------------------------------------------------------------------
# Undistortion


def undistort_maps(
    K_dataset: Sequence[float], distortion: Sequence[float], width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 source x and y (pixel centres at integers) for each pixel of the
    undistorted image, which keeps the same intrinsics ``K_dataset`` (OpenCV convention).

    ``distortion`` is OpenCV's (k1, k2, p1, p2[, k3]).
    """
    fx, fy, cx, cy = K_dataset
    camera = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    map_x, map_y = cv2.initUndistortRectifyMap(
        camera, np.asarray(distortion, dtype=np.float64), None, camera, (width, height), cv2.CV_32FC1
    )
    return map_x, map_y


def remap_rgb(rgb: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(H, W, 3) uint8 resampled bilinearly at ``maps``; outside the source image becomes black."""
    height, width = rgb.shape[:2]
    map_x, map_y = maps
    out = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    inside = (map_x > -0.5) & (map_x < width - 0.5) & (map_y > -0.5) & (map_y < height - 0.5)
    out[~inside] = 0
    return out


def remap_depth(
    depth_m: np.ndarray, maps: tuple[np.ndarray, np.ndarray], max_ratio: float = 1.05
) -> np.ndarray:
    """(H, W) float32 depth resampled at ``maps`` without mixing surfaces: bilinear where the four
    source neighbours are all valid and within ``max_ratio`` of each other, else the nearest
    source pixel; 0 (unknown) outside the hull of the source pixel centres (no extrapolation)."""
    height, width = depth_m.shape
    map_x, map_y = maps
    x0 = np.floor(map_x).astype(np.int64)
    y0 = np.floor(map_y).astype(np.int64)
    fx = (map_x - x0).astype(np.float32)
    fy = (map_y - y0).astype(np.float32)
    inside = (map_x >= 0) & (map_x <= width - 1) & (map_y >= 0) & (map_y <= height - 1)
    xa, xb = np.clip(x0, 0, width - 1), np.clip(x0 + 1, 0, width - 1)
    ya, yb = np.clip(y0, 0, height - 1), np.clip(y0 + 1, 0, height - 1)
    d00, d01, d10, d11 = depth_m[ya, xa], depth_m[ya, xb], depth_m[yb, xa], depth_m[yb, xb]
    low = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    high = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    smooth = (low > 0) & (high <= low * max_ratio)
    bilinear = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
    xn = np.clip(np.rint(map_x).astype(np.int64), 0, width - 1)
    yn = np.clip(np.rint(map_y).astype(np.int64), 0, height - 1)
    out = np.where(smooth, bilinear, depth_m[yn, xn])
    return np.where(inside, out, 0.0).astype(np.float32)
