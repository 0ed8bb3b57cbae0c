"""``govnesf bench --quick``: the command starts a real node, runs every phase at tiny sizes and
writes valid JSON (with the expected keys) and Markdown. No timing is asserted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from clients.cli import SUBCOMMANDS
from clients.cli.bench import EXPECTED_KEYS, main

pytestmark = pytest.mark.slow


def test_bench_quick_writes_json_and_markdown(tmp_path: Path) -> None:
    assert SUBCOMMANDS["bench"][0] == "clients.cli.bench"
    out = tmp_path / "bench"
    # without the learned model the node starts fast; render / govnesf then record not_ready
    assert main(["--quick", "--out", str(out), "--node-arg=--set", "--node-arg=serve_model=false"]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert set(EXPECTED_KEYS) <= set(result)
    machine = result["machine"]
    assert machine["python"] and machine["cpu_count"] and machine["torch"]
    assert result["ingest"]["frames"] == 12 and sum(result["ingest"]["acks"].values()) == 12
    assert result["ingest"]["integrate_ms_p50"] is not None
    planner = result["ingest"]["planner"]
    assert planner["answer_age"]["n"] == planner["answers"]  # one age per answer
    for method in ("average", "average_depth"):
        assert result["segment_points"][method]["error"] is None
        assert result["segment_points"][method]["per_100k_s"] > 0
        assert result["segment_points"][method]["first_s"] > 0  # the first call, apart from the repeats
        assert len(result["segment_points"][method]["seconds"]) == 1
    assert 0 <= result["segment_points"]["settle_s"] <= 60.0
    assert "not_ready" in (result["segment_points"]["govnesf"]["error"] or "")
    assert set(result["render"]) == {"16x12", "20x15"}
    assert result["status_during_render"]["status"]["n"] >= 3
    q = result["query_points"]["1000"]
    assert q["first"]["n"] == 1 and q["cached"]["n"] == 3 and q["floor_ms"] > 0
    assert q["repeat"]["n"] == 3 and q["new_text"]["n"] == 3
    assert [s["frame"] for s in result["rss"]["samples"]] == [5, 10]
    assert all(s["rss_bytes"] for s in result["rss"]["samples"])
    floor = result["floor"]  # a tiny floor's tour into a second node (default settings + --node-arg)
    assert floor["rooms"] == 2 and floor["frames"] == 40 and sum(floor["acks"].values()) == 40
    assert floor["tour"]["visits"] == [0, 1, 0, 1]
    assert floor["global_points"] > 0 and floor["global_points_pruned"] == 0
    assert [s["frame"] for s in floor["rss"]] == [10, 20, 30, 40]
    assert all(s["rss_bytes"] for s in floor["rss"])
    assert floor["ack_first"]["n"] == floor["ack_last"]["n"] == floor["window"] == 20
    assert floor["integrate_last"]["p95_ms"] is not None
    assert floor["query_points"]["whole"]["n"] == floor["query_points"]["region"]["n"] == 3
    assert floor["save_s"] > 0 and floor["load_s"] > 0
    md = out.with_suffix(".md").read_text()
    assert md.startswith("# govnesf bench (quick)") and "## query_points" in md
    assert "## A floor of 2 rooms" in md


def test_bench_refuses_bad_input_before_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bad --frames is an argparse error; an unwritable --out fails at once, writes nothing."""
    for bad in (["--frames", "-3"], ["--rss-frames", "0"], ["--floor-frames", "0"]):
        with pytest.raises(SystemExit) as exc:
            main(bad)
        assert exc.value.code == 2
        assert "must be 1 or more" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["--floor-rooms", "31"])
    assert exc.value.code == 2 and "must be 0 (no floor phase) or 2..30" in capsys.readouterr().err
    afile = tmp_path / "afile"
    afile.write_text("")
    assert main(["--out", str(afile / "x")]) == 2
    assert "cannot write --out" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_busy_items_count_what_the_node_still_has_queued() -> None:
    from clients.cli.bench_common import _busy_items

    assert _busy_items({}) == 0
    assert _busy_items({"integration": {"backlog": 0}, "model": {"pending": 0}, "map_features": None}) == 0
    extra = {"integration": {"backlog": 2}, "model": {"pending": 3}, "map_features": {"pending": 1},
             "rendered_depth": {"pending": 0}, "other": {"pending": 9}}
    assert _busy_items(extra) == 6  # keys it does not know are not counted
    # a node that reports its own pending work is read from that (the model's window changes wait
    # for the next query: not background work)
    assert _busy_items({**extra, "pending": {"integration": 2, "map_features": 0, "evicted_views": 4}}) == 6
    assert _busy_items({**extra, "pending": {}}) == 0


def test_map_writer_is_a_package_module_run_from_anywhere(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The query_points phase's maps come from a module of the package (``python -m``), not from a
    script of the checkout: run from another directory, it writes maps the node's store loads."""
    import importlib.util

    from clients.cli.bench import MAP_WRITER, write_synthetic_maps
    from clients.harness import REPO_ROOT
    from mapper.bench.synthetic_maps import main as writer_main
    from mapper.node.store import MapStore

    spec = importlib.util.find_spec(MAP_WRITER)
    assert spec is not None and spec.origin is not None
    assert Path(spec.origin).is_relative_to(REPO_ROOT / "mapper")
    monkeypatch.chdir(tmp_path)
    write_synthetic_maps(tmp_path / "maps", [64])
    arrays, manifest = MapStore(tmp_path / "maps").load("points_64")
    assert manifest["global_map"]["points"] == 64 and arrays["global.xyz"].shape == (64, 3)
    assert arrays["global.feat"].shape == (64, manifest["ov_dim"])
    with pytest.raises(SystemExit) as exc:
        writer_main([str(tmp_path / "maps"), "0"])
    assert exc.value.code == 2 and "sizes must be >= 1" in capsys.readouterr().err
