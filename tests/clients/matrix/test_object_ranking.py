"""``benchmarks/studies/object_ranking.py``: how its tally counts the objects found."""

from __future__ import annotations

from benchmarks.studies.object_ranking import tally


def test_tally_counts_found_objects_by_depth_and_chair() -> None:
    rows = [
        (True, {"off": {"chair": 0.2, "bed": 0.5}, "on": {"chair": 0.2, "bed": 0.3}}),
        (False, {"off": {"chair": None, "desk": 0.1}, "on": {"chair": 0.35, "desk": 2.0}}),
    ]
    got = tally(rows)
    assert got["off"] == {"chair d": [1, 1], "chair rgb": [0, 1], "all d": [1, 2], "all rgb": [1, 2]}
    # 0.35 m is within the matrix's radius; 2 m is not
    assert got["on"] == {"chair d": [1, 1], "chair rgb": [1, 1], "all d": [2, 2], "all rgb": [1, 2]}
