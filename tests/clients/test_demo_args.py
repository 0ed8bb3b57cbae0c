"""The demo's command line: node overrides (``--set``) are checked before any work and reach both
nodes' command lines."""

from __future__ import annotations

from pathlib import Path

import pytest

from clients import demo


def test_demo_set_is_validated_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    for bad, message in (("bogus", "expected KEY=VALUE"), ("window.nope=3", "unknown config key"),
                         ("model.source_views=999", "out of range")):
        with pytest.raises(SystemExit) as exc:
            demo.main(["--out", str(out), "--set", bad])
        assert exc.value.code == 2
        assert message in capsys.readouterr().err
    assert not out.exists()  # nothing written


def test_demo_set_reaches_the_nodes() -> None:
    args = demo._parse_args(["--set", "model.source_views=16", "--set", "queries.workers=2"])
    assert demo._node_sets(args) == ["--set", "model.source_views=16", "--set", "queries.workers=2"]
    assert demo._node_sets(demo._parse_args([])) == []


def test_serve_check_config(capsys: pytest.CaptureFixture[str]) -> None:
    from mapper.node.cli import serve_main

    assert serve_main(["--check-config", "--set", "model.point_source_views=12"]) == 0
    assert capsys.readouterr().out.strip() == "config ok"
    assert serve_main(["--check-config", "--set", "window.nope=1"]) == 2
    assert "unknown config key" in capsys.readouterr().err
