"""``benchmarks/studies/evicted_evidence.py``: labels only where seen, and bad arguments refused
before anything streams."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.studies.evicted_evidence import _labels, main


def test_labels_are_the_best_text_where_seen() -> None:
    cos = np.array([[0.1, 0.9], [0.8, 0.2], [0.5, 0.6]], np.float32)
    assert _labels(cos, np.array([True, True, False])).tolist() == [1, 0, -1]
    assert _labels(np.zeros((2, 0), np.float32), np.array([True, True])).tolist() == [-1, -1]


@pytest.mark.parametrize("argv,words", [(["--set", "novalue"], "KEY=VALUE"), (["--set", "=1"], "KEY=VALUE"),
                                        (["--index", "99"], "scenarios")])
def test_bad_arguments_are_refused(argv: list[str], words: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(argv)
    assert words in capsys.readouterr().err
