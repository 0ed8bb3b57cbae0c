"""Training loss: colour MSE + alpha * (1 - cos(S_hat, S)).

The OV term must not train the density: ``render_rays`` composites OV features with detached
weights, so this loss only reaches the blending network through the OV branch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.checks import check_shape

__all__ = [
    "LossOutputs", "color_loss", "distortion_loss", "govnesf_loss", "ov_cosine_loss"]


@dataclass
class LossOutputs:
    total: Tensor
    """() weighted sum, what to back-propagate."""
    color: Tensor
    """() colour MSE."""
    ov: Tensor
    """() mean (1 - cosine similarity) of the OV features."""


def _masked_mean(values: Tensor, mask: Tensor | None) -> Tensor:
    if mask is None:
        return values.mean()
    m = mask.to(values.dtype)
    return (values * m).sum() / m.sum().clamp_min(1.0)


def color_loss(pred_rgb: Tensor, target_rgb: Tensor, mask: Tensor | None = None) -> Tensor:
    """(R, 3), (R, 3), optional (R,) bool -> () mean squared error over the kept rays."""
    dims = check_shape(pred_rgb, "R 3", "pred_rgb")
    check_shape(target_rgb, "R 3", "target_rgb", dims)
    if mask is not None:
        check_shape(mask, "R", "mask", dims)
    per_ray = ((pred_rgb.float() - target_rgb.float()) ** 2).mean(dim=-1)
    return _masked_mean(per_ray, mask)


def ov_cosine_loss(pred_ov: Tensor, target_ov: Tensor, mask: Tensor | None = None) -> Tensor:
    """(R, D), (R, D), optional (R,) bool -> () mean of 1 - cos over the kept rays.

    Zero vectors give cos = 0 (loss 1) with finite gradients (eps in the norm).
    """
    dims = check_shape(pred_ov, "R D", "pred_ov")
    check_shape(target_ov, "R D", "target_ov", dims)
    if mask is not None:
        check_shape(mask, "R", "mask", dims)
    cos = F.cosine_similarity(pred_ov.float(), target_ov.float(), dim=-1, eps=1e-8)
    return _masked_mean(1.0 - cos, mask)


def govnesf_loss(
    pred_rgb: Tensor,
    target_rgb: Tensor,
    pred_ov: Tensor,
    target_ov: Tensor,
    *,
    ov_weight: float = 1.0,
    ov_mask: Tensor | None = None,
    rgb_mask: Tensor | None = None,
) -> LossOutputs:
    """Colour MSE + ov_weight * (1 - cos).

    Args:
        pred_rgb, target_rgb: (R, 3); pred_ov, target_ov: (R, D).
        ov_weight: alpha >= 0.
        ov_mask, rgb_mask: optional (R,) bool rays to keep (e.g. rays with a valid target).
    """
    if ov_weight < 0:
        raise ValueError(f"ov_weight {ov_weight} out of range: must be >= 0")
    color = color_loss(pred_rgb, target_rgb, rgb_mask)
    ov = ov_cosine_loss(pred_ov, target_ov, ov_mask)
    return LossOutputs(total=color + ov_weight * ov, color=color, ov=ov)


def distortion_loss(weights: Tensor, t: Tensor) -> Tensor:
    """mip-NeRF 360's distortion loss, mean over rays: small when each ray's weight sits in one
    short interval (a sharp surface), large when it is spread along the ray.

    ``sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 d_i`` with ``s`` the sample distances rescaled
    to [0, 1] per ray (first to last sample) and ``d`` their spacing.

    Args:
        weights: (R, S) rendering weights; t: (R, S) sample distances along each ray (increasing).
    """
    dims = check_shape(weights, "R S", "weights")
    check_shape(t, "R S", "t (the same (R, S) as weights)", dims)
    w = weights.float()
    tt = t.float()
    span = (tt[:, -1:] - tt[:, :1]).clamp_min(1e-9)
    s = (tt - tt[:, :1]) / span  # (R, S) in [0, 1]
    d = torch.diff(s, dim=-1)
    d = torch.cat([d, d[:, -1:]], dim=-1) if d.shape[-1] else torch.ones_like(s)
    pairwise = (w[:, :, None] * w[:, None, :] * (s[:, :, None] - s[:, None, :]).abs()).sum(dim=(1, 2))
    return (pairwise + (w * w * d).sum(dim=-1) / 3.0).mean()

