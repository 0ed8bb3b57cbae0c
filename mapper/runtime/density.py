"""The density field of a :class:`~mapper.runtime.prepared.Prepared` and the occupancy grid that
lets renders skip empty space.

:func:`density` is what the marcher evaluates (the model's density, masked by view support; a render
volume's features outside its box come from the window's volume). :func:`occupancy_grid` is the
density's occupancy (computed once per version at 2x2x2 sub-samples, dilated by one voxel) less the
free space that the depth priors of keyframes without input depth carve (``carve_free_space``).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.model.field import GovNeSF
from mapper.model.ops.cost_volume import sample_volume
from mapper.runtime.loading import LoadedModel
from mapper.runtime.prepared import Prepared


def density(model: GovNeSF, prep: Prepared, points: Tensor) -> tuple[Tensor, Tensor]:
    """sigma (P,) and volume feature (P, Dv) at (P, 3) points; sigma is 0 where fewer than
    ``min_view_support`` views see the volume (trilinear in the support mask). A render
    volume's prep (``parent``) has no density outside its bounds; v there is the window's."""
    sigma, v = model.density_at(prep.volume, prep.bounds, points)
    if prep.support is not None:
        support, _ = sample_volume(prep.support, prep.bounds, points)
        sigma = sigma * support[..., 0]
    if prep.parent is not None:  # a render volume: the window's features outside it
        lo, hi = points.new_tensor(prep.bounds.origin_m), points.new_tensor(prep.bounds.max_corner_m)
        outside = ~((points >= lo) & (points <= hi)).all(dim=-1)
        if bool(outside.any()):
            window = prep.parent
            v = v.clone()
            v[outside] = sample_volume(window.volume, window.bounds,
                                       points[outside].to(window.volume.dtype))[0].to(v.dtype)
    return sigma, v


def occupancy_grid(loaded: LoadedModel, prep: Prepared) -> Tensor:
    """The occupancy grid (X, Y, Z) bool: the density's (:func:`density_occupancy`) less the free
    space the depth priors carve (``carve_free_space``, :func:`free_space`)."""
    occupied = density_occupancy(loaded, prep)
    if not loaded.config.carve_free_space:
        return occupied
    if prep.free_space is None:
        prep.free_space = free_space(loaded, prep)
    return occupied & ~prep.free_space


def free_space(loaded: LoadedModel, prep: Prepared) -> Tensor:
    """(X, Y, Z) bool: voxels the prior rays of at least ``carve_min_views`` keyframes without
    input depth cross short of their surface, away from every prior surface point."""
    cfg = loaded.config
    device = loaded.device
    b = prep.bounds
    dims = torch.tensor(b.dims, device=device)
    n_vox = int(np.prod(b.dims))
    empty = torch.zeros(b.dims, dtype=torch.bool, device=device)
    if prep.depth_m is None or prep.prior_only is None or not bool(prep.prior_only.any()):
        return empty
    origin = torch.tensor(b.origin_m, dtype=torch.float32, device=device)
    step = 0.5 * b.voxel_size_m
    crossed = torch.zeros(n_vox, dtype=torch.int32, device=device)
    surface = torch.zeros(n_vox, dtype=torch.bool, device=device)

    def linear(world: Tensor) -> tuple[Tensor, Tensor]:  # (..., 3) -> voxel index, inside
        vox = torch.floor((world - origin) / b.voxel_size_m).long()
        inside = ((vox >= 0) & (vox < dims)).all(dim=-1)
        idx = (vox[..., 0] * b.dims[1] + vox[..., 1]) * b.dims[2] + vox[..., 2]
        return idx, inside

    for v in prep.prior_only.nonzero().squeeze(-1).tolist():
        depth = prep.depth_m[v]
        rows, cols = (depth > 0).nonzero(as_tuple=True)
        if rows.numel() == 0:
            continue
        keep = torch.linspace(0, rows.numel() - 1, min(cfg.carve_rays, rows.numel()), device=device)
        keep = keep.round().long()
        rows, cols = rows[keep], cols[keep]
        z = depth[rows, cols]
        K, pose = prep.K[v], prep.world_from_cam[v]
        ray = torch.stack([(cols.float() + 0.5 - K[2]) / K[0], (rows.float() + 0.5 - K[3]) / K[1],
                           torch.ones_like(z)], dim=-1)  # (R, 3), z = 1
        ray_w = ray @ pose[:3, :3].T
        end, inside = linear(z[:, None] * ray_w + pose[:3, 3])
        surface[end[inside]] = True
        t = torch.arange(1, int(float(z.max()) / step) + 1, device=device) * step  # (S,)
        before = t[None, :] <= (1.0 - cfg.carve_margin) * z[:, None]  # (R, S)
        pts = pose[:3, 3] + t[None, :, None] * ray_w[:, None, :]  # (R, S, 3)
        idx, inside = linear(pts)
        seen = torch.unique(idx[before & inside])
        crossed[seen] += 1
    near_surface = F.max_pool3d(surface.view(1, 1, *b.dims).float(), 3, 1, 1)[0, 0] > 0
    empty = (crossed.view(b.dims) >= cfg.carve_min_views) & ~near_surface
    return empty


def density_occupancy(loaded: LoadedModel, prep: Prepared) -> Tensor:
    """(X, Y, Z) bool: True where the density at the voxel's 2x2x2 sub-samples or at a neighbour's
    reaches ``occupancy_threshold`` (the dilated maximum is cached in ``prep``; the threshold is
    applied per call)."""
    if prep.max_density is not None:
        return prep.max_density >= loaded.config.occupancy_threshold
    model = loaded.require_model()
    device = loaded.device
    b = prep.bounds
    axes = [
        (torch.arange(2 * n, dtype=torch.float32, device=device) + 0.5) * (b.voxel_size_m / 2) + o
        for n, o in zip(b.dims, b.origin_m, strict=True)
    ]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    sigma = torch.cat(
        [density(model, prep, grid[i : i + 65536])[0] for i in range(0, grid.shape[0], 65536)]
    )
    fine = sigma.reshape(1, 1, 2 * b.dims[0], 2 * b.dims[1], 2 * b.dims[2])
    coarse = F.max_pool3d(fine, kernel_size=2, stride=2)
    dilated = F.max_pool3d(coarse, kernel_size=3, stride=1, padding=1)[0, 0]
    prep.max_density = dilated  # cached; the threshold is applied per call (config may change)
    return prep.max_density >= loaded.config.occupancy_threshold
