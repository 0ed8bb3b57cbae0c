"""Volume rendering as pure functions (nerfstudio style).

A ray ``o + t d`` is cut into S bins ``[t_i - delta_i / 2, t_i + delta_i / 2]``. With density
``sigma_i`` (1/m) in bin i, the optical depth is ``tau_i = sigma_i * delta_i`` and

    alpha_i = 1 - exp(-tau_i)                (WITH the spacing, unlike the official code)
    T_i     = exp(-sum_{j < i} tau_j)        (exclusive cumulative sum, computed in log space)
    w_i     = T_i * alpha_i

so that ``sum_i w_i = 1 - T_S <= 1``. ``alpha`` uses ``expm1`` (accurate for tiny tau), tau is
clamped to ``[0, TAU_MAX]`` so that neither the cumulative sum nor its gradient overflows, and
half-precision inputs are computed in float32 and returned in their dtype. Density and spacing
are each capped at 1e10 before multiplying (an fp16 density that overflowed to inf still
renders as opaque with finite gradients).

Example:
    >>> import torch
    >>> t, deltas = sample_along_rays(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), 1.0, 3.0, 4,
    ...                               stratified=False)
    >>> t.tolist(), deltas.tolist()
    ([[1.25, 1.75, 2.25, 2.75]], [[0.5, 0.5, 0.5, 0.5]])
    >>> weights, transmittance = render_weights(torch.full((1, 4), 1e6), deltas)
    >>> weights.tolist()
    [[1.0, 0.0, 0.0, 0.0]]
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from mapper.checks import check_shape

__all__ = [
    "MIN_SPAN_M",
    "TAU_MAX",
    "RaySamples",
    "Rays",
    "accumulated_opacity",
    "clip_to_box",
    "composite",
    "expected_depth",
    "intersect_aabb",
    "optical_depth",
    "render_weights",
    "sample_along_rays",
]

TAU_MAX = 1.0e4
"""Largest optical depth a single bin may have; exp(-TAU_MAX) is 0 in every float dtype."""

_FACTOR_MAX = 1.0e10  # cap on density (1/m) and spacing (m) before their product

MIN_SPAN_M = 1.0e-6
"""Shortest part of ``[near, far]`` inside a box that ``clip_to_box`` counts as a hit (m)."""


@dataclass
class Rays:
    """A batch of rays."""

    origins: Tensor
    """(R, 3) ray origins in the world frame (m)."""
    directions: Tensor
    """(R, 3) unit directions in the world frame."""

    def __post_init__(self) -> None:
        check_shape(self.directions, "R 3", "directions", check_shape(self.origins, "R 3", "origins"))

    def __len__(self) -> int:
        return int(self.origins.shape[0])


@dataclass
class RaySamples:
    """Samples along a batch of rays."""

    rays: Rays
    """The R rays."""
    t: Tensor
    """(R, S) distance of each sample from the ray origin along the unit direction (m)."""
    deltas: Tensor
    """(R, S) length of the bin each sample stands for (m)."""

    @property
    def positions(self) -> Tensor:
        """(R, S, 3) world positions of the samples."""
        return self.rays.origins[:, None, :] + self.t[..., None] * self.rays.directions[:, None, :]


def _as_column(value: float | Tensor, n_rays: int, like: Tensor) -> Tensor:
    out = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if out.ndim == 0:
        return out.expand(n_rays).unsqueeze(-1)
    if out.shape != (n_rays,):
        raise ValueError(f"near/far must be a float or a ({n_rays},) tensor, got shape {tuple(out.shape)}")
    return out.unsqueeze(-1)


def sample_along_rays(
    origins: Tensor,
    directions: Tensor,
    near_m: float | Tensor,
    far_m: float | Tensor,
    n_samples: int,
    *,
    stratified: bool,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Split ``[near, far]`` into ``n_samples`` equal bins and place one sample in each.

    Args:
        origins: (R, 3); directions: (R, 3) unit (only their count, dtype and device are used).
        near_m, far_m: a float or (R,) per-ray bounds (m), ``0 <= near < far``.
        n_samples: S >= 1.
        stratified: jitter each sample uniformly inside its bin (training) instead of taking the
            bin midpoint (evaluation).
        generator: random source for the jitter.

    Returns:
        t: (R, S) sample distances (m); deltas: (R, S) bin lengths (m).
    """
    check_shape(directions, "R 3", "directions", check_shape(origins, "R 3", "origins"))
    if n_samples < 1:
        raise ValueError(f"n_samples {n_samples} out of range: must be >= 1")
    n_rays = origins.shape[0]
    near = _as_column(near_m, n_rays, origins)
    far = _as_column(far_m, n_rays, origins)
    if bool((near < 0).any()) or not bool((far > near).all()):
        raise ValueError(
            "ray bounds must satisfy 0 <= near < far, got near in "
            f"[{near.min().item()}, {near.max().item()}], "
            f"far in [{far.min().item()}, {far.max().item()}]"
        )
    steps = torch.linspace(0.0, 1.0, n_samples + 1, dtype=origins.dtype, device=origins.device)
    edges = near + (far - near) * steps  # (R, S + 1)
    lower, upper = edges[:, :-1], edges[:, 1:]
    if stratified:
        u = torch.rand(lower.shape, generator=generator, dtype=torch.float64, device="cpu")
        u = u.to(device=origins.device, dtype=origins.dtype)
    else:
        u = torch.full_like(lower, 0.5)
    t = lower + (upper - lower) * u
    return t, upper - lower


def _compute_dtype(x: Tensor) -> torch.dtype:
    return torch.float32 if x.dtype in (torch.float16, torch.bfloat16) else x.dtype


def optical_depth(sigma: Tensor, deltas: Tensor) -> Tensor:
    """Per-bin optical depth ``tau_i = sigma_i * delta_i`` as ``render_weights`` uses it.

    Args:
        sigma: (R, S) densities (1/m), negative = 0; deltas: (R, S) bin lengths (m).

    Returns:
        (R, S) tau in ``[0, TAU_MAX]``, in float32 for half-precision inputs (else their dtype);
        ``exp(-sum_{j < i} tau_j)`` is the transmittance in front of bin i.
    """
    if sigma.shape != deltas.shape:
        raise ValueError(
            f"sigma {tuple(sigma.shape)} and deltas {tuple(deltas.shape)} must have the same shape"
        )
    work = _compute_dtype(sigma)
    # Finite caps on both factors keep every product (and its gradient, e.g. 0 * inf) finite,
    # also for densities that overflowed to inf in half precision.
    tau = sigma.to(work).clamp(0.0, _FACTOR_MAX) * deltas.to(work).clamp(0.0, _FACTOR_MAX)
    return tau.clamp_max(TAU_MAX)


def render_weights(sigma: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Volume-rendering weights of samples along rays.

    Args:
        sigma: (R, S) densities (1/m); negative values are treated as 0.
        deltas: (R, S) bin lengths (m), >= 0.

    Returns:
        weights: (R, S) ``T_i * alpha_i`` (>= 0, sum over S <= 1).
        transmittance: (R, S) ``T_i``, the probability that the ray reaches bin i (non-increasing).
    """
    if sigma.shape != deltas.shape:
        raise ValueError(
            f"sigma {tuple(sigma.shape)} and deltas {tuple(deltas.shape)} must have the same shape"
        )
    out_dtype = sigma.dtype
    tau = optical_depth(sigma, deltas)
    alpha = -torch.expm1(-tau)
    # Exclusive cumulative sum by shifting (not inclusive minus own term, which loses the small
    # prefix next to a huge tau to rounding).
    log_t_exclusive = torch.cumsum(torch.cat([torch.zeros_like(tau[..., :1]), tau[..., :-1]], dim=-1), dim=-1)
    transmittance = torch.exp(-log_t_exclusive)
    weights = transmittance * alpha
    return weights.to(out_dtype), transmittance.to(out_dtype)


def accumulated_opacity(weights: Tensor) -> Tensor:
    """(R, S) weights -> (R,) opacity ``sum_i w_i`` in [0, 1]."""
    return weights.sum(dim=-1)


def composite(weights: Tensor, values: Tensor) -> Tensor:
    """Alpha-composite per-sample values along rays.

    Args:
        weights: (R, S); values: (R, S, C).

    Returns:
        (R, C) ``sum_i w_i v_i`` (no background: a constant colour renders to itself times the
        opacity; add ``(1 - opacity) * background`` yourself if you want one).
    """
    if values.shape[:-1] != weights.shape:
        raise ValueError(f"values {tuple(values.shape)} must be weights {tuple(weights.shape)} + (C,)")
    work = torch.promote_types(_compute_dtype(weights), _compute_dtype(values))
    out = (weights.to(work).unsqueeze(-1) * values.to(work)).sum(dim=-2)
    return out.to(torch.promote_types(weights.dtype, values.dtype))


def expected_depth(weights: Tensor, t: Tensor, eps: float = 1e-10) -> Tensor:
    """Expected ray distance of the surface, normalised by the opacity.

    Args:
        weights: (R, S); t: (R, S) sample distances (m).

    Returns:
        (R,) ``sum_i w_i t_i / sum_i w_i`` clamped to ``[t_0, t_{S-1}]`` (a ray with no opacity gets
        ``t_0``; use ``accumulated_opacity`` to tell it apart). This is a distance along the unit
        ray direction, not a camera z-depth.
    """
    if weights.shape != t.shape:
        raise ValueError(f"weights {tuple(weights.shape)} and t {tuple(t.shape)} must have the same shape")
    work = torch.promote_types(_compute_dtype(weights), _compute_dtype(t))
    w, tt = weights.to(work), t.to(work)
    depth = (w * tt).sum(dim=-1) / (w.sum(dim=-1) + eps)
    depth = torch.maximum(torch.minimum(depth, tt[..., -1]), tt[..., 0])
    return depth.to(torch.promote_types(weights.dtype, t.dtype))


def intersect_aabb(
    origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Slab-method intersection of rays with an axis-aligned box (for empty-space skipping).

    Rays parallel to a face are handled without NaN (a zero direction component is replaced by
    a tiny one of the same sign); the box is closed, so a ray lying in a face plane hits.

    Args:
        origins: (R, 3); directions: (R, 3); box_min, box_max: (3,) world corners (m).

    Returns:
        t_near: (R,) entry distance clamped at 0, t_far: (R,) exit distance, hit: (R,) bool
        (``t_far >= t_near``); where there is no hit, t_near = t_far = 0.
    """
    out_dtype = origins.dtype
    if out_dtype in (torch.float16, torch.bfloat16):
        origins, directions = origins.float(), directions.float()
    tiny = 1e-12 if origins.dtype == torch.float64 else 1e-30
    sign = torch.where(directions < 0, -1.0, 1.0).to(directions.dtype)
    safe = torch.where(directions.abs() < tiny, sign * tiny, directions)
    t1 = (box_min.to(origins) - origins) / safe
    t2 = (box_max.to(origins) - origins) / safe
    t_near = torch.minimum(t1, t2).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t1, t2).amin(dim=-1)
    hit = t_far >= t_near
    zero = torch.zeros_like(t_near)
    t_near, t_far = torch.where(hit, t_near, zero), torch.where(hit, t_far, zero)
    return t_near.to(out_dtype), t_far.to(out_dtype), hit


def clip_to_box(
    origins: Tensor,
    directions: Tensor,
    near_m: float | Tensor,
    far_m: float | Tensor,
    box_min: Tensor,
    box_max: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Clip per-ray ``[near, far]`` to the part inside an axis-aligned box.

    Args:
        origins, directions: (R, 3); near_m, far_m: a float or (R,) bounds (m);
        box_min, box_max: (3,) world corners (m).

    Returns:
        near: (R,), far: (R,) the clipped bounds where the ray crosses the box for more than
        ``MIN_SPAN_M`` inside ``[near, far]``, the given bounds elsewhere; inside: (R,) bool, where
        it does.
    """
    check_shape(directions, "R 3", "directions", check_shape(origins, "R 3", "origins"))
    n_rays = origins.shape[0]
    t_in, t_out, hit = intersect_aabb(origins, directions, box_min, box_max)
    near = torch.as_tensor(near_m, dtype=t_in.dtype, device=t_in.device).expand(n_rays)
    far = torch.as_tensor(far_m, dtype=t_in.dtype, device=t_in.device).expand(n_rays)
    clipped_near, clipped_far = torch.maximum(near, t_in), torch.minimum(far, t_out)
    inside = hit & (clipped_far > clipped_near + MIN_SPAN_M)
    return torch.where(inside, clipped_near, near), torch.where(inside, clipped_far, far), inside
