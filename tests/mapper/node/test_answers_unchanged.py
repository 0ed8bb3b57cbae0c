"""Answers and renders of the node on a recorded stream equal those stored in
``tests/data/node_answers_golden.npz`` (made by the code before the node was split by request;
made again when the map began answering from the evicted views at a voxel)
(:mod:`tests.mapper.node.answers_golden` says how). Labels, sources and geometry exactly; scores
within 1e-4 (the text encoder's float32 sums differ in the last bits between runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.mapper.node.answers_golden import build_answers

GOLDEN = Path(__file__).resolve().parents[2] / "data" / "node_answers_golden.npz"


@pytest.mark.slow
def test_answers_and_renders_equal_the_stored_ones(tmp_path: Path) -> None:
    stored = np.load(GOLDEN)
    answers = build_answers(tmp_path)
    assert sorted(answers) == sorted(stored.files)
    for name in stored.files:
        want, got = stored[name], np.asarray(answers[name])
        assert got.shape == want.shape, name
        if name.endswith("_score"):
            np.testing.assert_allclose(got, want, atol=1e-4, err_msg=name)
        else:
            np.testing.assert_array_equal(got, want, err_msg=name)
