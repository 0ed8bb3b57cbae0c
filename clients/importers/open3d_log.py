"""Open3D reconstruction-system layout with a trajectory log (e.g. ICL-NUIM as Open3D ships it)::

    SEQ/image/00000.jpg ...       colour (the folder may also be color/ or rgb/; .jpg or .png)
    SEQ/depth/00000.png ...       uint16 depth, millimetres (depth_scale 1000), 0 = no measurement
    SEQ/trajectory.log            Open3D log: per frame a line "i j n", then the 4x4 camera-to-world
    SEQ/camera_intrinsic.json     optional: Open3D PinholeCameraIntrinsic (width, height,
                                  intrinsic_matrix: 9 numbers, column-major)

Each block of ``trajectory.log`` is a header line ``i j n`` and four rows of the camera-to-world
matrix (OpenCV optical camera, metres; Open3D writes the inverse of its world-to-camera
``extrinsic``). For a camera trajectory ``i == j`` is the frame number; ``n`` is ignored (Open3D
writes ``i + 1``, Redwood's files the frame count). A header with ``i != j`` is a pairwise
(odometry / pose-graph) log and is refused. Block ``i`` goes with the images numbered ``i``; if
the numbers differ but the counts agree, blocks and images are paired in order, as Open3D's
reconstruction system does, with a warning. Every pose must be a finite rigid transform: a log
holds no markers for lost tracking, so a bad matrix means a damaged or wrong file, and the
import stops before writing anything.

Intrinsics: ``--K`` if given, else ``camera_intrinsic.json`` in the folder, else the import stops
and names both (ICL-NUIM: ``--K 525,525,319.5,239.5``). Capture times are synthesised at ``--fps``.
Open3D's reconstruction system anchors the world at its first camera (pose 0 is the identity),
an OpenCV frame whose -y axis points up for an upright camera, so ``--up-axis`` defaults to
``-y`` (a warning says when pose 0 is not the identity).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from clients.importers.base import (
    DatasetReader,
    ImportedFrame,
    ImporterError,
    ReaderOptions,
    SkippedFrame,
    describe_missing,
    half_pixel_K,
    natural_index,
    pose_problem,
    read_depth_sized,
    read_rgb,
    require_dir,
    require_file,
)

DEPTH_UNITS_PER_M = 1000.0  # Open3D's default depth_scale
TRAJECTORY = "trajectory.log"
INTRINSIC_JSON = "camera_intrinsic.json"
COLOUR_DIRS = ("image", "color", "rgb")
ICL_K = (525.0, 525.0, 319.5, 239.5)  # ICL-NUIM 640x480 (documented, not a silent default)
_NUMBER = re.compile(r"\D*(\d+)")


def load_log(path: Path) -> tuple[list[int], np.ndarray]:
    """Frame numbers (N,) and (N, 4, 4) float64 camera-to-world poses of an Open3D trajectory log.

    Raises :class:`ImporterError` naming the line for a malformed or truncated file, a pairwise
    log (``i != j``), repeated frame numbers or a pose that is not a finite rigid transform.
    """
    require_file(path, f"Open3D trajectory {TRAJECTORY}")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ImporterError(f"Open3D trajectory {str(path)!r} is not a text file") from None
    lines = [(n, line.split()) for n, line in enumerate(text.splitlines(), start=1) if line.strip()]
    if not lines:
        raise ImporterError(f"Open3D trajectory {str(path)!r} is empty")
    ids: list[int] = []
    poses: list[np.ndarray] = []
    first_line: dict[int, int] = {}
    for start in range(0, len(lines), 5):
        line_no, header = lines[start]
        try:
            i, j, n = (int(v) for v in header)
        except ValueError:
            raise ImporterError(
                f"{path}:{line_no}: expected a block header 'i j n' (3 integers) before each 4x4 pose, "
                f"got {' '.join(header)[:60]!r}"
            ) from None
        if i != j:
            raise ImporterError(
                f"{path}:{line_no}: block header '{i} {j} {n}' pairs two frames (i != j): this is a "
                "pairwise odometry / pose-graph log, not a camera trajectory"
            )
        if i in first_line:
            raise ImporterError(f"{path}:{line_no}: frame {i} appears twice (first at line {first_line[i]})")
        block = lines[start + 1 : start + 5]
        if len(block) < 4:
            raise ImporterError(
                f"{path}: truncated: the block of frame {i} (line {line_no}) has {len(block)} "
                "of 4 matrix rows"
            )
        rows = []
        for row_no, fields in block:
            try:
                values = [float(v) for v in fields]
            except ValueError:
                raise ImporterError(
                    f"{path}:{row_no}: not numbers in the pose of frame {i}: {' '.join(fields)[:60]!r}"
                ) from None
            if len(values) != 4:
                raise ImporterError(
                    f"{path}:{row_no}: expected 4 numbers (a row of the 4x4 pose of frame {i}), "
                    f"got {len(values)}"
                )
            rows.append(values)
        pose = np.asarray(rows, dtype=np.float64)
        problem = pose_problem(pose)
        if problem is not None:
            raise ImporterError(
                f"{path}:{line_no}: frame {i}: {problem}; a trajectory log must hold a rigid "
                "camera-to-world matrix for every frame"
            )
        first_line[i] = line_no
        ids.append(i)
        poses.append(pose)
    return ids, np.stack(poses)


def load_intrinsic_json(path: Path) -> tuple[tuple[float, float, float, float], tuple[int, int]]:
    """(fx, fy, cx, cy) and (width, height) from an Open3D ``PinholeCameraIntrinsic`` JSON."""
    what = (
        "an Open3D camera_intrinsic.json ({'width', 'height', 'intrinsic_matrix': 9 numbers, column-major})"
    )
    try:
        data = json.loads(path.read_text())
        width, height = data["width"], data["height"]
        values = [float(v) for v in data["intrinsic_matrix"]]
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise ImporterError(f"{str(path)!r} is not {what}: {exc!r}") from None
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise ImporterError(
            f"{str(path)!r}: width and height must be positive integers, got {width!r}, {height!r}"
        )
    if len(values) != 9 or not all(math.isfinite(v) for v in values):
        raise ImporterError(f"{str(path)!r}: intrinsic_matrix must be 9 finite numbers, got {values}")
    matrix = np.asarray(values).reshape(3, 3).T  # column-major (Eigen) -> row-major
    fx, fy, cx, cy = float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]), float(matrix[1, 2])
    if fx <= 0 or fy <= 0 or not np.allclose(matrix[2], [0.0, 0.0, 1.0]):
        raise ImporterError(
            f"{str(path)!r}: intrinsic_matrix (column-major) must be [fx 0 0, 0 fy 0, cx cy 1] with "
            f"fx, fy > 0, got {values}"
        )
    return (fx, fy, cx, cy), (width, height)


def _numbered(folder: Path, suffixes: tuple[str, ...], what: str) -> dict[int, Path]:
    files: dict[int, Path] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() in suffixes:
            number = natural_index(path.stem, _NUMBER)
            if number is None:
                continue
            if number in files:
                raise ImporterError(
                    f"two {what} files for frame {number}: {files[number].name!r} and {path.name!r}"
                )
            files[number] = path
    return files


class Open3dLogReader(DatasetReader):
    format_name = "open3d"
    description = "Open3D reconstruction layout: image/ depth/ trajectory.log (ICL-NUIM, Redwood)"
    default_up_axis = "-y"  # the world is the first camera's OpenCV frame: y points down

    def __init__(
        self, root: Path | str, options: ReaderOptions | None = None, depth_scale: float = DEPTH_UNITS_PER_M
    ) -> None:
        """``depth_scale``: depth PNG units per metre (Open3D's ``depth_scale``, 1000 = millimetres)."""
        super().__init__(root, options)
        if not (math.isfinite(depth_scale) and depth_scale > 0):
            raise ImporterError(
                f"depth_scale must be a positive number of units per metre, got {depth_scale}"
            )
        self._depth_scale = float(depth_scale)
        colour_dir = next((self.root / d for d in COLOUR_DIRS if (self.root / d).is_dir()), None)
        if colour_dir is None:
            raise ImporterError(
                f"missing Open3D colour folder: none of {', '.join(d + '/' for d in COLOUR_DIRS)} "
                f"exists in {str(self.root)!r}"
            )
        self._colour_dir = colour_dir
        colours = _numbered(colour_dir, (".jpg", ".jpeg", ".png"), "colour")
        if not colours:
            raise ImporterError(
                f"Open3D colour folder {str(colour_dir)!r} holds no numbered .jpg/.png images"
            )
        self._log_path = self.root / TRAJECTORY
        ids, poses = load_log(self._log_path)

        numbers = sorted(colours)
        self._paired_in_order = False
        if set(ids) == set(numbers):
            order = sorted(range(len(ids)), key=lambda k: ids[k])
            self._numbers = numbers
            self._poses = poses[order]
        elif len(ids) == len(numbers):
            self._paired_in_order = True
            self._numbers = numbers
            self._poses = poses
            self._id_range = (min(ids), max(ids))
        else:
            no_pose = sorted(set(numbers) - set(ids))
            no_image = sorted(set(ids) - set(numbers))
            details = []
            if no_image:
                details.append(f"missing colour images for frames {describe_missing(no_image)}")
            if no_pose:
                details.append(f"no pose for colour images {describe_missing(no_pose)}")
            raise ImporterError(
                f"Open3D sequence {str(self.root)!r}: {len(numbers)} colour images in {colour_dir.name}/ "
                f"but {len(ids)} poses in {TRAJECTORY}; " + "; ".join(details)
            )

        self._depths: dict[int, Path] = {}
        if self.options.load_depth:
            depth_dir = require_dir(self.root / "depth", "Open3D depth folder (or use --no-depth)")
            self._depths = _numbered(depth_dir, (".png",), "depth")
            missing = sorted(set(numbers) - set(self._depths))
            if missing:
                raise ImporterError(
                    f"Open3D sequence {str(self.root)!r}: {len(numbers)} colour images but "
                    f"{len(self._depths)} depth/*.png; missing depth for frames {describe_missing(missing)} "
                    "(use --no-depth to import colour only)"
                )

        self._intrinsic_path = self.root / INTRINSIC_JSON
        json_size: tuple[int, int] | None = None
        if self.options.K is not None:
            K_dataset = self.options.K
            self._K_source = "--K"
        elif self._intrinsic_path.is_file():
            K_dataset, json_size = load_intrinsic_json(self._intrinsic_path)
            self._K_source = INTRINSIC_JSON
        else:
            raise ImporterError(
                f"open3d: no intrinsics for {str(self.root)!r}: put an Open3D {INTRINSIC_JSON} "
                "(width, height, intrinsic_matrix column-major) in the folder or pass --K fx,fy,cx,cy "
                "(ICL-NUIM 640x480: --K 525,525,319.5,239.5)"
            )
        self._K_dataset = tuple(float(v) for v in K_dataset)
        self._K = half_pixel_K(*self._K_dataset)
        first = read_rgb(colours[numbers[0]])
        self._size = (first.shape[1], first.shape[0])
        if json_size is not None and json_size != self._size:
            raise ImporterError(
                f"colour images are {self._size[0]}x{self._size[1]} but {str(self._intrinsic_path)!r} is for "
                f"{json_size[0]}x{json_size[1]}; pass --K fx,fy,cx,cy for this image size"
            )
        self._colours = colours
        self._first_is_identity = bool(np.allclose(self._poses[0], np.eye(4), atol=1e-6))

    def __len__(self) -> int:
        return len(self._numbers)

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        number = self._numbers[index]
        colour_path = self._colours[number]
        source = f"{self._colour_dir.name}/{colour_path.name}"
        rgb = read_rgb(colour_path)
        if (rgb.shape[1], rgb.shape[0]) != self._size:
            raise ImporterError(
                f"colour image {str(colour_path)!r} is {rgb.shape[1]}x{rgb.shape[0]}, "
                f"expected {self._size[0]}x{self._size[1]} as the first"
            )
        depth_m = None
        if self.options.load_depth:
            depth_m = read_depth_sized(
                self._depths[number], self._depth_scale, self._size, against=f"colour {source} is"
            )
        return ImportedFrame(
            rgb=rgb,
            depth_m=depth_m,
            K=self._K.copy(),
            world_from_cam=self._poses[index].copy(),
            stamp_ns=self.stamp_from_index(index),
            source=source,
        )

    def meta(self) -> dict[str, Any]:
        return {
            "trajectory": TRAJECTORY,
            "colour_folder": self._colour_dir.name,
            "intrinsics": self._K_source,
            "K_dataset": list(self._K_dataset),
            "depth_scale": self._depth_scale,
            "pairing": "in order" if self._paired_in_order else "by frame number",
        }

    def warnings(self) -> list[str]:
        out = []
        if self._paired_in_order:
            lo, hi = self._id_range
            out.append(
                f"{TRAJECTORY} numbers frames {lo}..{hi} but the colour images are numbered "
                f"{self._numbers[0]}..{self._numbers[-1]}; paired in order, as Open3D does"
            )
        if self.options.up_axis is None and not self._first_is_identity:
            out.append(
                "the first pose is not the identity, so the world may not be the first camera's frame; "
                "--up-axis -y (the default for open3d) may not point up: check, or pass --up-axis"
            )
        return out
