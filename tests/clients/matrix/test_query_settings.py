"""``benchmarks/studies/query_settings.py``: its variants are checked against the ``[queries]``
settings before anything streams, and its summary compares each variant with the first."""

from __future__ import annotations

import pytest

from benchmarks.studies.query_settings import parse_variants, summary


def test_variants_name_queries_settings_only() -> None:
    want = {"off": {"learned_evicted_views": 0.0}}
    assert parse_variants('{"off": {"learned_evicted_views": 0.0}}') == want
    for bad, words in (("{not json", "not JSON"), ("[1]", "object of objects"), ("{}", "object of objects"),
                       ('{"a": {"window_size": 3}}', "window_size not a [queries] setting"),
                       ('{"a": {"map_blend": 5.0}}', "map_blend")):
        with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
            parse_variants(bad)


def test_summary_compares_with_the_first_variant() -> None:
    results = {
        "s-d": {"base": {"average": 30.0, "govnesf": 31.0, "average_depth": 32.0, "dgm": 33.0},
                "on": {"average": 30.0, "govnesf": 33.0, "average_depth": 32.0, "dgm": 35.0}},
        "s-rgb": {"base": {"average": 20.0, "govnesf": 18.0, "average_depth": 25.0, "dgm": 19.0},
                  "on": {"average": 20.0, "govnesf": 19.0, "average_depth": 25.0, "dgm": 19.5}},
    }
    lines = summary(results, {"s-d": True, "s-rgb": False})
    assert lines[0].startswith("base: govnesf - average median -0.50 worst -2.00")
    assert "dgm - average_depth median +1.00 worst +1.00" in lines[0]  # streams with depth only
    assert "govnesf vs base median +1.50 worst +1.00" in lines[1]
    assert "vs base" not in lines[0]
