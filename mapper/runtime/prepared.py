"""What a query needs of the window, built once per runtime version: :class:`Prepared`.

:func:`stack_views` stacks the window's :class:`~mapper.runtime.entries.ViewEntry` tensors and runs
the 3D U-Net over the cost volume's statistics. A render may ask for a volume over the few keyframes
that best overlap its view (``render_volume_views``): :func:`render_prep` builds it (bounds from what
those keyframes observed), keeps the last few per version, and hands back a :class:`Prepared` that
shares the window's stacked views.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from mapper.errors import RuntimeNotReady
from mapper.model.field import GovNeSF, OVMaps
from mapper.model.ops.cost_volume import (
    CostVolume,
    VolumeBounds,
    bounds_from_points,
    build_cost_volume,
    cost_volume_features,
)
from mapper.model.ops.geometry import in_view, invert_pose, project_points
from mapper.runtime.entries import ViewEntry, render_extents
from mapper.runtime.loading import LoadedModel

RENDER_VOLUMES_KEPT = 8
"""Most render volumes kept per version, the oldest dropped first (a client rendering a few poses
over and over reuses them)."""


@dataclass
class Prepared:
    """Everything a query needs, cached per runtime version."""

    version: int
    bounds: VolumeBounds
    volume: Tensor  # (Dv, X, Y, Z) 3D U-Net output
    rgb: Tensor  # (M, 3, H, W)
    features: Tensor  # (M, F, h, w)
    ov: Tensor | None  # (M, D, h_ov, w_ov) float32 (zeros for views without ov) or None
    has_ov: Tensor  # (M,) bool
    depth_m: Tensor | None  # (M, H, W) (zeros for views without depth) or None
    K: Tensor  # (M, 4)
    world_from_cam: Tensor  # (M, 4, 4)
    ov_space: str | None
    support: Tensor | None = None  # (1, X, Y, Z) 1 where >= min_view_support views see the voxel
    max_density: Tensor | None = None  # (X, Y, Z) dilated max sub-voxel density (1/m), on first use
    prior_only: Tensor | None = None  # (M,) bool: the view's depth_m is a prior (no input depth)
    input_depth: Tensor | None = None  # (M,) bool: the view's depth_m is input depth
    free_space: Tensor | None = None  # (X, Y, Z) bool carved by the priors (carve_free_space), on first use
    ov_table: Tensor | None = None  # (M * h_ov * w_ov, D) ``ov`` channel-last, on first use
    extents: list[Tensor] = field(default_factory=list)
    """M x (E_m, 3): what each view observed (depth points; without depth the points
    ``set_view_extent`` gave it, without the camera centre), for the bounds of render volumes."""
    render_volumes: dict[tuple[int, ...], Prepared] = field(default_factory=dict)
    """Render preps over keyframe subsets (``render_volume_views``), by view indices; this version's."""
    parent: Prepared | None = None
    """A render volume's prep (``render_volume_views``): the window's, whose OV gather table it
    shares (built once) and whose volume features the blend takes at points outside this prep's
    bounds (the render volume has none there)."""
    render_views: int = 0
    """A render volume's prep: the keyframes its volume spans (0: the window's prep)."""

    def ov_maps(self, view_idx: Tensor, image_wh: tuple[int, int]) -> OVMaps:
        """The OV maps of ``view_idx`` (N,) as a gather table (built once per version)."""
        assert self.ov is not None
        if self.parent is not None:
            return self.parent.ov_maps(view_idx, image_wh)
        if self.ov_table is None:
            self.ov_table = self.ov.permute(0, 2, 3, 1).reshape(-1, self.ov.shape[1]).contiguous()
        h, w = self.ov.shape[-2:]
        return OVMaps(self.ov_table, (int(w), int(h)), view_idx, image_wh)

    def __len__(self) -> int:
        return int(self.rgb.shape[0])


def stack_views(
    loaded: LoadedModel, model: GovNeSF, entries: Sequence[ViewEntry], volume: CostVolume, version: int
) -> Prepared:
    """The window's views stacked (OV on the common grid, zeros for views without it; input depth,
    else the sparse prior, else zeros) with the 3D U-Net's output over ``volume``'s statistics."""
    device = loaded.device
    has_ov = torch.tensor([e.ov is not None for e in entries], device=device)
    ov = None
    if bool(has_ov.any()):
        dims = {int(e.ov.shape[0]) for e in entries if e.ov is not None}
        if len(dims) != 1:
            raise RuntimeNotReady(f"keyframes carry OV features of different dimensions {sorted(dims)}")
        d = dims.pop()
        ow, oh = loaded.ov_wh
        ov = torch.stack(
            [e.ov.float() if e.ov is not None else torch.zeros(d, oh, ow, device=device) for e in entries]
        )
    has_depth = any(e.depth_m is not None or e.depth_prior is not None for e in entries)
    depth = None
    if has_depth:  # input depth, else the sparse prior (set_view_depth_prior), else none (0)
        w, h = loaded.image_wh
        depth = torch.stack(
            [
                e.depth_m if e.depth_m is not None
                else e.depth_prior if e.depth_prior is not None
                else torch.zeros(h, w, device=device)
                for e in entries
            ]
        )
    spaces = {e.ov_space for e in entries if e.ov is not None}
    volume_features, support = volume_and_support(loaded, model, *volume.statistics())
    prior_only = torch.tensor([e.depth_m is None and e.depth_prior is not None for e in entries],
                              device=device)
    input_depth = torch.tensor([e.depth_m is not None for e in entries], device=device)
    return Prepared(
        version=version,
        prior_only=prior_only,
        input_depth=input_depth,
        bounds=volume.bounds,
        volume=volume_features,
        rgb=torch.stack([e.rgb for e in entries]),
        features=torch.stack([e.features for e in entries]),
        ov=ov,
        has_ov=has_ov,
        depth_m=depth,
        K=torch.stack([e.K for e in entries]),
        world_from_cam=torch.stack([e.world_from_cam for e in entries]),
        ov_space=spaces.pop() if len(spaces) == 1 else None,
        support=support,
        extents=render_extents(entries),
    )


def volume_and_support(loaded: LoadedModel, model: GovNeSF, mean: Tensor, var: Tensor, count: Tensor
                       ) -> tuple[Tensor, Tensor | None]:
    """Cost-volume statistics (C, X, Y, Z) x 2 and (X, Y, Z) -> the 3D U-Net's volume (Dv, X, Y, Z)
    and the ``min_view_support`` mask (1, X, Y, Z) (None when that is off)."""
    volume = model.volume_features(cost_volume_features(mean, var, count).to(loaded.device))
    support = None
    if loaded.config.min_view_support > 1:
        support = (count >= loaded.config.min_view_support).to(loaded.device, torch.float32)[None]
    return volume, support


@torch.no_grad()
def render_prep(loaded: LoadedModel, model: GovNeSF, prep: Prepared, K: Tensor, world_from_cam: Tensor,
                width: int, height: int, n: int) -> Prepared:
    """``prep`` with the volume of the ``n`` keyframes that best overlap the view (K (4,) for
    width x height, world_from_cam (4, 4)) and its bounds, or ``prep`` itself: n = 0, a
    window of at most n keyframes, or fewer than 2 of them overlapping the view
    (``ModelRuntimeConfig.render_volume_views``)."""
    if n <= 0 or len(prep) <= n:
        return prep
    chosen = overlapping_views(loaded, prep, K, world_from_cam, width, height, n)
    if chosen.numel() < 2:
        return prep
    key = tuple(sorted(chosen.tolist()))  # the volume does not depend on the order
    local = prep.render_volumes.get(key)
    if local is not None:
        return local
    idx = torch.tensor(key, device=prep.K.device)
    vcfg = model.cfg.volume
    observed = torch.cat([prep.extents[i] for i in key]).cpu()
    lo, hi = torch.tensor(prep.bounds.origin_m), torch.tensor(prep.bounds.max_corner_m)
    # inside the window's box: a keyframe left out of its bounds (a wild pose) is no reason to
    # stretch this one
    observed = observed[((observed >= lo) & (observed <= hi)).all(dim=-1)]
    if observed.shape[0] < 2:
        return prep
    bounds = bounds_from_points(
        observed,
        max_voxels=loaded.config.max_voxels or vcfg.max_voxels,
        min_voxel_size_m=loaded.config.voxel_size_m or vcfg.min_voxel_size_m,
        margin_m=loaded.config.bounds_margin_m,
    )
    features, K_views, poses = prep.features[idx], prep.K[idx], prep.world_from_cam[idx]
    volume, support = volume_and_support(
        loaded, model, *build_cost_volume(bounds, features, K_views, poses, loaded.image_wh)
    )
    local = Prepared(
        version=prep.version, bounds=bounds, volume=volume, rgb=prep.rgb, features=prep.features,
        ov=prep.ov, has_ov=prep.has_ov, depth_m=prep.depth_m, K=prep.K,
        world_from_cam=prep.world_from_cam, ov_space=prep.ov_space, support=support,
        prior_only=prep.prior_only, extents=prep.extents, parent=prep, render_views=len(key),
    )
    if len(prep.render_volumes) >= RENDER_VOLUMES_KEPT:
        prep.render_volumes.pop(next(iter(prep.render_volumes)))
    prep.render_volumes[key] = local
    return local


def overlapping_views(loaded: LoadedModel, prep: Prepared, K: Tensor, world_from_cam: Tensor, width: int,
                      height: int, n: int) -> Tensor:
    """(k,) long, k <= n: the views whose observed points fall most inside the view (share of
    each view's extent points in front of the camera, at most ``far_m`` away, inside the
    image; the training's ``overlap_scores``), best first; views with no point inside are
    left out. Ties go to the camera nearest the view's, then to the older keyframe."""
    counts = torch.tensor([e.shape[0] for e in prep.extents])
    points = torch.cat(prep.extents).to(torch.float32)
    cam_from_world = invert_pose(world_from_cam.to(points))
    uv, z = project_points(points[None], K.to(points)[None], cam_from_world[None])
    seen = in_view(uv, z, width, height)[0] & (z[0] <= loaded.config.far_m)
    view_of = torch.repeat_interleave(torch.arange(len(counts)), counts).to(seen.device)
    inside = torch.zeros(len(counts), device=seen.device).index_add_(0, view_of, seen.to(torch.float32))
    share = (inside.cpu() / counts.clamp_min(1)).to(torch.float64)
    centre = world_from_cam[:3, 3].to(prep.world_from_cam)
    distance = (prep.world_from_cam[:, :3, 3] - centre).norm(dim=-1).cpu()
    by_distance = torch.argsort(distance, stable=True)
    order = by_distance[torch.argsort(-share[by_distance], stable=True)][:n]
    return order[share[order] > 0]
