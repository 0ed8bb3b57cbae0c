"""Geometry and visibility supervision from training depth (NeuRay / S-Ray style).

Training data has depth for free (the simulator, real RGB-D sequences); inference stays RGB-only.
These pure functions turn that depth into targets and losses for the three things the paper's
depth-free loss never teaches directly:

* where each ray's weight sits: :func:`ray_depth_loss` (rendered depth vs the true ray distance)
  and :func:`surface_loss` (no weight in the free space in front of the surface, the weight
  mass in a band around it);
* which source views see a surface point: :func:`visibility_targets` (project the true surface
  point into every source view and compare with that view's depth);
* blending that trusts the views that see the point: :func:`visibility_loss` (the OV blending
  weight mass on the visible views).

All take plain tensors with shapes in their docstrings; none needs the model.

>>> import torch
>>> t = torch.linspace(0.5, 4.5, 9).expand(2, 9)               # (R, S) sample distances
>>> w = torch.zeros(2, 9); w[0, 4] = 1.0; w[1, 0] = 1.0         # ray 0 at 2.5 m, ray 1 at 0.5 m
>>> [float(surface_loss(w[i:i + 1], t[i:i + 1], torch.tensor([2.5]), band_m=0.3)) for i in range(2)]
[0.0, 2.0]
"""

from __future__ import annotations

import torch
from torch import Tensor

from mapper.checks import check_shape
from mapper.model.ops.geometry import in_view, invert_pose, project_points, sample_nearest, scale_uv

__all__ = [
    "ray_depth_loss",
    "ray_distance",
    "surface_loss",
    "surface_points",
    "visibility_loss",
    "visibility_targets",
]


def ray_distance(z_depth: Tensor, directions: Tensor, optical_axis: Tensor) -> Tensor:
    """z-depth along the optical axis -> distance along each unit ray (0 stays 0 = no depth).

    Args:
        z_depth: (R,) metres; directions: (R, 3) unit ray directions (world); optical_axis: (3,)
            the camera's z axis in the world (``world_from_cam[:3, 2]``).
    """
    dims = check_shape(z_depth, "R", "z_depth")
    check_shape(directions, "R 3", "directions", dims)
    cos = (directions @ optical_axis.to(directions.dtype)).clamp_min(1e-6)
    return torch.where(z_depth > 0, z_depth / cos, torch.zeros_like(z_depth))


def surface_points(origins: Tensor, directions: Tensor, t_surface: Tensor) -> Tensor:
    """(R, 3), (R, 3), (R,) -> (R, 3) the true surface point of each ray (``o + t d``)."""
    return origins + t_surface.unsqueeze(-1).to(origins.dtype) * directions


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    m = mask.to(values.dtype)
    return (values * m).sum() / m.sum().clamp_min(1.0)


def ray_depth_loss(pred_t: Tensor, target_t: Tensor) -> Tensor:
    """Mean relative L1 ``|t_hat - t| / t`` over rays with a target (``target_t > 0``).

    Relative, so near and far surfaces weigh alike (the node reads depth as relative error).
    """
    dims = check_shape(pred_t, "R", "pred_t")
    check_shape(target_t, "R", "target_t", dims)
    has = target_t > 0
    err = (pred_t.float() - target_t.float()).abs() / target_t.float().clamp_min(1e-3)
    return _masked_mean(err, has)


def surface_loss(weights: Tensor, t: Tensor, target_t: Tensor, *, band_m: float = 0.15) -> Tensor:
    """Line-of-sight loss: weight in front of the surface + weight missing around it.

    For a ray whose true surface lies at ``target_t``: ``empty`` = the weight of samples closer
    than ``target_t - band``, ``near`` = the weight within ``band`` of it; loss = empty + (1 - near),
    averaged over rays with a target. 0 exactly when all the weight sits in the band; at most 2.
    The band is widened per ray to at least the sample spacing (a band narrower than the spacing
    could hold no sample).

    Args:
        weights: (R, S) rendering weights; t: (R, S) sample distances (increasing);
        target_t: (R,) true ray distance, 0 = no target (ray ignored).
    """
    dims = check_shape(weights, "R S", "weights")
    check_shape(t, "R S", "t", dims)
    check_shape(target_t, "R", "target_t", dims)
    if band_m <= 0:
        raise ValueError(f"band_m {band_m} out of range: must be > 0")
    w = weights.float()
    tt = t.float()
    target = target_t.float().unsqueeze(-1)
    spacing = (tt[:, -1:] - tt[:, :1]) / max(tt.shape[1] - 1, 1)
    band = torch.clamp(spacing, min=band_m)
    empty = (w * (tt < target - band).to(w.dtype)).sum(-1)
    near = (w * ((tt - target).abs() <= band).to(w.dtype)).sum(-1)
    return _masked_mean(empty + (1.0 - near), target_t > 0)


@torch.no_grad()
def visibility_targets(
    points: Tensor,
    K: Tensor,
    world_from_cam: Tensor,
    depth_m: Tensor,
    image_wh: tuple[int, int],
    *,
    rel_tol: float = 0.05,
    abs_tol_m: float = 0.05,
) -> tuple[Tensor, Tensor]:
    """Which source views see each point, from their depth maps.

    A view sees a point when the point projects inside its image, in front of it, and its depth
    there agrees with the point's depth (``|z - d| <= abs_tol + rel_tol * d``). A view that has no
    depth at that pixel (0) is unknown.

    Args:
        points: (P, 3) world points; K: (N, 4) for ``image_wh``; world_from_cam: (N, 4, 4);
        depth_m: (N, H', W') z-depth maps (any size; 0 = none).

    Returns:
        visible: (P, N) bool; known: (P, N) bool (in view with a depth reading: visible or occluded).
    """
    dims = check_shape(points, "P 3", "points")
    check_shape(K, "N 4", "K", dims)
    check_shape(world_from_cam, "N 4 4", "world_from_cam", dims)
    check_shape(depth_m, "N H W", "depth_m", dims)
    width, height = image_wh
    uv, z = project_points(points.unsqueeze(0), K, invert_pose(world_from_cam))  # (N, P, 2), (N, P)
    inside = in_view(uv, z, width, height)
    duv = scale_uv(uv, (width, height), (depth_m.shape[-1], depth_m.shape[-2]))
    d, _ = sample_nearest(depth_m.unsqueeze(1).to(uv.dtype), duv)  # (N, P, 1)
    d = d[..., 0]
    known = inside & (d > 0)
    visible = known & ((z - d).abs() <= abs_tol_m + rel_tol * d)
    return visible.T.contiguous(), known.T.contiguous()


def visibility_loss(blend_weights: Tensor, visible: Tensor, known: Tensor) -> Tensor:
    """``-log`` of the blending weight mass on the views that see the point.

    Counted only for points where some view is known to see it and some view is known to be
    occluded there (elsewhere every choice is right); 0 when there is no such point.

    Args:
        blend_weights: (P, N) the network's per-view blending weights (rows sum to 1 or 0);
        visible, known: (P, N) bool from :func:`visibility_targets`.
    """
    dims = check_shape(blend_weights, "P N", "blend_weights")
    check_shape(visible, "P N", "visible", dims)
    check_shape(known, "P N", "known", dims)
    occluded = known & ~visible
    use = visible.any(-1) & occluded.any(-1)
    mass = (blend_weights.float() * visible.float()).sum(-1)
    nll = -torch.log(mass.clamp_min(1e-6))
    return _masked_mean(nll, use)
