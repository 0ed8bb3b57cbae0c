"""Saving and loading maps inside one directory, crash-safe and without pickle.

A saved map is a single file ``<map_dir>/<name>.govmap``: an uncompressed ``.npz`` (a zip of
``.npy`` arrays, loaded with ``allow_pickle=False``) whose array ``manifest.json`` holds a UTF-8
JSON manifest (format version, what each section contains, metadata). Sections are key prefixes:
``kf.<i>.<field>`` for the keyframe window; a later stage adds e.g. ``global.<field>`` for the
global semantic map by passing more arrays and manifest entries, without changing this module.

Safety rules (a name comes off the network):
- names must match ``[A-Za-z0-9_.-]{1,64}`` and not be all dots;
- the resolved path must lie directly in the resolved map directory (symlinks pointing elsewhere
  are refused);
- writes go to a temporary file in the same directory, are fsynced, then ``os.replace``d over the
  target, so a crash leaves either the old map or the new one, never half a file.

Example::

    >>> import tempfile, numpy as np
    >>> store = MapStore(tempfile.mkdtemp())
    >>> _ = store.save("demo", {"x": np.arange(3)}, {"note": "hi"})
    >>> arrays, manifest = store.load("demo")
    >>> arrays["x"].tolist(), manifest["note"]
    ([0, 1, 2], 'hi')
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

MAP_NAME_PATTERN = r"[A-Za-z0-9_.-]{1,64}"
"""Allowed map names (wire protocol ``save`` / ``load``)."""

MAP_SUFFIX = ".govmap"
FORMAT = "govnesf-map"
FORMAT_VERSION = 1
_MANIFEST_KEY = "manifest.json"


class StoreError(Exception):
    """A save or load failed; the message says why (safe to send to a client)."""


class StoreWriteError(StoreError):
    """Writing failed on the node's side (disk full, permissions): not the requester's fault."""


def validate_map_name(name: object) -> str:
    """Return ``name`` if it is a valid map name, else raise ``ValueError`` saying what is allowed."""
    if not isinstance(name, str) or not re.fullmatch(MAP_NAME_PATTERN, name) or set(name) == {"."}:
        raise ValueError(
            f"map name {name!r} is invalid: use 1..64 characters from A-Z a-z 0-9 _ . - (not only dots)"
        )
    return name


class MapStore:
    """Reads and writes ``.govmap`` files inside ``map_dir`` and nowhere else."""

    def __init__(self, map_dir: str | Path) -> None:
        self.map_dir = Path(map_dir)

    def path_for(self, name: str) -> Path:
        """The file for map ``name``; raises ``StoreError`` for bad names or paths leaving map_dir."""
        try:
            validate_map_name(name)
        except ValueError as exc:
            raise StoreError(str(exc)) from None
        root = self.map_dir.resolve()
        path = (root / (name + MAP_SUFFIX)).resolve()
        if path.parent != root:
            raise StoreError(f"map name {name!r} resolves outside the map directory {str(root)!r}")
        return path

    def names(self) -> list[str]:
        """Names of the saved maps, sorted."""
        if not self.map_dir.is_dir():
            return []
        return sorted(p.name[: -len(MAP_SUFFIX)] for p in self.map_dir.glob("*" + MAP_SUFFIX) if p.is_file())

    def save(self, name: str, arrays: dict[str, np.ndarray], manifest: dict[str, Any]) -> Path:
        """Write ``arrays`` (numeric arrays only) and a JSON-serialisable ``manifest`` atomically."""
        path = self.path_for(name)
        for key, array in arrays.items():
            if key == _MANIFEST_KEY or not re.fullmatch(r"[A-Za-z0-9_.-]+", key):
                raise StoreError(f"array key {key!r} is not allowed in a map file")
            if array.dtype.hasobject:
                raise StoreError(f"array {key!r} has dtype {array.dtype}; only numeric arrays can be saved")
        full_manifest = {"format": FORMAT, "format_version": FORMAT_VERSION, **manifest}
        manifest_bytes = np.frombuffer(json.dumps(full_manifest).encode("utf-8"), dtype=np.uint8)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp_name = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=path.parent)
        except OSError as exc:
            raise StoreWriteError(
                f"cannot write to map directory {str(path.parent)!r}: {exc.strerror}"
            ) from None
        try:
            with os.fdopen(fd, "wb") as fh:
                payload: dict[str, Any] = {_MANIFEST_KEY: manifest_bytes, **arrays}
                np.savez(fh, allow_pickle=False, **payload)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp_name, path)
        except BaseException as exc:
            try:
                os.unlink(tmp_name)
            except OSError:
                pass
            if isinstance(exc, OSError):
                raise StoreWriteError(f"saving map {name!r} failed: {exc}") from None
            raise
        _fsync_dir(path.parent)
        return path

    def load(self, name: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Read map ``name``: ``(arrays, manifest)``. Raises ``StoreError`` when missing or corrupt."""
        path = self.path_for(name)
        if not path.is_file():
            available = ", ".join(self.names()) or "none"
            raise StoreError(f"no saved map named {name!r} (available: {available})")
        try:
            with np.load(path, allow_pickle=False) as npz:
                arrays = {key: npz[key] for key in npz.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise StoreError(f"map {name!r} is unreadable or corrupt: {exc}") from None
        raw = arrays.pop(_MANIFEST_KEY, None)
        if raw is None or raw.dtype != np.uint8 or raw.ndim != 1:
            raise StoreError(f"map {name!r} has no valid manifest")
        try:
            manifest = json.loads(raw.tobytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise StoreError(f"map {name!r} has a corrupt manifest: {exc}") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise StoreError(f"{str(path)!r} is not a govnesf map file")
        if manifest.get("format_version") != FORMAT_VERSION:
            raise StoreError(
                f"map {name!r} has format version {manifest.get('format_version')!r}; "
                f"this node reads version {FORMAT_VERSION}"
            )
        return arrays, manifest


def _fsync_dir(directory: Path) -> None:
    """Make the rename durable (best effort; not every platform can open a directory)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
