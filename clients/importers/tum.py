"""TUM RGB-D benchmark sequences (``rgbd_dataset_freiburgN_*``)::

    SEQ/rgb.txt            "timestamp filename" per line, '#' comments
    SEQ/depth.txt          same; depth PNGs are uint16, metres * 5000, 0 = no measurement
    SEQ/groundtruth.txt    "timestamp tx ty tz qx qy qz qw" (motion capture, ~100 Hz)
    SEQ/rgb/*.png, SEQ/depth/*.png

Each colour image is associated with the depth image and the ground-truth pose nearest in time,
each within ``max_dt_s`` (0.02 s, as TUM's ``associate.py``); colour images without a partner
are skipped and counted. The pose gives the optical centre of the colour camera in the motion
capture world, i.e. camera-to-world with an OpenCV optical camera (the TUM tools project depth
with it unchanged). The frame's capture time is the colour image's timestamp.

Intrinsics default to TUM's published calibration of the colour camera, chosen from the folder
name (``freiburg1``/``fr1`` etc.); ``--K`` overrides, and is required for other names. With the
default intrinsics, fr1 and fr2 images are undistorted with TUM's published coefficients (same K;
colour bilinear, depth edge-aware, see :func:`~clients.importers.base.remap_depth`); fr3 images are
undistorted already. With ``--K`` images are used as they are (a warning says so for fr1/fr2).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from clients.importers.base import (
    NS_PER_S,
    DatasetReader,
    ImportedFrame,
    ImporterError,
    ReaderOptions,
    SkippedFrame,
    half_pixel_K,
    pose_problem,
    read_depth_sized,
    read_rgb,
    remap_depth,
    remap_rgb,
    require_file,
    undistort_maps,
)

DEPTH_UNITS_PER_M = 5000.0
MAX_DT_S = 0.02
# https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats (colour camera calibration)
FREIBURG_K: dict[str, tuple[float, float, float, float]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
}
# OpenCV (k1, k2, p1, p2, k3) of the colour cameras, same source; fr3 images are undistorted already
FREIBURG_DISTORTION: dict[str, tuple[float, float, float, float, float]] = {
    "fr1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "fr2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "fr3": (0.0, 0.0, 0.0, 0.0, 0.0),
}
_FREIBURG = re.compile(r"(?:freiburg|fr)([123])(?![0-9])")


def parse_stamp_ns(text: str) -> int:
    """'1305031102.175304' -> nanoseconds, exactly (no float rounding)."""
    whole, _, frac = text.partition(".")
    if not whole.lstrip("-").isdigit() or (frac and not frac.isdigit()):
        raise ValueError(f"not a timestamp: {text!r}")
    return int(whole) * NS_PER_S + int((frac + "000000000")[:9])


def read_list(path: Path, n_values: int, what: str) -> tuple[np.ndarray, list[list[str]]]:
    """Rows of a TUM list file: (N,) int64 stamps in ns (sorted) and the other fields per row."""
    require_file(path, what)
    stamps: list[int] = []
    rows: list[list[str]] = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 1 + n_values:
            raise ImporterError(
                f"{path}:{line_no}: expected a timestamp and {n_values} value(s), got {len(parts)} fields"
            )
        try:
            stamps.append(parse_stamp_ns(parts[0]))
        except ValueError as exc:
            raise ImporterError(f"{path}:{line_no}: {exc}") from None
        rows.append(parts[1:])
    if not rows:
        raise ImporterError(f"{what} {str(path)!r} lists nothing")
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    return np.asarray(stamps, dtype=np.int64)[order], [rows[i] for i in order]


def nearest(sorted_stamps: np.ndarray, query: np.ndarray, max_dt_ns: int) -> np.ndarray:
    """(M,) index into ``sorted_stamps`` (N,) of the nearest stamp to each query, -1 if farther
    than ``max_dt_ns``."""
    right = np.clip(np.searchsorted(sorted_stamps, query), 0, len(sorted_stamps) - 1)
    left = np.clip(right - 1, 0, len(sorted_stamps) - 1)
    pick = np.where(np.abs(sorted_stamps[left] - query) <= np.abs(sorted_stamps[right] - query), left, right)
    return np.where(np.abs(sorted_stamps[pick] - query) <= max_dt_ns, pick, -1)


def pose_from_tum(values: list[str]) -> np.ndarray:
    """'tx ty tz qx qy qz qw' -> (4, 4) float64 world_from_cam (quaternion normalised)."""
    t = np.array([float(v) for v in values[:3]])
    q = np.array([float(v) for v in values[3:7]])
    world_from_cam = np.full((4, 4), np.nan)
    norm = float(np.linalg.norm(q))
    if np.all(np.isfinite(t)) and np.isfinite(norm) and norm > 1e-9:
        world_from_cam = np.eye(4)
        world_from_cam[:3, :3] = Rotation.from_quat(q / norm).as_matrix()  # scalar-last (x, y, z, w)
        world_from_cam[:3, 3] = t
    return world_from_cam


class TumReader(DatasetReader):
    format_name = "tum"
    description = "TUM RGB-D sequence: rgb.txt depth.txt groundtruth.txt"

    def __init__(
        self,
        root: Path | str,
        options: ReaderOptions | None = None,
        max_dt_s: float = MAX_DT_S,
        distortion: Sequence[float] | None = None,
    ) -> None:
        """``distortion``: OpenCV (k1, k2, p1, p2[, k3]) to undo; None = the published coefficients
        of the Freiburg camera when its default intrinsics are used, none with ``--K``."""
        super().__init__(root, options)
        rgb_stamps, rgb_rows = read_list(self.root / "rgb.txt", 1, "TUM colour list rgb.txt")
        gt_stamps, gt_rows = read_list(self.root / "groundtruth.txt", 7, "TUM ground truth groundtruth.txt")
        if not 0 < max_dt_s < 1:
            raise ImporterError(f"max_dt_s must be in (0, 1) s, got {max_dt_s}")
        self._max_dt_s = max_dt_s
        max_dt_ns = int(round(max_dt_s * NS_PER_S))
        self._rgb_stamps = rgb_stamps
        self._rgb_paths = [self.root / row[0] for row in rgb_rows]
        self._pose_index = nearest(gt_stamps, rgb_stamps, max_dt_ns)
        self._gt_rows = gt_rows
        self._depth_paths: list[Path] = []
        self._depth_index = np.zeros(len(rgb_stamps), dtype=np.int64)
        if self.options.load_depth:
            depth_stamps, depth_rows = read_list(self.root / "depth.txt", 1, "TUM depth list depth.txt")
            self._depth_paths = [self.root / row[0] for row in depth_rows]
            self._depth_index = nearest(depth_stamps, rgb_stamps, max_dt_ns)

        self._sequence = self._camera_name()
        if self.options.K is not None:
            K_dataset = self.options.K
        elif self._sequence is not None:
            K_dataset = FREIBURG_K[self._sequence]
        else:
            raise ImporterError(
                "cannot tell the TUM camera (fr1, fr2, fr3) from the folder name "
                f"{self.root.resolve().name!r}; pass --K fx,fy,cx,cy"
            )
        self._K_dataset = tuple(float(v) for v in K_dataset)
        self._K = half_pixel_K(*K_dataset)
        if distortion is None:
            published = self._sequence is not None and self.options.K is None
            distortion = FREIBURG_DISTORTION[self._sequence] if self._sequence and published else (0.0,) * 5
        if len(distortion) not in (4, 5) or not all(np.isfinite(distortion)):
            raise ImporterError(
                f"distortion must be 4 or 5 finite numbers (k1, k2, p1, p2[, k3]), got {distortion}"
            )
        self._distortion = tuple(float(v) for v in distortion)
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        self._maps_size: tuple[int, int] | None = None

    def _camera_name(self) -> str | None:
        match = _FREIBURG.search(self.root.resolve().name.lower())
        return f"fr{match.group(1)}" if match else None

    def __len__(self) -> int:
        return len(self._rgb_paths)

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        source = self._rgb_paths[index].name
        pose_index = int(self._pose_index[index])
        if pose_index < 0:
            return SkippedFrame(source, f"no ground-truth pose within {self._max_dt_s} s")
        depth_index = int(self._depth_index[index])
        if self.options.load_depth and depth_index < 0:
            return SkippedFrame(source, f"no depth image within {self._max_dt_s} s")
        world_from_cam = pose_from_tum(self._gt_rows[pose_index])
        problem = pose_problem(world_from_cam)
        if problem is not None:
            return SkippedFrame(source, problem)
        rgb = read_rgb(self._rgb_paths[index])
        depth_m = None
        if self.options.load_depth:
            depth_path = self._depth_paths[depth_index]
            depth_m = read_depth_sized(
                depth_path, DEPTH_UNITS_PER_M, (rgb.shape[1], rgb.shape[0]), against=f"colour {source} is"
            )
        if any(self._distortion):
            maps = self._undistort_maps(rgb.shape[1], rgb.shape[0])
            rgb = remap_rgb(rgb, maps)
            depth_m = remap_depth(depth_m, maps) if depth_m is not None else None
        return ImportedFrame(
            rgb=rgb,
            depth_m=depth_m,
            K=self._K.copy(),
            world_from_cam=world_from_cam,
            stamp_ns=int(self._rgb_stamps[index]),
            source=source,
        )

    def _undistort_maps(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        if self._maps is None or self._maps_size != (width, height):
            self._maps = undistort_maps(self._K_dataset, self._distortion, width, height)
            self._maps_size = (width, height)
        return self._maps

    def meta(self) -> dict[str, Any]:
        return {
            "camera": self._sequence or "custom",
            "K_dataset": list(self._K_dataset),
            "distortion_removed": list(self._distortion),
            "max_dt_s": self._max_dt_s,
        }

    def warnings(self) -> list[str]:
        if self._sequence in ("fr1", "fr2") and not any(self._distortion):
            return [
                f"{self._sequence} images are imported without undistortion (--K given): rays near the "
                "corners are off by up to 37 pixels at 640x480"
            ]
        return []
