"""Replica, as released with NICE-SLAM (the ``results/`` layout, also used by many later SLAM
papers)::

    Replica/cam_params.json           {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
    Replica/room0/traj.txt            one line per frame: 16 numbers, row-major 4x4 camera-to-world
    Replica/room0/results/frame000000.jpg   colour, 1200x680
    Replica/room0/results/depth000000.png   uint16, metres * scale (6553.5)

PATH is the scene folder (``Replica/room0``). ``cam_params.json`` is looked for in the scene
folder, then its parent; without it the NICE-SLAM defaults apply (1200x680, fx = fy = 600,
cx = 599.5, cy = 339.5, depth scale 6553.5); ``--K`` overrides the intrinsics. Poses are
camera-to-world with an OpenCV optical camera (NICE-SLAM flips y and z on load to get its
OpenGL-style camera, so the file itself is OpenCV). Frame i uses line i of ``traj.txt``.
Capture times are synthesised at ``--fps``.

The Semantic-NeRF renders of Replica (``rgb/rgb_N.png``, ``depth/depth_N.png``,
``traj_w_c.txt``) are a different layout and are not read by this importer.
"""

from __future__ import annotations

import json
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

# NICE-SLAM configs/Replica/replica.yaml
DEFAULT_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}
_FRAME = re.compile(r"frame(\d+)")
_DEPTH = re.compile(r"depth(\d+)")


def _numbered(folder: Path, pattern: re.Pattern[str], suffixes: tuple[str, ...]) -> dict[int, Path]:
    files: dict[int, Path] = {}
    for path in folder.iterdir():
        if path.suffix.lower() in suffixes:
            index = natural_index(path.stem, pattern)
            if index is not None:
                files[index] = path
    return files


def load_cam_params(path: Path) -> dict[str, float]:
    """The ``camera`` block of a NICE-SLAM ``cam_params.json``."""
    try:
        data = json.loads(path.read_text())
        camera = data["camera"]
        params = {key: float(camera[key]) for key in ("w", "h", "fx", "fy", "cx", "cy", "scale")}
    except (ValueError, KeyError, TypeError) as exc:
        raise ImporterError(
            f"{str(path)!r} is not a NICE-SLAM cam_params.json "
            f'({{"camera": {{"w", "h", "fx", "fy", "cx", "cy", "scale"}}}}): {exc!r}'
        ) from None
    if params["scale"] <= 0 or params["fx"] <= 0 or params["fy"] <= 0:
        raise ImporterError(f"{str(path)!r}: scale, fx and fy must be > 0, got {params}")
    return params


def load_traj(path: Path) -> np.ndarray:
    """(N, 4, 4) float64 camera-to-world poses, one row-major 4x4 per line."""
    require_file(path, "Replica trajectory traj.txt")
    rows = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise ImporterError(f"{path}:{line_no}: not numbers: {line[:60]!r}") from None
        if len(values) != 16:
            raise ImporterError(f"{path}:{line_no}: expected 16 numbers (a 4x4 pose), got {len(values)}")
        rows.append(values)
    if not rows:
        raise ImporterError(f"Replica trajectory {str(path)!r} is empty")
    return np.asarray(rows, dtype=np.float64).reshape(-1, 4, 4)


class ReplicaReader(DatasetReader):
    format_name = "replica"
    description = "Replica, NICE-SLAM layout: results/frame%06d.jpg, results/depth%06d.png, traj.txt"

    def __init__(self, root: Path | str, options: ReaderOptions | None = None) -> None:
        super().__init__(root, options)
        results = require_dir(self.root / "results", "Replica results folder (NICE-SLAM layout)")
        self._frames = _numbered(results, _FRAME, (".jpg", ".jpeg", ".png"))
        self._depths = _numbered(results, _DEPTH, (".png",)) if self.options.load_depth else {}
        if not self._frames:
            raise ImporterError(f"Replica results folder {str(results)!r} holds no frame%06d.jpg files")
        self._poses = load_traj(self.root / "traj.txt")
        ids = sorted(self._frames)
        problems = []
        if len(self._poses) != len(ids) or ids[-1] >= len(self._poses):
            problems.append(f"traj.txt has {len(self._poses)} poses for {len(ids)} colour frames")
        if self.options.load_depth and set(self._depths) != set(ids):
            missing = sorted(set(ids) - set(self._depths))
            problems.append(
                f"{len(self._depths)} depth images for {len(ids)} colour frames"
                + (f" (missing depth for frames {describe_missing(missing)})" if missing else "")
                + "; use --no-depth to import colour only"
            )
        if problems:
            raise ImporterError(f"Replica scene {str(self.root)!r}: " + "; ".join(problems))
        self._ids = ids

        self._cam_params_path: Path | None = None
        params = dict(DEFAULT_CAMERA)
        for candidate in (self.root / "cam_params.json", self.root.parent / "cam_params.json"):
            if candidate.is_file():
                params = load_cam_params(candidate)
                self._cam_params_path = candidate
                break
        self._depth_scale = params["scale"]
        K_dataset = self.options.K or (params["fx"], params["fy"], params["cx"], params["cy"])
        self._K_dataset = tuple(float(v) for v in K_dataset)
        self._K = half_pixel_K(*K_dataset)
        self._size = (int(params["w"]), int(params["h"]))
        first = read_rgb(self._frames[ids[0]])
        if (first.shape[1], first.shape[0]) != self._size and self.options.K is None:
            raise ImporterError(
                f"Replica frames are {first.shape[1]}x{first.shape[0]} but the intrinsics are for "
                f"{self._size[0]}x{self._size[1]} ({self._cam_params_path or 'NICE-SLAM defaults'}); "
                "pass --K fx,fy,cx,cy for this image size"
            )
        self._size = (first.shape[1], first.shape[0])

    def __len__(self) -> int:
        return len(self._ids)

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        frame_id = self._ids[index]
        source = f"frame{frame_id:06d}"
        world_from_cam = self._poses[frame_id].copy()
        problem = pose_problem(world_from_cam)
        if problem is not None:
            return SkippedFrame(source, problem)
        rgb = read_rgb(self._frames[frame_id])
        if (rgb.shape[1], rgb.shape[0]) != self._size:
            raise ImporterError(
                f"colour image {str(self._frames[frame_id])!r} is {rgb.shape[1]}x{rgb.shape[0]}, "
                f"expected {self._size[0]}x{self._size[1]}"
            )
        depth_m = None
        if self.options.load_depth:
            depth_m = read_depth_sized(
                self._depths[frame_id], self._depth_scale, (rgb.shape[1], rgb.shape[0]), against="colour is"
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
            "variant": "nice-slam",
            "cam_params": str(self._cam_params_path) if self._cam_params_path else "nice-slam defaults",
            "depth_scale": self._depth_scale,
            "K_dataset": list(self._K_dataset),
        }
