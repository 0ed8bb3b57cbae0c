"""Dataset importers: convert ScanNet, Replica (NICE-SLAM layout), TUM RGB-D, 7-Scenes, Open3D
logs, ROS 2 bags and the simulator's export into ``.govrec`` recordings (``govnesf import``; see
``docs/how-to/import.md``).

Example::

    from clients.importers import ReaderOptions, convert, open_dataset

    reader = open_dataset("tum", "rgbd_dataset_freiburg1_xyz", ReaderOptions(load_depth=True))
    summary = convert(reader, "fr1_xyz.govrec", stride=2, rgb_encoding="jpeg")
    print(summary.format())
"""

from clients.importers.base import (
    DatasetReader,
    ImportedFrame,
    ImporterError,
    ImportSummary,
    ReaderOptions,
    SkippedFrame,
)
from clients.importers.convert import convert
from clients.importers.registry import FORMATS, open_dataset

__all__ = [
    "FORMATS",
    "DatasetReader",
    "ImportSummary",
    "ImportedFrame",
    "ImporterError",
    "ReaderOptions",
    "SkippedFrame",
    "convert",
    "open_dataset",
]
