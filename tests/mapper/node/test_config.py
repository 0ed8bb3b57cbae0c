"""Config loading: defaults, TOML files, unknown keys, wrong types, ranges, overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapper.node.config import (
    DEFAULT_CONFIG_PATH,
    ConfigError,
    NodeConfig,
    WindowConfig,
    apply_overrides,
    config_from_dict,
    load_config,
    to_dict,
)


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "node.toml"
    path.write_text(text)
    return path


def test_shipped_launch_file_loads_and_matches_code_defaults() -> None:
    assert DEFAULT_CONFIG_PATH.is_file()
    assert load_config(DEFAULT_CONFIG_PATH) == NodeConfig()
    assert load_config() == NodeConfig()


def test_file_values_and_nested_table(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        'ingest_endpoint = "tcp://127.0.0.1:7000"\nevents_endpoint = ""\n'
        "[window]\nmax_keyframes = 5\nmin_rotation_deg = 3\n",
    )
    cfg = load_config(path)
    assert cfg.ingest_endpoint == "tcp://127.0.0.1:7000"
    assert cfg.events_endpoint is None
    assert cfg.window == WindowConfig(max_keyframes=5, min_translation_m=0.10, min_rotation_deg=3.0)
    assert isinstance(cfg.window.min_rotation_deg, float)


def test_unknown_key_names_key_and_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "[window]\nmax_keyframe = 5\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "window.max_keyframe" in str(info.value) and str(path) in str(info.value)
    with pytest.raises(ConfigError, match="ingest_endpont"):
        load_config(_write(tmp_path, 'ingest_endpont = "tcp://127.0.0.1:1"\n'))


@pytest.mark.parametrize(
    "text, key",
    [
        ('[window]\nmax_keyframes = "5"\n', "window.max_keyframes"),
        ("[window]\nmax_keyframes = 5.0\n", "window.max_keyframes"),
        ("allow_remote = 1\n", "allow_remote"),
        ("max_message_bytes = true\n", "max_message_bytes"),
        ("map_dir = 3\n", "map_dir"),
        ("window = 3\n", "window"),
    ],
)
def test_wrong_types_are_errors(tmp_path: Path, text: str, key: str) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert key in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"window": {"max_keyframes": 0}}, "window.max_keyframes = 0 out of range"),
        ({"window": {"min_rotation_deg": 181.0}}, "window.min_rotation_deg"),
        ({"ingest_endpoint": "127.0.0.1:5555"}, "not a ZeroMQ endpoint"),
        ({"ingest_endpoint": "tcp://127.0.0.1"}, "port"),
        ({"query_endpoint": "tcp://*:5556"}, "allow_remote"),
        ({"query_endpoint": "tcp://0.0.0.0:5556"}, "allow_remote"),
        ({"query_endpoint": "tcp://127.0.0.1:5555"}, "must differ"),
        ({"autosave_name": "../x"}, "autosave_name"),
        ({"log_level": "LOUD"}, "log_level"),
        ({"max_message_bytes": 10}, "max_message_bytes"),
    ],
)
def test_invalid_values_rejected(data: dict[str, object], fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment.replace("*", r"\*")):
        config_from_dict(data, where="test")


def test_remote_bind_allowed_when_explicit() -> None:
    cfg = config_from_dict({"query_endpoint": "tcp://*:5556", "allow_remote": True})
    assert cfg.query_endpoint == "tcp://*:5556"
    assert config_from_dict({"ingest_endpoint": "tcp://[::1]:5000"}).ingest_endpoint == "tcp://[::1]:5000"
    assert config_from_dict({"ingest_endpoint": "ipc:///tmp/x.sock"}).ingest_endpoint == "ipc:///tmp/x.sock"


def test_overrides_are_typed_and_skip_none() -> None:
    cfg = NodeConfig()
    new = apply_overrides(cfg, {"map_dir": "/tmp/m", "window.max_keyframes": 7, "query_endpoint": None})
    assert new.map_dir == "/tmp/m" and new.window.max_keyframes == 7
    assert new.query_endpoint == cfg.query_endpoint
    assert cfg.window.max_keyframes == 30  # the original is untouched (frozen)
    with pytest.raises(ConfigError, match="unknown config key 'window.nope'"):
        apply_overrides(cfg, {"window.nope": 1})
    with pytest.raises(ConfigError, match="unknown config key 'window'"):
        apply_overrides(cfg, {"window": 1})
    with pytest.raises(ConfigError, match="window.max_keyframes must be an int"):
        apply_overrides(cfg, {"window.max_keyframes": "7"})


def test_to_dict_roundtrip() -> None:
    cfg = config_from_dict({"events_endpoint": "", "window": {"max_keyframes": 3}})
    assert config_from_dict(to_dict(cfg)) == cfg


def test_missing_and_broken_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(_write(tmp_path, "x = = 1\n"))


def test_docstring_examples_of_config_window_store() -> None:
    import doctest

    import mapper.map.window
    import mapper.node.config
    import mapper.node.store

    for module in (mapper.node.config, mapper.map.window, mapper.node.store):
        result = doctest.testmod(module)
        assert result.attempted > 0 and result.failed == 0, module.__name__


def test_every_launch_preset_loads() -> None:
    presets = sorted(DEFAULT_CONFIG_PATH.parent.glob("node*.toml"))
    assert DEFAULT_CONFIG_PATH in presets and len(presets) >= 2
    for path in presets:
        cfg = load_config(path)
        assert cfg.window.max_keyframes >= 1, path


def test_node_limits_numpys_blas_threads(tmp_path: Path) -> None:
    """``limits.blas_threads``: the node sets numpy's BLAS threads when it is made (process-wide);
    0 leaves them as they are."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from mapper.node.service import MapperNode

    def blas_threads() -> set[int]:
        return {int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"}

    before = threadpool_limits(limits=2, user_api="blas")  # a known starting point, restored below
    try:
        base = {"map_dir": str(tmp_path), "autosave_name": "", "save_on_exit": False}
        MapperNode(config_from_dict({**base, "limits": {"blas_threads": 0}})).stop()
        assert blas_threads() == {2}
        MapperNode(config_from_dict(base)).stop()  # the default, 1
        assert blas_threads() == {1}
    finally:
        before.restore_original_limits()
