"""Semantic segmentation metrics, as in the official ScanNet / GOV-NeSF evaluation.

* Classes: the 20 ScanNet benchmark classes (label ids 0..19); every other label (ceiling,
  extras, -1 = none) is ignored.
* Per scene: a confusion matrix over the valid points (or pixels); IoU per class
  TP / (TP + FP + FN), accuracy per class TP / (TP + FN); mIoU and mAcc average over the classes
  PRESENT in the scene's ground truth; oAcc = sum TP / number of valid points.
* Over scenes: the per-scene numbers are averaged (``average_over_scenes``).

Example:
    >>> import numpy as np
    >>> cm = confusion_matrix(np.array([0, 0, 1, 5]), np.array([0, 1, 1, 1]), num_classes=2)
    >>> cm.tolist()
    [[1, 1], [0, 1]]
    >>> round(segmentation_scores(cm).miou, 4)
    0.5
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

NUM_SCANNET_CLASSES = 20
"""Number of ScanNet benchmark classes; label ids 0..19."""


@dataclass(frozen=True)
class SegmentationScores:
    """Scores of one scene (or of an average over scenes)."""

    miou: float
    """Mean IoU over the classes present in the ground truth (NaN if none)."""
    macc: float
    """Mean per-class accuracy (recall) over the present classes (NaN if none)."""
    oacc: float
    """Overall accuracy over the valid points (NaN if none)."""
    iou: np.ndarray
    """(num_classes,) IoU per class, NaN for classes absent from the ground truth."""
    acc: np.ndarray
    """(num_classes,) accuracy per class, NaN for classes absent from the ground truth."""
    num_valid: int
    """Number of points with a ground-truth label in 0..num_classes-1."""


def confusion_matrix(gt: np.ndarray, pred: np.ndarray, num_classes: int = NUM_SCANNET_CLASSES) -> np.ndarray:
    """Confusion matrix, rows = ground truth, columns = prediction.

    Args:
        gt: (N,) int ground-truth labels; labels outside 0..num_classes-1 are ignored.
        pred: (N,) int predicted labels in 0..num_classes-1 (only checked at valid points).
        num_classes: number of evaluated classes (20).

    Returns:
        (num_classes, num_classes) int64.
    """
    gt = np.asarray(gt).reshape(-1)
    pred = np.asarray(pred).reshape(-1)
    if gt.shape != pred.shape:
        raise ValueError(f"gt has {gt.size} labels but pred has {pred.size}")
    if num_classes < 1:
        raise ValueError(f"num_classes {num_classes} must be >= 1")
    valid = (gt >= 0) & (gt < num_classes)
    g = gt[valid].astype(np.int64)
    p = pred[valid].astype(np.int64)
    bad = (p < 0) | (p >= num_classes)
    if bad.any():
        raise ValueError(
            f"pred has labels {np.unique(p[bad])[:5].tolist()} outside 0..{num_classes - 1} at "
            "evaluated points; predict among the evaluated classes only"
        )
    cm = np.bincount(g * num_classes + p, minlength=num_classes * num_classes)
    return cm.reshape(num_classes, num_classes).astype(np.int64)


def segmentation_scores(cm: np.ndarray) -> SegmentationScores:
    """mIoU / mAcc / oAcc of a (C, C) confusion matrix (rows = ground truth) over present classes."""
    cm = np.asarray(cm, dtype=np.float64)
    if cm.ndim != 2 or cm.shape[0] != cm.shape[1]:
        raise ValueError(f"confusion matrix must be square (C, C), got shape {cm.shape}")
    return _scores(cm, cm.sum(axis=1))


def _scores(cm: np.ndarray, gt_count: np.ndarray) -> SegmentationScores:
    tp = np.diag(cm)
    pred_count = cm.sum(axis=0)
    present = gt_count > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(present, tp / (gt_count + pred_count - tp), np.nan)
        acc = np.where(present, tp / gt_count, np.nan)
    total = gt_count.sum()
    return SegmentationScores(
        miou=float(np.nanmean(iou)) if present.any() else float("nan"),
        macc=float(np.nanmean(acc)) if present.any() else float("nan"),
        oacc=float(tp.sum() / total) if total > 0 else float("nan"),
        iou=iou,
        acc=acc,
        num_valid=int(total),
    )


def scores_from_labels(gt: np.ndarray, pred: np.ndarray,
                       num_classes: int = NUM_SCANNET_CLASSES) -> SegmentationScores:
    """Scores of one scene straight from (N,) ground-truth and (N,) predicted labels."""
    return segmentation_scores(confusion_matrix(gt, pred, num_classes))


def average_over_scenes(scores: Iterable[SegmentationScores]) -> SegmentationScores:
    """Mean of per-scene scores (scenes without valid points are skipped).

    ``iou`` / ``acc`` per class average over the scenes where the class is present.
    """
    items = [s for s in scores if s.num_valid > 0]
    if not items:
        raise ValueError("no scene with valid points to average")
    with np.errstate(invalid="ignore"), _quiet_nanmean():
        iou = np.nanmean(np.stack([s.iou for s in items]), axis=0)
        acc = np.nanmean(np.stack([s.acc for s in items]), axis=0)
    return SegmentationScores(
        miou=float(np.mean([s.miou for s in items])),
        macc=float(np.mean([s.macc for s in items])),
        oacc=float(np.mean([s.oacc for s in items])),
        iou=iou,
        acc=acc,
        num_valid=int(sum(s.num_valid for s in items)),
    )


class _quiet_nanmean:
    """Silence numpy's 'Mean of empty slice' warning for all-NaN columns (absent classes)."""

    def __enter__(self):
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore", category=RuntimeWarning)

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


def predict_labels(features: np.ndarray | torch.Tensor, text_emb: np.ndarray | torch.Tensor,
                   chunk: int = 65536) -> np.ndarray | torch.Tensor:
    """Label of each feature: argmax cosine similarity against class text embeddings.

    Args:
        features: (N, D) features (any norm; zero rows get label 0 by convention).
        text_emb: (C, D) class text embeddings (any norm).
        chunk: rows per matrix product (bounds memory).

    Returns:
        (N,) int64 class indices; a numpy array for numpy input, a tensor for tensor input.
    """
    is_numpy = not isinstance(features, torch.Tensor)
    f = torch.as_tensor(np.asarray(features) if is_numpy else features)
    t = torch.as_tensor(text_emb).to(device=f.device)
    if f.ndim != 2 or t.ndim != 2 or f.shape[1] != t.shape[1]:
        raise ValueError(f"features (N, D) and text_emb (C, D) must share D, got {tuple(f.shape)} "
                         f"and {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise ValueError("text_emb has no classes")
    t = t.float()
    t = t / t.norm(dim=1, keepdim=True).clamp_min(1e-12)
    out = torch.empty(f.shape[0], dtype=torch.int64, device=f.device)
    for start in range(0, f.shape[0], chunk):
        part = f[start:start + chunk].float()
        # Row norms do not change the argmax of a row; only the text side needs normalising.
        out[start:start + chunk] = (part @ t.T).argmax(dim=1)
    return out.numpy() if is_numpy else out


def format_scores_table(rows: Sequence[tuple[str, SegmentationScores]],
                        class_names: Sequence[str] | None = None, per_class: bool = False) -> str:
    """Markdown table: one row per (name, scores), mIoU / mAcc / oAcc in percent (and per-class IoU)."""
    header = ["method", "mIoU", "mAcc", "oAcc"]
    if per_class and class_names is not None:
        header += list(class_names)
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, s in rows:
        cells = [name, f"{100 * s.miou:.1f}", f"{100 * s.macc:.1f}", f"{100 * s.oacc:.1f}"]
        if per_class and class_names is not None:
            cells += ["-" if np.isnan(v) else f"{100 * v:.1f}" for v in s.iou[: len(class_names)]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
