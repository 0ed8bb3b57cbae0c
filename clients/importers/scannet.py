"""ScanNet, in the layout written by ScanNet's ``SensReader`` (``reader.py --export_*``).

::

    SCENE/color/0.jpg ...           colour, 1296x968 in real ScanNet
    SCENE/depth/0.png ...           uint16 millimetres, 640x480
    SCENE/pose/0.txt ...            4x4 camera-to-world (OpenCV optical camera), metres
    SCENE/intrinsic/intrinsic_color.txt   4x4 (fx, fy, cx, cy of the colour camera)
    SCENE/intrinsic/intrinsic_depth.txt   4x4 (of the depth camera; only compared, see below)

Colour and depth differ in size in real ScanNet. The importer resizes colour to the depth size
(``cv2.INTER_AREA``) and scales the colour intrinsics by the same factors, so ``K`` describes the
frame as sent. ScanNet's depth is registered to colour (identity extrinsics), so the scaled colour
``K`` also describes the depth image; ``intrinsic_depth.txt`` is only compared against it and a
warning is printed when they disagree by more than 3%. Poses with -inf/NaN (ScanNet marks
tracking failures so) are skipped and counted. Capture times are synthesised from the frame
number at ``--fps`` (30 Hz, ScanNet's rate).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from clients.importers.base import (
    DatasetReader,
    ImportedFrame,
    ImporterError,
    K_from_matrix,
    ReaderOptions,
    SkippedFrame,
    describe_missing,
    half_pixel_K,
    natural_index,
    pose_problem,
    read_depth_sized,
    read_matrix_txt,
    read_rgb,
    require_dir,
    require_file,
    scale_K,
)

_NUMBER = re.compile(r"(\d+)")
DEPTH_UNITS_PER_M = 1000.0


def _numbered_files(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    files: dict[int, Path] = {}
    for path in folder.iterdir():
        if path.suffix.lower() in suffixes:
            index = natural_index(path.stem, _NUMBER)
            if index is not None:
                files[index] = path
    return files


class ScanNetReader(DatasetReader):
    format_name = "scannet"
    description = "ScanNet SensReader export: color/ depth/ pose/ intrinsic/"

    def __init__(self, root: Path | str, options: ReaderOptions | None = None) -> None:
        super().__init__(root, options)
        color_dir = require_dir(self.root / "color", "ScanNet colour folder")
        pose_dir = require_dir(self.root / "pose", "ScanNet pose folder")
        self._colors = _numbered_files(color_dir, (".jpg", ".jpeg", ".png"))
        self._poses = _numbered_files(pose_dir, (".txt",))
        depth_dir = self.root / "depth"
        self._depths: dict[int, Path] = {}
        if self.options.load_depth or depth_dir.is_dir():
            require_dir(depth_dir, "ScanNet depth folder (use --no-depth to import colour only)")
            self._depths = _numbered_files(depth_dir, (".png",))
        if not self._colors:
            raise ImporterError(f"ScanNet colour folder {str(color_dir)!r} holds no numbered .jpg/.png files")
        self._check_counts()
        self._ids = sorted(self._colors)

        if self.options.K is not None:
            self._K_color_dataset = self.options.K
        else:
            intrinsic = self.root / "intrinsic" / "intrinsic_color.txt"
            require_file(intrinsic, "ScanNet colour intrinsics (or pass --K fx,fy,cx,cy)")
            self._K_color_dataset = K_from_matrix(read_matrix_txt(intrinsic, "colour intrinsics"), intrinsic)

        first = self._ids[0]
        color_h, color_w = read_rgb(self._colors[first]).shape[:2]
        self._color_size = (color_w, color_h)
        if self._depths:
            first_depth = self._depths.get(first, next(iter(self._depths.values())))
            depth = cv2.imread(str(first_depth), cv2.IMREAD_UNCHANGED)
            if depth is None or depth.ndim != 2:
                raise ImporterError(
                    f"unreadable depth image {str(first_depth)!r}: not a decodable 1-channel PNG"
                )
            self._size = (int(depth.shape[1]), int(depth.shape[0]))
        else:
            self._size = self._color_size
        sx, sy = self._size[0] / color_w, self._size[1] / color_h
        self._K = scale_K(half_pixel_K(*self._K_color_dataset), sx, sy)
        self._warnings: list[str] = []
        self._compare_depth_intrinsics()

    def _check_counts(self) -> None:
        colors, poses, depths = set(self._colors), set(self._poses), set(self._depths)
        problems = []
        if poses != colors:
            problems.append(self._mismatch("pose/*.txt", colors, poses))
        if self.options.load_depth and depths != colors:
            problems.append(self._mismatch("depth/*.png", colors, depths))
        if problems:
            raise ImporterError(
                f"ScanNet folder {str(self.root)!r}: {len(colors)} colour images but "
                + "; ".join(problems)
                + " (every frame needs a colour image, a depth image and a pose)"
            )

    @staticmethod
    def _mismatch(name: str, colors: set[int], other: set[int]) -> str:
        parts = [f"{len(other)} {name}"]
        if colors - other:
            parts.append(f"missing for frames {describe_missing(sorted(colors - other))}")
        if other - colors:
            parts.append(f"extra for frames {describe_missing(sorted(other - colors))}")
        return ", ".join(parts)

    def _compare_depth_intrinsics(self) -> None:
        path = self.root / "intrinsic" / "intrinsic_depth.txt"
        if self.options.K is not None or not self._depths or not path.is_file():
            return
        K_depth = half_pixel_K(*K_from_matrix(read_matrix_txt(path, "depth intrinsics"), path))
        rel = np.abs(K_depth - self._K) / np.maximum(np.abs(K_depth), 1.0)
        if float(rel.max()) > 0.03:
            self._warnings.append(
                f"scaled colour K {np.round(self._K, 2).tolist()} differs from intrinsic_depth.txt "
                f"{np.round(K_depth, 2).tolist()} by {100 * float(rel.max()):.1f}%; the colour K is used"
            )

    def __len__(self) -> int:
        return len(self._ids)

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        frame_id = self._ids[index]
        source = f"frame {frame_id}"
        world_from_cam = read_matrix_txt(self._poses[frame_id], "ScanNet pose")
        problem = pose_problem(world_from_cam)
        if problem is not None:
            return SkippedFrame(source, problem)
        rgb = read_rgb(self._colors[frame_id])
        if (rgb.shape[1], rgb.shape[0]) != self._color_size:
            raise ImporterError(
                f"colour image {str(self._colors[frame_id])!r} is {rgb.shape[1]}x{rgb.shape[0]}, "
                f"the first one is {self._color_size[0]}x{self._color_size[1]}"
            )
        if self._color_size != self._size:
            rgb = cv2.resize(rgb, self._size, interpolation=cv2.INTER_AREA)
        depth_m = None
        if self.options.load_depth:
            depth_m = read_depth_sized(
                self._depths[frame_id], DEPTH_UNITS_PER_M, self._size, against="the first one is"
            )
        return ImportedFrame(
            rgb=rgb,
            depth_m=depth_m,
            K=self._K.copy(),
            world_from_cam=world_from_cam,
            stamp_ns=self.stamp_from_index(frame_id),
            source=source,
        )

    def meta(self) -> dict[str, Any]:
        return {
            "color_size": list(self._color_size),
            "size": list(self._size),
            "K_color_dataset": list(self._K_color_dataset),
        }

    def warnings(self) -> list[str]:
        return list(self._warnings)
