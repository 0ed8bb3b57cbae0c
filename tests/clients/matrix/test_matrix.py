"""The scenario matrix's plumbing (``govnesf matrix``): the sample of the axes, the seed split,
what counts as pending background work, the summary's median/worst, and the quick subset end to
end through real nodes (that it runs and writes its outputs with the expected keys, not its numbers)."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from clients.matrix.driver import (
    RunSettings,
    asked_points,
    ground_truth_pool,
    methods_of,
    pending_work,
    psnr_db,
)
from clients.matrix.report import figures, summarise
from clients.matrix.scenarios import (
    EFFECTS,
    LAYOUTS,
    PATHS,
    POSE_ERRORS,
    build_matrix,
    quick_matrix,
    seeds_of,
    split_of,
)


def test_every_level_of_every_axis_appears_and_the_big_sensors_are_rare() -> None:
    scenarios = build_matrix("heldout", 12)
    axes = (("layout", LAYOUTS), ("path", PATHS), ("effect", EFFECTS), ("pose_error", POSE_ERRORS))
    for attr, levels in axes:
        counts = Counter(getattr(s, attr) for s in scenarios)
        assert set(counts) == set(levels) and min(counts.values()) >= 12 // len(levels)
    assert Counter(s.depth for s in scenarios) == {True: 6, False: 6}
    widths = Counter(s.width for s in scenarios)
    assert widths[640] == 1 and widths[320] == 2 and widths[160] == 9
    assert all(60 <= s.hfov_deg <= 90 for s in scenarios)
    assert [s.name for s in build_matrix("heldout", 12)] == [s.name for s in scenarios]  # deterministic


def test_seed_split_is_documented_rule_and_splits_do_not_overlap() -> None:
    held, tune = seeds_of("heldout", 20), seeds_of("tune", 20)
    assert all(s % 3 == 0 for s in held) and all(s % 3 for s in tune) and not set(held) & set(tune)
    assert {split_of(s.seed) for s in build_matrix("tune", 6)} == {"tune"}
    both = build_matrix("all", 3)
    assert [s.split for s in both] == ["heldout"] * 3 + ["tune"] * 3 and len({s.index for s in both}) == 6
    with pytest.raises(ValueError, match="unknown split"):
        seeds_of("train", 3)


def test_pending_work_reads_the_status_maps() -> None:
    extra = {"integration": {"backlog": 3}, "map_features": {"pending": 0},
             "triangulation": {"pending": 2}, "rendered_depth": "not a map", "model": {"pending": 9}}
    assert pending_work(extra) == {"integration": 3, "triangulation": 2}
    assert pending_work({}) == {}


def test_asked_points_top_up_small_classes_from_their_own_seen_samples() -> None:
    # 6 area-uniform points (class 0 x4, class 1 x1, class 2 x1 unseen), then extras of each class
    label = np.array([0, 0, 0, 0, 1, 2] + [0] * 3 + [1] * 4 + [2] * 4)
    seen = np.array([1, 1, 1, 0, 1, 0] + [1] * 3 + [1, 0, 1, 1] + [1, 1, 0, 0], bool)
    asked = asked_points(label, seen, n_uniform=6, min_class_points=3)
    assert asked[:6].tolist() == [True, True, True, False, True, False]  # uniform: exactly the seen ones
    assert not asked[6:9].any()  # class 0 already has 3 seen uniform points
    assert asked[9:13].tolist() == [True, False, True, False]  # class 1: 1 + the first 2 seen extras
    assert asked[13:].tolist() == [True, True, False, False]  # class 2: only what is seen, up to 3
    assert asked_points(label, seen, 6, 0).tolist() == asked[:6].tolist() + [False] * 11
    assert not (asked & ~seen).any()  # nothing unseen is ever asked


def test_ground_truth_pool_samples_each_class_on_its_own_surface() -> None:
    from clients.sim.scenes import LABEL_OF, generate_scene

    scene = generate_scene(5, "studio")
    xyz, label, n_uniform = ground_truth_pool(scene, RunSettings(gt_samples=300, min_class_points=5), seed=5)
    assert n_uniform == 300 and xyz.shape == (len(label), 3)
    classes = set(np.unique(scene.face_label).tolist()) - {LABEL_OF["ceiling"]}
    assert set(np.unique(label[n_uniform:]).tolist()) == classes
    assert np.all(np.bincount(label[n_uniform:])[sorted(classes)] == 20)  # 4 x min_class_points each
    assert LABEL_OF["ceiling"] not in label
    plain, plain_label, n = ground_truth_pool(scene, RunSettings(gt_samples=300, min_class_points=0), seed=5)
    assert n == len(plain) == 300
    assert np.array_equal(plain, xyz[:300]) and np.array_equal(plain_label, label[:300])


def test_methods_follow_the_depth_axis() -> None:
    with_depth, without = quick_matrix()
    assert [m[0] for m in methods_of(with_depth)] == ["govnesf", "average", "dgm", "average_depth"]
    assert [m[0] for m in methods_of(without)] == ["govnesf", "average", "dgm"]


def test_psnr_of_identical_and_offset_images() -> None:
    import numpy as np

    a = np.full((4, 4, 3), 100, np.uint8)
    mask = np.ones((4, 4), bool)
    assert psnr_db(a, a, mask) == float("inf")
    assert psnr_db(a + 1, a, mask) == pytest.approx(48.13, abs=0.01)


def _row(name: str, gov: float, avg: float) -> dict:
    node = {"settled": {"govnesf": gov, "average": avg}, "after_ack": {"govnesf": gov - 5, "average": avg},
            "settle_s": 3.0}
    return {"name": name, "window": {**node, "find_chair_m": 0.2, "objects_found_share": 2 / 3,
                                     "render_depth_rel_err": 0.1, "render_psnr_db": 20.0},
            "all": {**node, "settled": {"govnesf": gov + 2, "average": avg + 1}}}


def test_summary_reports_median_and_the_worst_scenario() -> None:
    rows = [_row("a", 40.0, 38.0), _row("b", 30.0, 35.0), _row("c", 50.0, 45.0)]
    f = figures(rows[1])
    assert f["govnesf - average (settled)"] == -5.0 and f["window - all (govnesf)"] == -2.0
    assert f["after ack - settled (govnesf)"] == -5.0 and f["dgm window settled"] is None
    s = {x["figure"]: x for x in summarise(rows)}
    assert s["govnesf window settled"]["median"] == 40.0
    gap = s["govnesf - average (settled)"]
    assert (gap["worst"], gap["worst_scenario"]) == (-5.0, "b")
    assert s["dgm window settled"]["n"] == 0


def test_quick_matrix_runs_end_to_end_and_writes_its_outputs(tmp_path: Path) -> None:
    from clients.cli import main

    out = tmp_path / "m"
    args = ["matrix", "--quick", "--gt-samples", "800", "--settle-timeout", "30", "--out", str(out)]
    assert main(args) == 0
    rows = [json.loads(line) for line in (out / "scenarios.jsonl").read_text().splitlines()]
    assert [r["name"] for r in rows] == [s.name for s in quick_matrix()]
    for r in rows:
        axes = {"layout", "path", "width", "effect", "pose_error", "ov_noise", "depth", "split", "wall_s"}
        assert axes <= set(r)
        for which in ("window", "all"):
            node = r[which]
            assert {"after_ack", "settled", "settle_s", "settled_ok", "stream_s", "keyframes"} <= set(node)
            names = [m[0] for m in methods_of(next(s for s in quick_matrix() if s.name == r["name"]))]
            assert set(node["after_ack"]) == set(node["settled"]) == set(names)
        once = {"render_depth_rel_err", "render_psnr_db", "objects_found_share", "objects_asked"}
        assert once <= set(r["window"])
    summary = json.loads((out / "summary.json").read_text())
    figs = {s["figure"] for s in summary["summary"]}
    assert {"govnesf - average (settled)", "window - all (average)", "after ack - settled (govnesf)",
            "settle s (window)", "render PSNR dB", "find chair m"} <= figs
    assert set(summary["scenarios"]) == {r["name"] for r in rows}
    md = (out / "summary.md").read_text()
    assert "| figure | scenarios | median | worst | worst scenario |" in md and rows[0]["name"] in md
    png = (out / "heatmap.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 1000
