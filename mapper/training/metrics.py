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

from mapper.checks import check_shape

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
    check_shape(cm, "C C", "confusion matrix")
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
    dims = check_shape(f, "N D", "features")
    check_shape(t, "C D", "text_emb (must share D with features)", dims)
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


# ---- novel-view render metrics (rgb and depth against a real frame) ----------------------------
# Used by benchmarks/studies/real_sequence.py. A depth of 0 or a non-finite value means "no depth" on
# either side (the runtime renders 0 where the opacity stays below ``min_opacity``; sensors write 0
# where they measured nothing).


@dataclass(frozen=True)
class DepthErrors:
    """Relative depth error of a predicted depth map against a reference depth map."""

    median_rel: float
    """Median of |pred - ref| / ref over the compared pixels (NaN if none)."""
    mean_rel: float
    """Mean of |pred - ref| / ref over the compared pixels (NaN if none)."""
    within_10pct: float
    """Fraction of the compared pixels with a relative error <= 0.10 (NaN if none)."""
    within_25pct: float
    """Fraction of the compared pixels with a relative error <= 0.25 (NaN if none)."""
    coverage: float
    """Compared pixels / pixels with a reference depth: how much of the measured scene got a
    predicted depth (NaN if the reference has no depth)."""
    num_compared: int
    """Pixels where both maps have a depth."""
    num_reference: int
    """Pixels where the reference has a depth."""


def has_depth(depth_m: np.ndarray) -> np.ndarray:
    """Boolean mask of the pixels carrying a depth: finite and > 0.

    >>> has_depth(np.array([0.0, 1.5, np.nan, -1.0, np.inf])).tolist()
    [False, True, False, False, False]
    """
    depth_m = np.asarray(depth_m)
    return np.isfinite(depth_m) & (depth_m > 0)


def relative_depth_errors(pred_m: np.ndarray, ref_m: np.ndarray) -> tuple[np.ndarray, int]:
    """|pred - ref| / ref at the pixels where both maps have a depth (:func:`has_depth`).

    Args:
        pred_m: (H, W) predicted depth (metres), 0 / non-finite = none.
        ref_m: (H, W) reference depth (metres), same shape, 0 / non-finite = none.

    Returns:
        ((N,) float64 relative errors in row-major pixel order, number of pixels with a reference
        depth). N / that number is the coverage.

    >>> pred = np.array([[1.1, 0.0], [2.0, 3.0]])
    >>> ref = np.array([[1.0, 2.0], [0.0, 2.0]])
    >>> rel, n_ref = relative_depth_errors(pred, ref)
    >>> rel.round(6).tolist(), n_ref
    ([0.1, 0.5], 3)
    """
    pred = np.asarray(pred_m, dtype=np.float64)
    ref = np.asarray(ref_m, dtype=np.float64)
    if pred.shape != ref.shape:
        raise ValueError(f"predicted depth has shape {pred.shape} but the reference {ref.shape}")
    ref_ok = has_depth(ref)
    both = ref_ok & has_depth(pred)
    return np.abs(pred[both] - ref[both]) / ref[both], int(ref_ok.sum())


def summarize_depth_errors(rel: np.ndarray, num_reference: int) -> DepthErrors:
    """:class:`DepthErrors` of (N,) relative errors from ``num_reference`` reference pixels.

    Pool several images by concatenating their errors and adding their reference counts.
    """
    rel = np.asarray(rel, dtype=np.float64).reshape(-1)
    if num_reference < rel.size:
        raise ValueError(f"{rel.size} compared pixels but only {num_reference} reference pixels")
    nan = float("nan")
    if rel.size == 0:
        return DepthErrors(nan, nan, nan, nan, 0.0 if num_reference else nan, 0, int(num_reference))
    return DepthErrors(
        median_rel=float(np.median(rel)),
        mean_rel=float(rel.mean()),
        within_10pct=float((rel <= 0.10).mean()),
        within_25pct=float((rel <= 0.25).mean()),
        coverage=float(rel.size / num_reference),
        num_compared=int(rel.size),
        num_reference=int(num_reference),
    )


def depth_errors(pred_m: np.ndarray, ref_m: np.ndarray) -> DepthErrors:
    """:class:`DepthErrors` of a (H, W) predicted depth against a (H, W) reference depth."""
    return summarize_depth_errors(*relative_depth_errors(pred_m, ref_m))


def masked_psnr(
    pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None, *, max_value: float = 1.0
) -> float:
    """PSNR (dB) = 10 log10(max_value^2 / MSE), the MSE over the pixels of ``mask`` (all channels).

    Args:
        pred: (H, W) or (H, W, C) image.
        target: same shape as ``pred``, same units.
        mask: (H, W) bool, the pixels to compare; None = all.
        max_value: peak value of the images (1.0 for [0, 1], 255.0 for uint8).

    Returns:
        inf for identical pixels, NaN for an empty mask.

    >>> masked_psnr(np.array([[0.0, 0.5]]), np.array([[0.0, 0.0]]))  # MSE 0.125 -> 10 log10(8)
    9.030899869919436
    """
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    if p.shape != t.shape or p.ndim not in (2, 3):
        raise ValueError(f"pred {p.shape} and target {t.shape} must be the same (H, W) or (H, W, C) shape")
    if max_value <= 0:
        raise ValueError(f"max_value must be > 0, got {max_value}")
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != p.shape[:2]:
            raise ValueError(f"mask has shape {m.shape}, expected the image's (H, W) = {p.shape[:2]}")
        p, t = p[m], t[m]
    if p.size == 0:
        return float("nan")
    mse = float(np.mean((p - t) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(max_value**2 / mse))
