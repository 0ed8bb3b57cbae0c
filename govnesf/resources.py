"""Where the shipped data lives: the model checkpoints and the ``launch/*.toml`` presets.

In a checkout they are the repository's ``checkpoints/`` and ``launch/`` folders. An installed
wheel carries the same files as package data, ``govnesf/checkpoints/`` and ``govnesf/launch/``
(``pyproject.toml`` maps the two folders into the package), found through ``importlib.resources``.
So a relative path such as ``checkpoints/cpu-small.safetensors`` or ``launch/node.toml`` means
the same file in both cases (after the working directory, which is always tried first).
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

__all__ = ["DATA_DIRS", "data_root", "find_data_file"]

DATA_DIRS: tuple[str, ...] = ("checkpoints", "launch")
"""The folders shipped as package data."""

_REPO_ROOT = Path(__file__).resolve().parents[1]


def data_root() -> Path:
    """The folder that holds ``checkpoints/`` and ``launch/``.

    The installed package's data when it has them (``importlib.resources.files("govnesf")``),
    otherwise the repository root this module lives in (a checkout, an editable install).
    """
    packaged = importlib.resources.files("govnesf")
    if isinstance(packaged, Path) and all((packaged / name).is_dir() for name in DATA_DIRS):
        return packaged
    return _REPO_ROOT


def find_data_file(relative: str | Path) -> Path:
    """``relative`` (e.g. ``launch/node.toml``) under :func:`data_root`; the path is returned
    whether or not it exists (callers report a missing file with its full path)."""
    rel = Path(relative)
    if rel.is_absolute():
        raise ValueError(f"expected a path relative to the data root, got {str(rel)!r}")
    return data_root() / rel
