"""The simulator's export (``clients/sim/export.py``)::

    DIR/frames.govrec    a recording, already in project conventions
    DIR/gt/              ground truth (labels, meshes); not part of the recording

Importing it validates every frame (each is decoded and checked by ``protocol``) and writes a new
recording with the chosen stride, frame limit and colour encoding; K, poses, depth and any
open-vocabulary features pass through unchanged. PATH is the export folder or a ``.govrec`` file.
Colour is decoded and re-encoded, so ``jpeg`` -> ``jpeg`` loses a little quality.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from clients.importers.base import (
    DatasetReader,
    ImportedFrame,
    ImporterError,
    ReaderOptions,
    SkippedFrame,
    require_file,
)

RECORDING_NAME = "frames.govrec"


class SimReader(DatasetReader):
    format_name = "sim"
    description = "simulator export: DIR/frames.govrec (+ DIR/gt/), or a .govrec file"

    def __init__(self, root: Path | str, options: ReaderOptions | None = None) -> None:
        from protocol.errors import ProtocolError
        from protocol.recording import read_recording

        super().__init__(root, options)
        if self.options.K is not None:
            raise ImporterError("--K does not apply to sim: the recording carries each frame's intrinsics")
        self._path = self.root / RECORDING_NAME if self.root.is_dir() else self.root
        require_file(self._path, f"simulator recording ({RECORDING_NAME})")
        try:
            self._recording = read_recording(self._path)
        except ProtocolError as exc:
            raise ImporterError(f"cannot read recording {str(self._path)!r}: {exc.message}") from None
        self._count = sum(1 for _ in self._recording)  # scans message boundaries only
        self._warnings = []
        if self._recording.truncated:
            self._warnings.append(
                f"source recording is damaged, using the {self._count} frames before it: "
                f"{self._recording.error}"
            )
        gt_dir = self._path.parent / "gt"
        self._gt_dir = gt_dir if gt_dir.is_dir() else None

    def __len__(self) -> int:
        return self._count

    def iter_frames(self, indices: Iterable[int]) -> Iterator[ImportedFrame | SkippedFrame]:
        from protocol.errors import ProtocolError

        wanted = iter(sorted(set(indices)))
        next_index = next(wanted, None)
        frames = self._recording.frames()
        position = 0
        while next_index is not None:
            try:
                frame = next(frames)
            except StopIteration:
                return
            except ProtocolError as exc:
                raise ImporterError(f"invalid frame in {str(self._path)!r}: {exc.message}") from None
            if position == next_index:
                depth_m = frame.depth_m if self.options.load_depth else None
                yield ImportedFrame(
                    rgb=frame.rgb,
                    depth_m=depth_m,
                    K=np.asarray(frame.K, dtype=np.float64),
                    world_from_cam=np.asarray(frame.world_from_cam, dtype=np.float64),
                    stamp_ns=frame.stamp_ns,
                    source=f"frame {position} (seq {frame.seq})",
                    ov=frame.ov,
                    ov_space=frame.ov_space,
                )
                next_index = next(wanted, None)
            position += 1

    def read(self, index: int) -> ImportedFrame | SkippedFrame:
        if not 0 <= index < self._count:
            raise IndexError(f"frame index {index} out of range 0..{self._count - 1}")
        return next(iter(self.iter_frames([index])))

    def meta(self) -> dict[str, Any]:
        return {
            "source_meta": dict(self._recording.header.meta),
            "gt_dir": str(self._gt_dir.resolve()) if self._gt_dir else None,
        }

    def warnings(self) -> list[str]:
        return list(self._warnings)
