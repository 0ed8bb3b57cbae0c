"""The docstring examples in `protocol/` run, and the docs state the limits the code enforces."""

from __future__ import annotations

import doctest
from pathlib import Path

import numpy as np
import pytest

import protocol.messages
import protocol.recording
from protocol.messages import LAST_ROW_TOL, MAX_IMAGE_SIDE, MAX_TEXTS, ORTHONORMAL_TOL, Frame, encode

DOCS = Path(__file__).resolve().parents[2] / "docs"


@pytest.mark.parametrize("module", [protocol.messages, protocol.recording], ids=lambda m: m.__name__)
def test_docstring_examples(module: object) -> None:
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)  # type: ignore[arg-type]
    assert result.attempted > 0 and result.failed == 0


def test_protocol_doc_states_the_enforced_limits() -> None:
    text = (DOCS / "reference" / "protocol.md").read_text()
    assert ORTHONORMAL_TOL == 1e-3 and "ORTHONORMAL_TOL = 1e-3" in text
    assert LAST_ROW_TOL == 1e-6 and "LAST_ROW_TOL = 1e-6" in text
    assert f"1..{MAX_IMAGE_SIDE}" in text and f"1..{MAX_TEXTS}" in text


def test_conventions_example_pose_is_valid_and_means_what_it_says() -> None:
    world_from_cam = np.array([[0, 0, 1, 1], [-1, 0, 0, 2], [0, -1, 0, 1.5], [0, 0, 0, 1]], float)
    assert "[ 0, -1, 0, 1.5]" in (DOCS / "concepts" / "conventions.md").read_text()
    encode(Frame(0, 0, 2, 2, np.ones(4), world_from_cam, np.zeros((2, 2, 3), np.uint8)))  # valid
    forward_cam = np.array([0.0, 0.0, 1.0, 0.0])  # camera +z as a direction
    down_cam = np.array([0.0, 1.0, 0.0, 0.0])
    assert np.allclose(world_from_cam @ forward_cam, [1, 0, 0, 0])  # looks along world +x
    assert np.allclose(world_from_cam @ down_cam, [0, 0, -1, 0])  # image down is world -z
    assert np.allclose(world_from_cam @ np.array([0.0, 0.0, 0.0, 1.0]), [1, 2, 1.5, 1])  # centre


def test_repr_summarises_arrays() -> None:
    msg = Frame(0, 0, 64, 48, np.ones(4), np.eye(4), np.zeros((48, 64, 3), np.uint8))
    text = repr(msg)
    assert "rgb=<uint8 (48, 64, 3)>" in text and len(text) < 400
