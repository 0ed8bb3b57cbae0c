"""Turn a :class:`DatasetReader`'s frames into a ``.govrec`` recording.

The recording is written to ``OUT.partial`` and renamed to ``OUT`` only when the import
succeeds, so a failed import leaves nothing behind and never clobbers an existing file.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from clients.importers.base import DatasetReader, ImportedFrame, ImporterError, ImportSummary, SkippedFrame

RGB_ENCODINGS = ("rgb8", "jpeg", "png")
MAX_IMAGE_SIDE = 4096  # protocol limit on width and height


def to_protocol_frame(
    frame: ImportedFrame,
    seq: int,
    rgb_encoding: str,
    with_depth: bool,
    world_from_dataset: np.ndarray | None = None,
) -> Any:
    """An :class:`ImportedFrame` as a ``protocol.messages.Frame`` with sequence number ``seq``;
    ``world_from_dataset`` (4, 4), if given, re-expresses the pose in the project's world frame."""
    from protocol.messages import Frame

    world_from_cam = np.asarray(frame.world_from_cam, dtype=np.float64)
    if world_from_dataset is not None:
        world_from_cam = world_from_dataset @ world_from_cam

    height, width = frame.rgb.shape[:2]
    depth_m = None
    if with_depth and frame.depth_m is not None:
        depth_m = np.ascontiguousarray(frame.depth_m, dtype=np.float32)
    return Frame(
        seq=seq,
        stamp_ns=int(frame.stamp_ns),
        width=int(width),
        height=int(height),
        K=np.asarray(frame.K, dtype=np.float64),
        world_from_cam=world_from_cam,
        rgb=np.ascontiguousarray(frame.rgb, dtype=np.uint8),
        camera="cam0",
        depth_m=depth_m,
        ov=frame.ov,
        ov_space=frame.ov_space if frame.ov is not None else None,
        rgb_encoding=rgb_encoding,
    )


def _check_frame(frame: ImportedFrame, first: ImportedFrame | None) -> None:
    """Readers are trusted to follow the ImportedFrame contract; check the parts that would make
    a recording unusable, with the frame's source in the message."""
    rgb = frame.rgb
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ImporterError(f"{frame.source}: colour must be (H, W, 3) uint8, got {rgb.dtype} {rgb.shape}")
    height, width = rgb.shape[:2]
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise ImporterError(
            f"{frame.source}: image {width}x{height} out of the protocol's range 1..{MAX_IMAGE_SIDE}"
        )
    if frame.depth_m is not None and frame.depth_m.shape != (height, width):
        raise ImporterError(
            f"{frame.source}: depth {frame.depth_m.shape} does not match colour {(height, width)}"
        )
    if first is not None and first.rgb.shape != rgb.shape:
        raise ImporterError(
            f"{frame.source}: image size {width}x{height} differs from the first frame's "
            f"{first.rgb.shape[1]}x{first.rgb.shape[0]}"
        )


def convert(
    reader: DatasetReader,
    out_path: Path | str,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    rgb_encoding: str = "rgb8",
    with_depth: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    extra_meta: dict[str, Any] | None = None,
) -> ImportSummary:
    """Write every ``stride``-th source frame of ``reader`` (at most ``max_frames`` written) to
    the recording ``out_path``; skipped frames are counted by reason in the returned summary.

    Raises :class:`ImporterError` on a bad option or bad input; then nothing is written.
    """
    from protocol.errors import ProtocolError
    from protocol.recording import RecordingWriter

    out_path = Path(out_path)
    if stride < 1:
        raise ImporterError(f"--stride must be >= 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise ImporterError(f"--max-frames must be >= 1, got {max_frames}")
    if rgb_encoding not in RGB_ENCODINGS:
        raise ImporterError(f"--rgb-encoding must be one of {', '.join(RGB_ENCODINGS)}, got {rgb_encoding!r}")
    if out_path.suffix != ".govrec":
        raise ImporterError(f"--out must name a .govrec file, got {str(out_path)!r}")
    if out_path.exists() and not overwrite:
        raise ImporterError(f"{str(out_path)!r} exists; pass --overwrite to replace it")
    if not out_path.parent.is_dir():
        raise ImporterError(f"output folder {str(out_path.parent)!r} does not exist")

    summary = ImportSummary(out_path=out_path, format_name=reader.format_name, warnings=reader.warnings())
    indices = range(0, len(reader), stride)
    meta: dict[str, Any] = {
        "source_format": reader.format_name,
        "source_path": str(reader.root.resolve()),
        "importer": "govnesf import",
        "imported_at_ns": time.time_ns(),
        "stride": stride,
        "K_convention": "pixel centres at integer + 0.5",
        "up_axis": reader.up_axis,
        "world_from_dataset": reader.world_from_dataset.reshape(16).tolist(),
        **reader.meta(),
        **(extra_meta or {}),
    }
    partial = out_path.with_name(out_path.name + ".partial")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(indices), unit="frame", desc=f"import {reader.format_name}", leave=False)
    first: ImportedFrame | None = None
    try:
        with RecordingWriter(partial, meta) as writer:
            for item in reader.iter_frames(indices):
                summary.frames_considered += 1
                if bar is not None:
                    bar.update(1)
                if isinstance(item, SkippedFrame):
                    summary.skipped[item.reason] = summary.skipped.get(item.reason, 0) + 1
                    continue
                _check_frame(item, first)
                first = first or item
                try:
                    message = to_protocol_frame(
                        item, summary.frames_written, rgb_encoding, with_depth, reader.world_from_dataset
                    )
                except ProtocolError as exc:
                    raise ImporterError(f"{item.source}: not a valid protocol frame: {exc.message}") from None
                writer.write(message)
                summary.frames_written += 1
                if max_frames is not None and summary.frames_written >= max_frames:
                    break
        if summary.frames_written == 0:
            reasons = ", ".join(f"{n} x {r}" for r, n in summary.skipped.items()) or "no source frames"
            raise ImporterError(
                f"no frames to write from {str(reader.root)!r}: {summary.frames_considered} considered, "
                f"all skipped ({reasons})"
            )
        os.replace(partial, out_path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    finally:
        if bar is not None:
            bar.close()
    if first is not None:
        summary.height, summary.width = first.rgb.shape[:2]
    return summary
