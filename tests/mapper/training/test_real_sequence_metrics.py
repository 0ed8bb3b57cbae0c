"""Novel-view render metrics (mapper.training.metrics, used by benchmarks/studies/real_sequence.py) on
exact small arrays: relative depth error with the masks of missing depth, coverage, pooling, PSNR."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapper.training.metrics import (
    DepthErrors,
    depth_errors,
    has_depth,
    masked_psnr,
    relative_depth_errors,
    summarize_depth_errors,
)

# reference: 6 pixels with a depth, 2 without (0 and NaN)
REF = np.array([[1.0, 2.0, 4.0, 0.0], [2.0, 1.0, np.nan, 5.0]], dtype=np.float32)
# prediction: misses (0, inf, -1) at three reference pixels, a depth where the reference has none
PRED = np.array([[1.5, 2.0, 0.0, 3.0], [np.inf, 0.875, 2.0, -1.0]], dtype=np.float32)
# compared pixels, row-major: (0,0) |1.5-1|/1 = 0.5, (0,1) 0, (1,1) |0.875-1|/1 = 0.125 (exact in float32)


def test_has_depth_excludes_zero_negative_and_non_finite() -> None:
    assert has_depth(REF).tolist() == [[True, True, True, False], [True, True, False, True]]
    assert has_depth(PRED).tolist() == [[True, True, False, True], [False, True, True, False]]


def test_relative_depth_errors_only_where_both_have_depth() -> None:
    rel, n_ref = relative_depth_errors(PRED, REF)
    assert rel.tolist() == [0.5, 0.0, 0.125]
    assert n_ref == 6


def test_depth_errors_by_hand() -> None:
    e = depth_errors(PRED, REF)
    assert e.num_compared == 3 and e.num_reference == 6
    assert e.median_rel == 0.125
    assert e.mean_rel == pytest.approx(0.625 / 3)
    assert e.coverage == 0.5
    assert e.within_10pct == pytest.approx(1 / 3)  # 0.0
    assert e.within_25pct == pytest.approx(2 / 3)  # 0.0 and 0.125


def test_relative_error_divides_by_the_reference_not_the_prediction() -> None:
    rel, _ = relative_depth_errors(np.array([[3.0, 1.0]]), np.array([[2.0, 2.0]]))
    np.testing.assert_allclose(rel, [0.5, 0.5])


def test_perfect_prediction_and_empty_cases() -> None:
    e = depth_errors(REF, REF)
    assert e.median_rel == 0.0 and e.mean_rel == 0.0 and e.coverage == 1.0 and e.within_10pct == 1.0
    none = depth_errors(np.zeros((2, 4)), REF)  # nothing rendered: coverage 0, errors undefined
    assert none.coverage == 0.0 and none.num_compared == 0 and none.num_reference == 6
    assert math.isnan(none.median_rel) and math.isnan(none.mean_rel) and math.isnan(none.within_25pct)
    blank = depth_errors(np.ones((2, 2)), np.zeros((2, 2)))  # no reference depth at all
    assert math.isnan(blank.coverage) and blank.num_reference == 0


def test_pooling_concatenates_pixels() -> None:
    rel_a, n_a = relative_depth_errors(PRED, REF)  # [0.5, 0, 0.125] of 6
    rel_b, n_b = relative_depth_errors(np.array([[1.2, 0.0]]), np.array([[1.0, 1.0]]))  # [0.2] of 2
    pooled = summarize_depth_errors(np.concatenate([rel_a, rel_b]), n_a + n_b)
    assert isinstance(pooled, DepthErrors)
    assert pooled.num_compared == 4 and pooled.num_reference == 8 and pooled.coverage == 0.5
    assert pooled.median_rel == pytest.approx(0.1625)  # median of 0, 0.125, 0.2, 0.5
    assert pooled.mean_rel == pytest.approx(0.825 / 4)
    with pytest.raises(ValueError, match="reference pixels"):
        summarize_depth_errors(np.zeros(3), 2)


def test_depth_shape_mismatch_is_refused() -> None:
    with pytest.raises(ValueError, match="shape"):
        relative_depth_errors(np.zeros((2, 3)), np.zeros((3, 2)))


def test_psnr_by_hand() -> None:
    target = np.zeros((2, 2, 3), dtype=np.uint8)
    pred = target.copy()
    pred[0, 0] = 255  # one pixel of four off by the peak in all channels: MSE = 255^2 / 4
    assert masked_psnr(pred, target, max_value=255.0) == pytest.approx(10 * math.log10(4))
    # the same in [0, 1] units
    assert masked_psnr(pred / 255.0, target / 255.0) == pytest.approx(10 * math.log10(4))
    # MSE 0.01 -> 20 dB
    assert masked_psnr(np.full((3, 3), 0.1), np.zeros((3, 3))) == pytest.approx(20.0)


def test_psnr_with_a_mask() -> None:
    target = np.zeros((2, 2, 3))
    pred = np.zeros((2, 2, 3))
    pred[0, 0] = 1.0
    pred[1, 1] = 0.1
    mask = np.array([[False, True], [False, True]])  # (0, 1) exact, (1, 1) off by 0.1: MSE 0.005
    assert masked_psnr(pred, target, mask) == pytest.approx(10 * math.log10(1 / 0.005))
    assert masked_psnr(pred, target, np.array([[False, True], [False, False]])) == math.inf
    assert math.isnan(masked_psnr(pred, target, np.zeros((2, 2), dtype=bool)))


def test_psnr_refuses_bad_shapes_and_peak() -> None:
    with pytest.raises(ValueError, match="same"):
        masked_psnr(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="mask"):
        masked_psnr(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), np.ones((2, 2, 3), dtype=bool))
    with pytest.raises(ValueError, match="max_value"):
        masked_psnr(np.zeros((2, 2)), np.zeros((2, 2)), max_value=0.0)
