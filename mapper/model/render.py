"""The one ray marcher: samples -> density -> weights -> appearance -> composite.

Every renderer of the model calls :func:`march_rays`: ``field.render_rays`` (training,
evaluation, ``render_image``), ``field.render_depth_maps`` (density only) and the node's
``ModelRuntime`` (occupancy-grid empty-space skipping, per-point source-view groups). What
differs between them is passed in, never re-implemented:

* ``density(points) -> (sigma, features)``: the field's density at (P, 3) points and the
  per-point features the appearance needs (``GovNeSF.density_at`` over a volume; the runtime
  adds its view-support mask);
* ``appearance(points, view_dirs, features) -> (rgb, ov, valid)`` over any subset of the
  samples (``GovNeSF.appearance`` with one set of source views; the runtime passes one that
  splits the samples into view groups), or None for a depth-only march;
* ``box``: clip ``[near, far]`` to the volume box (``clip_to_box``); ``skip_missed``: rays that
  do not cross it are not evaluated at all (they render nothing) instead of being marched over
  their unclipped ``[near, far]``;
* ``sample_mask(points) -> bool``: samples where the density may be non-zero (e.g.
  :func:`occupancy_mask`); the others get density 0 without a network call;
* ``min_weight``: the appearance runs only for samples whose (detached) weight reaches it; the
  others contribute 0 colour / OV;
* ``stop_transmittance`` (early ray termination): the density runs in steps of
  ``termination_block`` samples, and a ray whose transmittance has dropped below the threshold
  after a step is not evaluated any further (its later samples get density 0): opacity, colour and
  OV change by at most the threshold (times the largest |value|);
* ``appearance_groups = K`` (coarse-to-fine in weight space): the samples of a ray are cut into at
  most K runs of consecutive samples with about equal weight mass (:func:`weight_groups`); the
  appearance runs ONCE per run, at the run's weight-weighted mean position, and the run's value
  is composited with the run's total weight. Exact for an appearance that is affine in the
  position along the ray; K >= S evaluates every sample as without it.

The maths per ray (bins, weights, compositing) is ``mapper.model.ops.rendering``.

Example (a constant density, depth only):
    >>> import torch
    >>> from mapper.model.ops.rendering import Rays
    >>> rays = Rays(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]))
    >>> out = march_rays(rays, lambda p: (torch.full((p.shape[0],), 1e6), p.new_zeros(p.shape[0], 1)),
    ...                  n_samples=4, near_m=1.0, far_m=3.0)
    >>> out.depth_m.tolist(), out.opacity.tolist(), out.rgb is None
    ([1.25], [1.0], True)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from mapper.checks import check_shape
from mapper.model.ops.cost_volume import VolumeBounds
from mapper.model.ops.rendering import (
    Rays,
    clip_to_box,
    composite,
    expected_depth,
    optical_depth,
    render_weights,
    sample_along_rays,
)

__all__ = [
    "AppearanceFn",
    "DensityFn",
    "MarchOutputs",
    "SampleMask",
    "march_rays",
    "occupancy_mask",
    "weight_groups",
]

DensityFn = Callable[[Tensor], tuple[Tensor, Tensor]]
"""(P, 3) points -> sigma (P,) (1/m), features (P, Dv) handed to the appearance."""

AppearanceFn = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]
"""points (K, 3), unit view directions (K, 3), features (K, Dv) -> rgb (K, 3), ov (K, D),
valid (K,) bool (some source view sees the point). Called once per march, with K >= 0."""

SampleMask = Callable[[Tensor], Tensor]
"""(P, 3) points -> (P,) bool: where the density may be non-zero."""


@dataclass
class MarchOutputs:
    """Per-ray results of :func:`march_rays`."""

    t: Tensor
    """(R, S) sample distances along the unit ray directions (m)."""
    weights: Tensor
    """(R, S) rendering weights ``T_i alpha_i``."""
    depth_m: Tensor
    """(R,) expected distance along the unit direction (``expected_depth``)."""
    opacity: Tensor
    """(R,) accumulated opacity."""
    rgb: Tensor | None
    """(R, 3) composited colour; None for a depth-only march."""
    ov: Tensor | None
    """(R, D) OV feature composited with DETACHED weights; None for a depth-only march."""
    valid: Tensor
    """(R, S) bool: the appearance ran for the sample and some source view sees it."""
    density_evals: int
    """Samples the density was evaluated for."""
    appearance_evals: int
    """Samples the appearance was evaluated for."""


def occupancy_mask(occupancy: Tensor, bounds: VolumeBounds) -> SampleMask:
    """A ``sample_mask`` from an (X, Y, Z) bool occupancy grid over ``bounds``: True for points
    inside the grid whose voxel is occupied."""
    check_shape(occupancy, "X Y Z", "occupancy (bounds.dims)", dict(zip("XYZ", bounds.dims, strict=True)))

    def mask(points: Tensor) -> Tensor:
        vox = ((points - points.new_tensor(bounds.origin_m)) / bounds.voxel_size_m).floor().long()
        dims = torch.tensor(bounds.dims, device=points.device)
        inside = ((vox >= 0) & (vox < dims)).all(dim=-1)
        vox = torch.minimum(vox.clamp_min(0), dims - 1)
        return inside & occupancy[vox[:, 0], vox[:, 1], vox[:, 2]]

    return mask


def weight_groups(weights: Tensor, n_groups: int) -> Tensor:
    """Cut every ray's samples into at most ``n_groups`` runs of about equal weight mass.

    Sample i of a ray goes to group ``floor(K * (C_{i-1} + w_i / 2) / W)`` (clamped to
    ``[0, K)``), with C the cumulative weight and W the ray's total: the index never decreases
    along the ray, so each group is a run of consecutive samples, and a group's mass is at most
    ``W / K`` plus the largest single weight. A ray with no weight is all group 0.

    Args:
        weights: (R, S) non-negative weights (detached; negative values count as 0).
        n_groups: K >= 1.

    Returns:
        (R, S) long group index of each sample.
    """
    check_shape(weights, "R S", "weights")
    if n_groups < 1:
        raise ValueError(f"n_groups {n_groups} out of range: must be >= 1")
    w = weights.detach().to(torch.promote_types(weights.dtype, torch.float32)).clamp_min(0.0)
    total = w.sum(dim=-1, keepdim=True)
    centre = w.cumsum(dim=-1) - 0.5 * w
    frac = centre / total.clamp_min(torch.finfo(w.dtype).tiny)
    return (frac * n_groups).floor().long().clamp_(0, n_groups - 1)


def _density_early_stop(
    flat: Tensor,  # (R * S, 3) sample positions
    deltas: Tensor,  # (R, S) bin lengths
    density: DensityFn,
    evaluate: Tensor | None,  # (R * S,) bool or None (every sample)
    block: int,
    stop_transmittance: float,
) -> tuple[Tensor, Tensor, int]:
    """sigma (R * S,), features (R * S, Dv) and the number of evaluations, marching ``block``
    samples at a time and dropping the rays whose transmittance fell below ``stop_transmittance``."""
    n_rays, S = deltas.shape
    ids = torch.arange(n_rays * S, device=flat.device).reshape(n_rays, S)
    active = torch.ones(n_rays, dtype=torch.bool, device=flat.device)
    selectable = None if evaluate is None else evaluate.reshape(n_rays, S)
    sigma: Tensor | None = None
    features: Tensor | None = None
    evals = 0
    for s0 in range(0, S, block):
        s1 = min(S, s0 + block)
        chosen = active[:, None].expand(n_rays, s1 - s0)
        if selectable is not None:
            chosen = chosen & selectable[:, s0:s1]
        idx = ids[:, s0:s1][chosen]
        sig, feat = density(flat[idx])
        if sigma is None or features is None:
            sigma = sig.new_zeros(n_rays * S)
            features = feat.new_zeros(n_rays * S, feat.shape[-1])
        sigma = sigma.index_copy(0, idx, sig)
        features = features.index_copy(0, idx, feat)
        evals += int(idx.numel())
        if s1 < S:
            tau = optical_depth(sigma.reshape(n_rays, S)[:, :s1].detach(), deltas[:, :s1])
            active = active & (torch.exp(-tau.sum(dim=-1)) >= stop_transmittance)
            if not bool(active.any()):
                break
    assert sigma is not None and features is not None
    return sigma, features, evals


def march_rays(
    rays: Rays,
    density: DensityFn,
    appearance: AppearanceFn | None = None,
    *,
    n_samples: int,
    near_m: float | Tensor,
    far_m: float | Tensor,
    stratified: bool = False,
    generator: torch.Generator | None = None,
    box: tuple[Tensor, Tensor] | None = None,
    skip_missed: bool = False,
    sample_mask: SampleMask | None = None,
    min_weight: float = 0.0,
    stop_transmittance: float = 0.0,
    termination_block: int = 8,
    appearance_groups: int = 0,
) -> MarchOutputs:
    """Volume-render R rays with the given density and appearance.

    Args:
        rays: R rays (unit directions).
        density, appearance: see the module docstring; ``appearance=None`` marches density only.
        n_samples: S bins on ``[near, far]`` (one sample each: the midpoint, or jittered with
            ``stratified``, using ``generator``).
        near_m, far_m: a float or (R,) per-ray bounds (m).
        box: (box_min (3,), box_max (3,)): clip ``[near, far]`` to this box.
        skip_missed: with ``box``: rays that do not cross it get density 0 and no appearance
            (their samples stay on ``[near, far]``).
        sample_mask: samples outside it get density 0 without a ``density`` call.
        min_weight: > 0: appearance only where the detached weight reaches it (approximate: the
            others render 0 and lose their colour gradient); 0 (default): every evaluated sample.
        stop_transmittance: in [0, 1): > 0: early ray termination (module docstring); the
            density runs ``termination_block`` samples at a time. 0 (default): off.
        appearance_groups: K > 0 and < S: one appearance evaluation per run of about equal
            weight mass (``weight_groups``), at the run's weighted mean position (its volume
            features from one more ``density`` call there); 0 (default) or >= S: every sample.

    With neither ``skip_missed``, ``sample_mask``, ``min_weight``, ``stop_transmittance`` nor
    ``appearance_groups`` every sample goes through ``density`` and ``appearance`` in one call
    each (the differentiable training path); otherwise the selected samples are gathered,
    evaluated and scattered back (differentiable too).
    """
    _check_march_options(min_weight, stop_transmittance, termination_block, appearance_groups,
                         skip_missed, box)
    origins, dirs = rays.origins, rays.directions
    n_rays = len(rays)
    t, deltas, flat, evaluate = _march_samples(
        origins, dirs, near_m, far_m, n_samples, stratified, generator, box, skip_missed, sample_mask
    )
    S = t.shape[1]
    sigma, features, density_evals = _march_density(
        flat, deltas, density, evaluate, termination_block, stop_transmittance
    )
    sigma = sigma.reshape(n_rays, S)
    weights, _ = render_weights(sigma, deltas.to(sigma.dtype))

    rgb = ov = None
    valid = torch.zeros(n_rays, S, dtype=torch.bool, device=flat.device)
    appearance_evals = 0
    if appearance is not None:
        keep = evaluate
        if min_weight > 0:
            heavy = (weights.detach() >= min_weight).reshape(n_rays * S)
            keep = heavy if keep is None else keep & heavy
        if 0 < appearance_groups < S:
            rgb, ov, valid, appearance_evals, extra = _grouped_appearance(
                origins, dirs, t, weights, keep, density, appearance, appearance_groups
            )
            density_evals += extra
        else:
            rgb, ov, valid, appearance_evals = _sample_appearance(
                flat, dirs, features, weights, keep, appearance
            )
    return MarchOutputs(
        t=t,
        weights=weights,
        depth_m=expected_depth(weights, t.to(weights.dtype)),
        opacity=weights.sum(dim=-1),
        rgb=rgb,
        ov=ov,
        valid=valid,
        density_evals=density_evals,
        appearance_evals=appearance_evals,
    )


def _check_march_options(
    min_weight: float,
    stop_transmittance: float,
    termination_block: int,
    appearance_groups: int,
    skip_missed: bool,
    box: tuple[Tensor, Tensor] | None,
) -> None:
    """Raise ``ValueError`` for an option of :func:`march_rays` out of its range."""
    if min_weight < 0:
        raise ValueError(f"min_weight {min_weight} out of range: must be >= 0")
    if not 0.0 <= stop_transmittance < 1.0:
        raise ValueError(f"stop_transmittance {stop_transmittance} out of range: must be in [0, 1)")
    if termination_block < 1:
        raise ValueError(f"termination_block {termination_block} out of range: must be >= 1")
    if appearance_groups < 0:
        raise ValueError(f"appearance_groups {appearance_groups} out of range: must be >= 0")
    if skip_missed and box is None:
        raise ValueError("skip_missed needs a box: it skips the rays that miss the box")


def _march_samples(
    origins: Tensor,  # (R, 3)
    dirs: Tensor,  # (R, 3) unit
    near_m: float | Tensor,
    far_m: float | Tensor,
    n_samples: int,
    stratified: bool,
    generator: torch.Generator | None,
    box: tuple[Tensor, Tensor] | None,
    skip_missed: bool,
    sample_mask: SampleMask | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """The samples of :func:`march_rays`: t (R, S), deltas (R, S), the points (R * S, 3) and which
    of them to evaluate ((R * S,) bool: on a ray that crosses the box with ``skip_missed``, inside
    ``sample_mask``), or None for every one."""
    n_rays = origins.shape[0]
    near = torch.as_tensor(near_m, dtype=origins.dtype, device=origins.device)
    far = torch.as_tensor(far_m, dtype=origins.dtype, device=origins.device)
    crosses: Tensor | None = None
    if box is not None:
        near, far, inside = clip_to_box(origins, dirs, near, far, box[0], box[1])
        crosses = inside if skip_missed else None
    t, deltas = sample_along_rays(
        origins, dirs, near, far, n_samples, stratified=stratified, generator=generator
    )
    S = t.shape[1]
    P = n_rays * S
    flat = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(P, 3)
    evaluate = None if crosses is None else crosses[:, None].expand(n_rays, S).reshape(P)
    if sample_mask is not None:
        occupied = sample_mask(flat)
        evaluate = occupied if evaluate is None else evaluate & occupied
    return t, deltas, flat, evaluate


def _march_density(
    flat: Tensor,  # (R * S, 3) sample points
    deltas: Tensor,  # (R, S) bin lengths
    density: DensityFn,
    evaluate: Tensor | None,  # (R * S,) bool or None (every sample)
    termination_block: int,
    stop_transmittance: float,
) -> tuple[Tensor, Tensor, int]:
    """sigma (R * S,), features (R * S, Dv) and the number of density evaluations: with early
    termination block by block, else every sample in one call, else the ``evaluate`` samples
    gathered, evaluated and scattered back (the others 0)."""
    P = flat.shape[0]
    if stop_transmittance > 0 and termination_block < deltas.shape[1]:
        return _density_early_stop(flat, deltas, density, evaluate, termination_block, stop_transmittance)
    if evaluate is None:
        sigma, features = density(flat)
        return sigma, features, P
    idx = evaluate.nonzero().squeeze(-1)
    sig, feat = density(flat[idx])
    sigma = sig.new_zeros(P).index_copy(0, idx, sig)
    features = feat.new_zeros(P, feat.shape[-1]).index_copy(0, idx, feat)
    return sigma, features, int(idx.numel())


def _sample_appearance(
    flat: Tensor,  # (R * S, 3) sample points
    dirs: Tensor,  # (R, 3) unit
    features: Tensor,  # (R * S, Dv)
    weights: Tensor,  # (R, S) rendering weights
    keep: Tensor | None,  # (R * S,) bool: samples whose appearance counts, or None (all)
    appearance: AppearanceFn,
) -> tuple[Tensor, Tensor, Tensor, int]:
    """rgb (R, 3), ov (R, D), valid (R, S) and the number of appearance evaluations of the
    per-sample appearance: every sample in one call, or the ``keep`` samples gathered, evaluated
    and scattered back (the others 0)."""
    n_rays, S = weights.shape
    P = n_rays * S
    view_dirs = dirs[:, None, :].expand(n_rays, S, 3).reshape(P, 3)
    if keep is None:
        rgb_s, ov_s, valid_s = appearance(flat, view_dirs, features)
        evals = P
    else:
        kept = keep.nonzero().squeeze(-1)
        rgb_k, ov_k, valid_k = appearance(flat[kept], view_dirs[kept], features[kept])
        rgb_s = rgb_k.new_zeros(P, 3).index_copy(0, kept, rgb_k)
        ov_s = ov_k.new_zeros(P, ov_k.shape[-1]).index_copy(0, kept, ov_k)
        valid_s = valid_k.new_zeros(P).index_copy(0, kept, valid_k)
        evals = int(kept.numel())
    rgb = composite(weights, rgb_s.reshape(n_rays, S, 3))
    ov = composite(weights.detach(), ov_s.reshape(n_rays, S, -1))
    return rgb, ov, valid_s.reshape(n_rays, S), evals


def _grouped_appearance(
    origins: Tensor,  # (R, 3)
    dirs: Tensor,  # (R, 3) unit
    t: Tensor,  # (R, S) sample distances
    weights: Tensor,  # (R, S) rendering weights
    keep: Tensor | None,  # (R * S,) bool: samples whose appearance counts, or None (all)
    density: DensityFn,
    appearance: AppearanceFn,
    n_groups: int,
) -> tuple[Tensor, Tensor, Tensor, int, int]:
    """rgb (R, 3), ov (R, D), valid (R, S), appearance evaluations and extra density evaluations
    of the weight-group appearance (``appearance_groups`` in :func:`march_rays`)."""
    n_rays, S = t.shape
    kept = weights if keep is None else weights * keep.reshape(n_rays, S).to(weights.dtype)
    mass = kept.detach()
    group = weight_groups(mass, n_groups)  # (R, S)
    gid = (torch.arange(n_rays, device=t.device)[:, None] * n_groups + group).reshape(-1)
    zeros = mass.new_zeros(n_rays * n_groups)
    group_mass = zeros.index_add(0, gid, mass.reshape(-1))
    group_t = zeros.index_add(0, gid, (mass * t.to(mass.dtype)).reshape(-1))
    live = (group_mass > 0).nonzero().squeeze(-1)  # (G,) groups that carry weight
    ray = live // n_groups
    t_rep = (group_t[live] / group_mass[live]).to(origins.dtype)
    points = origins[ray] + t_rep[:, None] * dirs[ray]
    _, feat = density(points)
    rgb_g, ov_g, valid_g = appearance(points, dirs[ray], feat)
    G = int(live.numel())
    rgb_all = rgb_g.new_zeros(n_rays * n_groups, 3).index_copy(0, live, rgb_g)
    ov_all = ov_g.new_zeros(n_rays * n_groups, ov_g.shape[-1]).index_copy(0, live, ov_g)
    valid_all = valid_g.new_zeros(n_rays * n_groups).index_copy(0, live, valid_g)
    # The groups' weights (with the gradient of the samples' weights) composite their values.
    group_w = weights.new_zeros(n_rays * n_groups).index_add(0, gid, kept.reshape(-1))
    rgb = composite(group_w.reshape(n_rays, n_groups), rgb_all.reshape(n_rays, n_groups, 3))
    ov = composite(group_w.detach().reshape(n_rays, n_groups), ov_all.reshape(n_rays, n_groups, -1))
    valid = (valid_all[gid] & (mass.reshape(-1) > 0)).reshape(n_rays, S)
    return rgb, ov, valid, G, G
