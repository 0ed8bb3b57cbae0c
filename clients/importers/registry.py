"""Format name -> reader class, and a helper to open a dataset folder by format name."""

from __future__ import annotations

from pathlib import Path

from clients.importers.base import DatasetReader, ImporterError, ReaderOptions
from clients.importers.replica import ReplicaReader
from clients.importers.scannet import ScanNetReader
from clients.importers.sevenscenes import SevenScenesReader
from clients.importers.sim import SimReader
from clients.importers.tum import TumReader

FORMATS: dict[str, type[DatasetReader]] = {
    reader.format_name: reader
    for reader in (ScanNetReader, ReplicaReader, TumReader, SevenScenesReader, SimReader)
}


def open_dataset(format_name: str, path: Path | str, options: ReaderOptions | None = None) -> DatasetReader:
    """Open ``path`` with the reader for ``format_name`` (one of :data:`FORMATS`)."""
    if format_name not in FORMATS:
        raise ImporterError(f"unknown dataset format {format_name!r}; choose one of {', '.join(FORMATS)}")
    return FORMATS[format_name](path, options)
