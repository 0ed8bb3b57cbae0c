"""Format name -> reader class, and a helper to open a dataset folder by format name."""

from __future__ import annotations

from pathlib import Path

from clients.importers.base import DatasetReader, ImporterError, ReaderOptions
from clients.importers.open3d_log import Open3dLogReader
from clients.importers.replica import ReplicaReader
from clients.importers.rosbag import RosbagReader
from clients.importers.scannet import ScanNetReader
from clients.importers.sevenscenes import SevenScenesReader
from clients.importers.sim import SimReader
from clients.importers.tum import TumReader

FORMATS: dict[str, type[DatasetReader]] = {
    reader.format_name: reader
    for reader in (
        ScanNetReader, ReplicaReader, TumReader, SevenScenesReader, Open3dLogReader, SimReader, RosbagReader
    )
}

ALIASES: dict[str, str] = {"icl": "open3d"}
"""Other names accepted for a format (alias -> a key of :data:`FORMATS`); recordings and summaries
carry the format's own name."""


def open_dataset(format_name: str, path: Path | str, options: ReaderOptions | None = None) -> DatasetReader:
    """Open ``path`` with the reader for ``format_name`` (one of :data:`FORMATS` or :data:`ALIASES`)."""
    name = ALIASES.get(format_name, format_name)
    if name not in FORMATS:
        aliases = ", ".join(f"{alias} = {target}" for alias, target in ALIASES.items())
        raise ImporterError(
            f"unknown dataset format {format_name!r}; choose one of {', '.join(FORMATS)} (aliases: {aliases})"
        )
    return FORMATS[name](path, options)
