"""Microsoft 7-Scenes (RGB-D relocalisation dataset)::

    SCENE/seq-01/frame-000000.color.png   colour, 640x480
    SCENE/seq-01/frame-000000.depth.png   uint16 millimetres, 65535 = no measurement
    SCENE/seq-01/frame-000000.pose.txt    4x4 camera-to-world, metres

PATH is a scene folder (all ``seq-XX`` folders are imported one after another, in name order;
they share one world frame) or a single ``seq-XX`` folder. Intrinsics default to the published
nominal values fx = fy = 585, cx = 320, cy = 240; ``--K`` overrides. Capture times are
synthesised at ``--fps`` over the concatenated frames. The 7-Scenes world frame is that of the
KinectFusion volume, set by a roughly upright camera, so its -y axis points (approximately) up:
the import rotates it to +z by default (``--up-axis -y``; ``--up-axis z`` keeps it as is).

Limitation: 7-Scenes colour and depth are NOT registered (the depth comes from the Kinect's
depth camera, a few centimetres beside the colour camera, with its own intrinsics). The importer
pairs them as they are, with one K, so colour and depth disagree by a few pixels, more at object
edges and close range. Geometry from depth and the poses is consistent (the poses were tracked
with the depth camera by KinectFusion).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from clients.importers.base import (
    DatasetReader,
    ImportedFrame,
    ImporterError,
    ReaderOptions,
    SkippedFrame,
    describe_missing,
    half_pixel_K,
    pose_problem,
    read_depth_sized,
    read_matrix_txt,
    read_rgb,
)

DEFAULT_K = (585.0, 585.0, 320.0, 240.0)
DEPTH_UNITS_PER_M = 1000.0
DEPTH_INVALID = 65535
_SEQ = re.compile(r"seq-\d+")
_FRAME = re.compile(r"frame-(\d+)\.(color|depth|pose)")


class SevenScenesReader(DatasetReader):
    format_name = "7scenes"
    description = "Microsoft 7-Scenes: seq-XX/frame-XXXXXX.{color,depth}.png + .pose.txt"
    default_up_axis = "-y"  # the world is KinectFusion's first camera frame: y points down

    def __init__(self, root: Path | str, options: ReaderOptions | None = None) -> None:
        super().__init__(root, options)
        if _SEQ.fullmatch(self.root.name):
            sequences = [self.root]
        else:
            sequences = sorted(p for p in self.root.iterdir() if p.is_dir() and _SEQ.fullmatch(p.name))
        if not sequences:
            raise ImporterError(
                f"7-Scenes path {str(self.root)!r} is neither a seq-XX folder nor holds seq-XX folders"
            )
        self._frames: list[tuple[str, Path, int]] = []  # (sequence name, folder, frame number)
        for seq in sequences:
            kinds: dict[str, set[int]] = {"color": set(), "depth": set(), "pose": set()}
            for path in seq.iterdir():
                match = _FRAME.fullmatch(path.name.rsplit(".", 1)[0])
                if match:
                    kinds[match.group(2)].add(int(match.group(1)))
            colors = kinds["color"]
            if not colors:
                raise ImporterError(f"7-Scenes sequence {str(seq)!r} holds no frame-XXXXXX.color.png files")
            needed = ["pose", "depth"] if self.options.load_depth else ["pose"]
            for kind in needed:
                missing = sorted(colors - kinds[kind])
                if missing:
                    hint = "" if kind == "pose" else " (use --no-depth to import colour only)"
                    raise ImporterError(
                        f"7-Scenes sequence {str(seq)!r}: {len(colors)} colour images but {len(kinds[kind])} "
                        f"{kind} files; missing {kind} for frames {describe_missing(missing)}{hint}"
                    )
            self._frames.extend((seq.name, seq, n) for n in sorted(colors))
        self._K_dataset = tuple(float(v) for v in (self.options.K or DEFAULT_K))
        self._K = half_pixel_K(*self._K_dataset)
        self._sequences = [s.name for s in sequences]

    def __len__(self) -> int:
        return len(self._frames)

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        seq_name, folder, number = self._frames[index]
        stem = folder / f"frame-{number:06d}"
        source = f"{seq_name}/frame-{number:06d}"
        world_from_cam = read_matrix_txt(stem.with_name(stem.name + ".pose.txt"), "7-Scenes pose")
        problem = pose_problem(world_from_cam)
        if problem is not None:
            return SkippedFrame(source, problem)
        rgb = read_rgb(stem.with_name(stem.name + ".color.png"))
        depth_m = None
        if self.options.load_depth:
            depth_path = stem.with_name(stem.name + ".depth.png")
            depth_m = read_depth_sized(
                depth_path,
                DEPTH_UNITS_PER_M,
                (rgb.shape[1], rgb.shape[0]),
                against="colour is",
                invalid_value=DEPTH_INVALID,
            )
        return ImportedFrame(
            rgb=rgb,
            depth_m=depth_m,
            K=self._K.copy(),
            world_from_cam=world_from_cam,
            stamp_ns=self.stamp_from_index(index),
            source=source,
        )

    def meta(self) -> dict[str, Any]:
        return {"sequences": self._sequences, "K_dataset": list(self._K_dataset), "registered_depth": False}

    def warnings(self) -> list[str]:
        if not self.options.load_depth:
            return []
        return ["7-Scenes colour and depth are not registered; they are paired as is "
                "(see docs/how-to/import.md)"]
