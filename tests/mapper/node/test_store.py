"""Map store: atomic save/load roundtrip, no pickle, names and paths confined to the map directory."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapper.node.store import MapStore, StoreError, validate_map_name


def test_roundtrip_and_names(tmp_path: Path) -> None:
    store = MapStore(tmp_path / "maps")
    assert store.names() == []
    arrays: dict[str, np.ndarray] = {
        "kf.0.rgb": np.arange(24, dtype=np.uint8).reshape(2, 4, 3),
        "x": np.eye(4),
    }
    path = store.save("room_1.v2", arrays, {"map_version": 3, "keyframes": [{"seq": 1}]})
    assert path == (tmp_path / "maps" / "room_1.v2.govmap").resolve()
    loaded, manifest = store.load("room_1.v2")
    assert set(loaded) == set(arrays)
    for key, value in arrays.items():
        np.testing.assert_array_equal(loaded[key], value)
        assert loaded[key].dtype == value.dtype
    assert manifest["map_version"] == 3 and manifest["keyframes"] == [{"seq": 1}]
    assert store.names() == ["room_1.v2"]
    # no temporary files are left behind
    assert sorted(os.listdir(tmp_path / "maps")) == ["room_1.v2.govmap"]


def test_overwrite_replaces_atomically(tmp_path: Path) -> None:
    store = MapStore(tmp_path)
    store.save("m", {"a": np.zeros(3)}, {"n": 1})
    store.save("m", {"b": np.ones(2)}, {"n": 2})
    arrays, manifest = store.load("m")
    assert set(arrays) == {"b"} and manifest["n"] == 2


@pytest.mark.parametrize(
    "name",
    [
        "../evil",
        "..",
        ".",
        "...",
        "a/b",
        "/etc/passwd",
        "a\\b",
        "",
        "x" * 65,
        "na me",
        "ü",
        "a\x00b",
        None,
        3,
    ],
)
def test_bad_names_rejected_and_nothing_written(tmp_path: Path, name: object) -> None:
    store = MapStore(tmp_path / "maps")
    with pytest.raises(StoreError, match="invalid"):
        store.save(name, {"a": np.zeros(1)}, {})  # type: ignore[arg-type]
    with pytest.raises(StoreError):
        store.load(name)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        validate_map_name(name)
    assert not (tmp_path / "maps").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_symlink_pointing_outside_is_refused(tmp_path: Path) -> None:
    maps = tmp_path / "maps"
    maps.mkdir()
    outside = tmp_path / "secret.govmap"
    outside.write_bytes(b"secret")
    (maps / "link.govmap").symlink_to(outside)
    store = MapStore(maps)
    with pytest.raises(StoreError, match="outside"):
        store.load("link")
    with pytest.raises(StoreError, match="outside"):
        store.save("link", {"a": np.zeros(1)}, {})
    assert outside.read_bytes() == b"secret"


def test_pickle_and_bad_arrays_refused(tmp_path: Path) -> None:
    store = MapStore(tmp_path)
    with pytest.raises(StoreError, match="numeric"):
        store.save("m", {"a": np.array([{"x": 1}], dtype=object)}, {})
    with pytest.raises(StoreError, match="not allowed"):
        store.save("m", {"../a": np.zeros(1)}, {})
    # a hand-made file with a pickled object array does not load
    with open(tmp_path / "p.govmap", "wb") as fh:
        payload: dict[str, Any] = {
            "manifest.json": np.frombuffer(b"{}", np.uint8),
            "o": np.array([1, "x"], dtype=object),
        }
        np.savez(fh, allow_pickle=True, **payload)
    with pytest.raises(StoreError):
        store.load("p")


def test_missing_and_corrupt_maps(tmp_path: Path) -> None:
    store = MapStore(tmp_path)
    store.save("good", {"a": np.zeros(1)}, {})
    with pytest.raises(StoreError, match="no saved map named 'nope' \\(available: good\\)"):
        store.load("nope")
    (tmp_path / "junk.govmap").write_bytes(b"not a zip")
    with pytest.raises(StoreError, match="corrupt"):
        store.load("junk")
    with open(tmp_path / "other.govmap", "wb") as fh:
        other: dict[str, Any] = {"manifest.json": np.frombuffer(b'{"format": "x"}', np.uint8)}
        np.savez(fh, allow_pickle=False, **other)
    with pytest.raises(StoreError, match="not a govnesf map"):
        store.load("other")
    # a truncated file (crash while someone else wrote it by hand) is reported, not crashed on
    data = (tmp_path / "good.govmap").read_bytes()
    (tmp_path / "cut.govmap").write_bytes(data[: len(data) // 2])
    with pytest.raises(StoreError):
        store.load("cut")


def test_failed_write_keeps_old_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = MapStore(tmp_path)
    store.save("m", {"a": np.zeros(3)}, {"n": 1})

    def boom(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(StoreError, match="No space left"):
        store.save("m", {"a": np.ones(3)}, {"n": 2})
    monkeypatch.undo()
    arrays, manifest = store.load("m")
    assert manifest["n"] == 1 and arrays["a"].tolist() == [0.0, 0.0, 0.0]
    assert sorted(os.listdir(tmp_path)) == ["m.govmap"]
