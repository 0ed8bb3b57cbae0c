"""check_shape: the one shape-check vocabulary (mapper/checks.py)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from mapper import checks
from mapper.checks import ShapeError, check_shape, format_spec

ARRAYS = [pytest.param(np.zeros, id="numpy"), pytest.param(torch.zeros, id="torch")]


@pytest.mark.parametrize("zeros", ARRAYS)
@pytest.mark.parametrize(
    ("shape", "spec", "bound"),
    [
        ((5, 3), "N 3", {"N": 5}),
        ((0, 3), "N 3", {"N": 0}),
        ((4,), "4", {}),
        ((4, 4), "4 4", {}),
        ((2, 3, 8, 6), "N 3 H W", {"N": 2, "H": 8, "W": 6}),
        ((6, 6), "C C", {"C": 6}),
        ((), "", {}),
        ((4, 4), "* 4 4", {}),
        ((2, 7, 4, 4), "* 4 4", {}),
        ((9, 2), "* N 2", {"N": 9}),
        ((3,), "3|4", {}),
        ((4,), "3|4", {}),
    ],
)
def test_matching_shapes_pass_and_return_the_bound_sizes(zeros, shape, spec, bound) -> None:  # noqa: ANN001
    assert check_shape(zeros(shape), spec, "x") == bound


@pytest.mark.parametrize("zeros", ARRAYS)
@pytest.mark.parametrize(
    ("shape", "spec", "message"),
    [
        ((5, 4), "N 3", "points: expected shape (N, 3), got (5, 4)"),  # wrong size
        ((5,), "N 3", "points: expected shape (N, 3), got (5,)"),  # too few dims
        ((2, 5, 3), "N 3", "points: expected shape (N, 3), got (2, 5, 3)"),  # too many dims
        ((), "4", "points: expected shape (4,), got ()"),  # a single dim keeps its comma
        ((3, 3), "* 4 4", "points: expected shape (..., 4, 4), got (3, 3)"),  # '*' written as '...'
        ((4,), "* 4 4", "points: expected shape (..., 4, 4), got (4,)"),  # '*' needs the fixed dims
        ((5,), "3|4", "points: expected shape (3|4,), got (5,)"),
        ((3, 4), "C C", "points: expected shape (C, C) with C = 3, got (3, 4)"),  # one name, one size
    ],
)
def test_wrong_rank_or_size_fails_with_one_wording(zeros, shape, spec, message) -> None:  # noqa: ANN001
    with pytest.raises(ShapeError, match=f"^{re.escape(message)}$"):
        check_shape(zeros(shape), spec, "points")


def test_shape_error_is_a_value_error() -> None:
    assert issubclass(ShapeError, ValueError)
    with pytest.raises(ValueError, match="rgb: expected shape"):
        check_shape(np.zeros((2, 2)), "H W 3", "rgb")


def test_named_dims_bind_across_calls_that_share_a_dict() -> None:
    dims = check_shape(np.zeros((5, 3)), "N 3", "points")
    assert check_shape(torch.zeros(5), "N", "weights", dims) is dims  # the same dict, extended
    check_shape(np.zeros((5, 8)), "N D", "features", dims)
    assert dims == {"N": 5, "D": 8}
    with pytest.raises(ShapeError, match=re.escape("weights: expected shape (N,) with N = 5, got (6,)")):
        check_shape(np.zeros(6), "N", "weights", dims)
    with pytest.raises(ShapeError, match=re.escape("text: expected shape (C, D) with D = 8, got (3, 7)")):
        check_shape(torch.zeros(3, 7), "C D", "text", dims)
    assert dims == {"N": 5, "D": 8}  # a failed check binds nothing
    # without a shared dict the calls are independent
    check_shape(np.zeros((5, 3)), "N 3", "points")
    check_shape(np.zeros(6), "N", "weights")


def test_caller_fixed_dims_and_a_partial_failure_bind_nothing() -> None:
    dims = {"C": 2}
    message = "features: expected shape (C, h, w) with C = 2, got (3, 4, 5)"
    with pytest.raises(ShapeError, match=re.escape(message)):
        check_shape(np.zeros((3, 4, 5)), "C h w", "features", dims)
    with pytest.raises(ShapeError):
        check_shape(np.zeros((2, 4, 5, 1)), "C h w", "features", dims)
    assert dims == {"C": 2}
    assert check_shape(np.zeros((2, 4, 5)), "C h w", "features", dims) == {"C": 2, "h": 4, "w": 5}


def test_star_matches_any_number_of_leading_dims() -> None:
    for lead in [(), (1,), (2, 3), (1, 1, 1, 1)]:
        dims = check_shape(torch.zeros(*lead, 7, 3), "* N 3", "points")
        assert dims == {"N": 7}
    with pytest.raises(ValueError, match="'\\*' may only come first"):
        check_shape(np.zeros((2, 3)), "N *", "points")


def test_alternatives_accept_either_number() -> None:
    for n in (3, 4):
        check_shape(np.zeros((2, n)), "N 3|4", "rgb_or_rgba")
    with pytest.raises(ShapeError, match=re.escape("expected shape (N, 3|4), got (2, 5)")):
        check_shape(np.zeros((2, 5)), "N 3|4", "rgb_or_rgba")


def test_works_on_anything_with_a_shape_and_on_torch_sizes() -> None:
    class Shaped:
        shape = (2, 3)

    assert check_shape(Shaped(), "A B", "thing") == {"A": 2, "B": 3}
    t = torch.zeros(2, 3, dtype=torch.float16, device="meta")  # no data needed
    assert check_shape(t, "A B", "meta tensor") == {"A": 2, "B": 3}
    with pytest.raises(ShapeError, match=re.escape("got (2, 3)")):  # plain ints, not torch.Size
        check_shape(t, "A B C", "meta tensor")


def test_format_spec() -> None:
    assert format_spec(["N", "3"]) == "(N, 3)"
    assert format_spec(["4"]) == "(4,)"
    assert format_spec(["*", "4", "4"]) == "(..., 4, 4)"
    assert format_spec([]) == "()"


def test_checks_can_be_switched_off(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(checks, "CHECKS_ENABLED", False)
    dims = {"N": 1}
    assert check_shape(np.zeros((5, 4)), "N 3", "points", dims) is dims and dims == {"N": 1}
