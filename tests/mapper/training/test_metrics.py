"""Segmentation metrics against hand-computed confusion matrices."""

import numpy as np
import pytest
import torch

from mapper.training.metrics import (
    average_over_scenes,
    confusion_matrix,
    predict_labels,
    scores_from_labels,
    segmentation_scores,
)


def test_confusion_matrix_by_hand_ignores_other_labels():
    gt = np.array([0, 0, 0, 1, 1, 2, -1, 20, 25])
    pred = np.array([0, 0, 1, 1, 2, 2, 1, 0, 3])
    cm = confusion_matrix(gt, pred, num_classes=3)
    # rows = gt, cols = pred; the last three points (labels -1, 20, 25) are ignored.
    assert cm.tolist() == [[2, 1, 0], [0, 1, 1], [0, 0, 1]]


def test_scores_by_hand():
    cm = np.array([[2, 1, 0], [0, 1, 1], [0, 0, 1]])
    s = segmentation_scores(cm)
    # IoU: c0 2/(3+2-2)=2/3, c1 1/(2+2-1)=1/3, c2 1/(1+2-1)=1/2
    np.testing.assert_allclose(s.iou, [2 / 3, 1 / 3, 1 / 2])
    np.testing.assert_allclose(s.acc, [2 / 3, 1 / 2, 1.0])
    assert s.miou == pytest.approx((2 / 3 + 1 / 3 + 1 / 2) / 3)
    assert s.macc == pytest.approx((2 / 3 + 1 / 2 + 1) / 3)
    assert s.oacc == pytest.approx(4 / 6)
    assert s.num_valid == 6


def test_miou_only_over_classes_present_in_ground_truth():
    # Class 2 is absent from gt but predicted once: it does not enter the mean, yet its false
    # positive lowers class 1's accuracy and IoU.
    gt = np.array([0, 0, 1, 1])
    pred = np.array([0, 0, 1, 2])
    s = scores_from_labels(gt, pred, num_classes=4)
    assert np.isnan(s.iou[2]) and np.isnan(s.iou[3])
    assert s.iou[0] == 1.0 and s.iou[1] == 0.5
    assert s.miou == pytest.approx(0.75)
    assert s.macc == pytest.approx(0.75)
    assert s.oacc == pytest.approx(0.75)


def test_average_over_scenes_is_the_mean_of_scene_scores():
    a = scores_from_labels(np.array([0, 0, 1, 1]), np.array([0, 0, 1, 1]), 2)  # perfect
    b = scores_from_labels(np.array([0, 0]), np.array([0, 1]), 2)  # class 0 only: IoU 1/2
    empty = scores_from_labels(np.array([-1]), np.array([0]), 2)
    avg = average_over_scenes([a, b, empty])
    assert avg.miou == pytest.approx((1.0 + 0.5) / 2)
    assert avg.oacc == pytest.approx((1.0 + 0.5) / 2)
    np.testing.assert_allclose(avg.iou, [0.75, 1.0])  # class 1 is present in scene a only
    with pytest.raises(ValueError, match="no scene"):
        average_over_scenes([empty])


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="outside 0..1"):
        confusion_matrix(np.array([0, 1]), np.array([0, 5]), num_classes=2)
    with pytest.raises(ValueError, match="2 labels but pred has 3"):
        confusion_matrix(np.array([0, 1]), np.array([0, 1, 1]), num_classes=2)


def test_predict_labels_argmax_cosine_numpy_and_torch():
    text = np.array([[1.0, 0.0], [0.0, 1.0], [0.7, 0.7]], np.float32)
    # Scaled text rows must not change the answer: cosine, not dot product.
    text_scaled = text * np.array([[10.0], [1.0], [1.0]], np.float32)
    feats = np.array([[0.9, 0.1], [0.1, 0.9], [0.5, 0.52], [-1.0, 0.0]], np.float32)
    expected = [0, 1, 2, 1]  # [-1, 0]: cosines -1, 0, -0.707 -> class 1
    assert predict_labels(feats, text_scaled, chunk=2).tolist() == expected
    out = predict_labels(torch.from_numpy(feats), torch.from_numpy(text))
    assert isinstance(out, torch.Tensor) and out.tolist() == expected
    with pytest.raises(ValueError, match="share D"):
        predict_labels(feats, np.ones((3, 5), np.float32))
