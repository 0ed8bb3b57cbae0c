"""View selection: which source views answer a point or a marched sample.

Points are bucketed into cells of ``view_cell_m``; for each cell the ``k`` views that see the most of
its points (ties and partial visibility ranked by distance, or by how frontally they see it with
``view_selection = "frontal"``) are its source views, and cells with the same view set are evaluated
together (:func:`view_groups`). Inside a set, the network masks every view that does not see the
individual point, so a point only ever uses views that see it. With ``depth_m`` a view sees a point
only where that depth agrees with it (the Depth Guided Masking test, :func:`depth_agrees`).

:func:`group_slots` lays the groups out for one network pass over all of them (each point with its
own views, padding masked); :func:`all_views` / :func:`source_views` hand the window's views to the
network as :class:`~mapper.model.field.SourceViews`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.model.field import SourceViews
from mapper.model.ops.geometry import DEFAULT_EPS, camera_centers, in_view, invert_pose, project_points
from mapper.runtime.loading import LoadedModel
from mapper.runtime.prepared import Prepared


def group_slots(groups: Sequence[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor, Tensor]:
    """View groups ``[(point_indices (p,), view_indices (k,)), ...]`` -> the points of every group
    (G,), each one's views (G, k_max) and slot mask (G, k_max) (False = padding, a masked view).
    Groups come largest view set first, so that a chunk of consecutive points can drop the padding
    columns none of its points uses (:func:`chunk_slots`)."""
    k_max = max(int(views.numel()) for _, views in groups)
    members, view_idx, slots = [], [], []
    for idx, views in sorted(groups, key=lambda g: -int(g[1].numel())):
        n, k = int(idx.numel()), int(views.numel())
        padded = torch.zeros(k_max, dtype=torch.long, device=idx.device)
        padded[:k] = views
        mask = torch.zeros(k_max, dtype=torch.bool, device=idx.device)
        mask[:k] = True
        members.append(idx)
        view_idx.append(padded.expand(n, k_max))
        slots.append(mask.expand(n, k_max))
    return torch.cat(members), torch.cat(view_idx), torch.cat(slots)


def chunk_slots(view_idx: Tensor, slots: Tensor, sel: slice) -> tuple[Tensor, Tensor]:
    """Rows ``sel`` of :func:`group_slots`' (G, k_max) views and slot mask, without the trailing
    padding columns that no row of the chunk uses (padding is masked: the answers are the same)."""
    s = slots[sel]
    k = max(1, int(s.sum(dim=1).max())) if s.shape[0] else 1
    return view_idx[sel, :k], s[:, :k]


def cell_view_sets(order: Tensor, chosen: Tensor, n_views: int) -> tuple[Tensor, list[Tensor]]:
    """Group cells by their set of chosen views: ``order`` (C, k) view indices, ``chosen`` (C, k)
    bool, views 0..n_views-1. Returns each cell's group (C,) long (-1 for a cell with no chosen
    view) and each group's views (ascending), groups in the order of their first cell. Equal to
    collecting ``tuple(sorted(chosen views))`` per cell in a dict, without a Python loop over
    cells."""
    n_cells = order.shape[0]
    rows = torch.where(chosen, order, torch.full_like(order, n_views)).sort(dim=1).values  # unused last
    if n_views <= 62:  # each set as one int64 bit mask: a 1-D unique, several times faster than by rows
        bits = torch.where(chosen, torch.bitwise_left_shift(torch.ones_like(order), order), 0).sum(dim=1)
        _, inverse = torch.unique(bits, return_inverse=True)  # a cell's views are distinct: the sum is the OR
        n_groups = int(inverse.max()) + 1 if n_cells else 0
    else:
        uniq, inverse = torch.unique(rows, dim=0, return_inverse=True)  # (G, k), (C,)
        n_groups = uniq.shape[0]
    first = torch.full((n_groups,), n_cells, dtype=torch.long, device=order.device)
    first.scatter_reduce_(0, inverse, torch.arange(n_cells, device=order.device), reduce="amin")
    uniq = rows[first]  # (G, k) each group's sorted views (and the unused marks)
    by_first = torch.argsort(first)  # groups in the order of their first cell
    non_empty = uniq[by_first, 0] < n_views
    kept = by_first[non_empty]
    new_id = torch.full((uniq.shape[0],), -1, dtype=torch.long, device=order.device)
    new_id[kept] = torch.arange(kept.numel(), device=order.device)
    keys = [row[row < n_views] for row in uniq[kept]]
    return new_id[inverse], keys


def cell_inverse(cell: Tensor) -> Tensor:
    """``torch.unique(cell, dim=0, return_inverse=True)[1]`` for (P, 3) int64 cells: the same
    indices (cells in lexicographic order), from a 1-D unique of one int64 key per cell (the
    row-wise unique is several times slower on the CPU)."""
    lo = cell.amin(dim=0)
    span = cell.amax(dim=0) - lo + 1  # (3,)
    if bool((span.double().prod() >= 2**62).item()):  # keys would overflow: the row-wise unique
        return torch.unique(cell, dim=0, return_inverse=True)[1]
    c = cell - lo
    key = (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]
    return torch.unique(key, return_inverse=True)[1]


def view_groups(
    loaded: LoadedModel, prep: Prepared, points: Tensor, allowed: Tensor, k: int | None = None,
    depth_m: Tensor | None = None,
) -> list[tuple[Tensor, Tensor]]:
    """Split (P, 3) points into groups sharing a source-view set.

    Returns ``[(point_indices (p,), view_indices (k,)), ...]``; points no allowed view sees
    are in no group. With at most ``source_views`` allowed views there is one group (views
    that do not see a point are masked per point by the network). ``k``: views per group
    (default ``source_views``). ``depth_m`` (M, H, W): a view sees a point only where this
    depth agrees with it (or has none), the DGM test (``dgm_view_selection``), so the views
    chosen are the ones DGM keeps.
    """
    candidates = allowed.nonzero().squeeze(-1)
    k = loaded.source_views if k is None else k
    n_points = points.shape[0]
    if n_points == 0 or candidates.numel() == 0:
        return []
    width, height = loaded.image_wh
    cam_from_world = invert_pose(prep.world_from_cam[candidates])  # (M, 4, 4)
    Ks = prep.K[candidates]
    cpu_kernels = (points.device.type == "cpu"
                   and points.dtype == cam_from_world.dtype == Ks.dtype == torch.float32)
    if cpu_kernels and depth_m is not None:  # in view and passing the depth test, one compiled pass
        from mapper.model.ops.occlusion_kernel import depth_test_matrix

        ratio = loaded.require_model().cfg.render.depth_mask_ratio
        vis = torch.from_numpy(depth_test_matrix(points.numpy(), cam_from_world.numpy(), Ks.numpy(),
                                                 (width, height), DEFAULT_EPS,
                                                 depth_m[candidates].float().numpy(), ratio,
                                                 threads=torch.get_num_threads()))  # (P, M)
    elif cpu_kernels:
        from mapper.kernels.average_kernel import in_view_matrix

        vis = torch.from_numpy(in_view_matrix(points.numpy(), cam_from_world.numpy(), Ks.numpy(),
                                              (width, height), DEFAULT_EPS,
                                              threads=torch.get_num_threads()))  # (P, M)
    else:  # off the CPU kernels (CUDA): in view and, with depth_m, the DGM test of one projection
        view_depth = None if depth_m is None else depth_m[candidates]
        vis_parts = []
        for i in range(0, n_points, 65536):
            chunk = points[i : i + 65536]
            uv, z = project_points(chunk.unsqueeze(0).expand(len(candidates), -1, -1), Ks, cam_from_world)
            ok = in_view(uv, z, width, height)  # (M, p)
            if view_depth is not None:
                ok = ok & depth_agrees(loaded, uv, z, view_depth)
            vis_parts.append(ok.T)  # (p, M)
        vis = torch.cat(vis_parts)  # (P, M)
    seen = vis.any(dim=1)
    if candidates.numel() <= k:
        idx = seen.nonzero().squeeze(-1)
        return [(idx, candidates)] if idx.numel() else []
    inverse = cell_inverse(torch.floor(points / loaded.config.view_cell_m).long())
    n_cells = int(inverse.max()) + 1
    counts = torch.zeros(n_cells, len(candidates), device=loaded.device).index_add_(0, inverse, vis.float())
    n_in = torch.zeros(n_cells, device=loaded.device).index_add_(0, inverse, torch.ones_like(points[:, 0]))
    centre = torch.zeros(n_cells, 3, device=loaded.device).index_add_(0, inverse, points) / n_in[:, None]
    cams = camera_centers(prep.world_from_cam[candidates])  # (M, 3)
    offset = centre[:, None, :] - cams[None, :, :]  # (C, M, 3)
    if loaded.config.view_selection == "frontal":
        axis = prep.world_from_cam[candidates][:, :3, 2]  # (M, 3) optical axes
        key = -(F.normalize(offset, dim=-1) * axis[None]).sum(-1)  # in [-1, 1]
    else:
        key = offset.norm(dim=-1).clamp_max(1e5)
    frac = counts / n_in[:, None]
    tier = torch.where(frac >= 0.5, 0.0, torch.where(frac > 0, 1.0, 2.0))
    order = torch.argsort(tier * 1e6 + key, dim=1)[:, :k]  # (C, k)
    chosen_ok = torch.gather(tier, 1, order) < 2
    cell_group, keys = cell_view_sets(order, chosen_ok, len(candidates))
    point_group = torch.where(seen, cell_group[inverse], torch.full_like(inverse, -1))
    # each group's points in ascending order, from one stable sort (was a scan per group)
    by_group = torch.argsort(point_group, stable=True)
    sizes = torch.bincount(point_group + 1, minlength=len(keys) + 1).tolist()  # [unseen, g0, g1, ...]
    parts = torch.split(by_group, sizes)
    out = []
    for g, views in enumerate(keys):
        idx = parts[g + 1]
        if idx.numel():
            out.append((idx, candidates[views]))
    return out


def all_views(
    loaded: LoadedModel, prep: Prepared, need_ov: bool, use_depth: bool, depth_m: Tensor | None = None
) -> SourceViews:
    """Every view of the window as one SourceViews (no copies), for ``sample_views_indexed``.
    ``depth_m`` (M, H, W): the depth DGM tests against instead of the window's (``points.occluder_depth``)."""
    if need_ov:
        assert prep.ov is not None
        ov = prep.ov
    else:  # the OV branch is not needed: a 1-channel dummy keeps sampling cheap
        ov = torch.zeros(len(prep), 1, 1, 1, device=loaded.device)
    depth = (prep.depth_m if depth_m is None else depth_m) if use_depth else None
    return SourceViews(prep.rgb, prep.features, ov, prep.K, prep.world_from_cam, depth)


def source_views(
    loaded: LoadedModel, prep: Prepared, view_idx: Tensor, need_ov: bool, use_depth: bool,
    depth_m: Tensor | None = None,
) -> SourceViews:
    """The views ``view_idx`` (k,) of the window as one SourceViews (copies); the OV maps only with
    ``need_ov`` (else a 1-channel dummy), the depth only with ``use_depth``. ``depth_m``: see
    :func:`all_views`."""
    if need_ov:
        assert prep.ov is not None
        ov = prep.ov[view_idx]
    else:  # the OV branch is not needed: a 1-channel dummy keeps sampling cheap
        ov = torch.zeros(len(view_idx), 1, 1, 1, device=loaded.device)
    window_depth = prep.depth_m if depth_m is None else depth_m
    depth = window_depth[view_idx] if (use_depth and window_depth is not None) else None
    return SourceViews(
        rgb=prep.rgb[view_idx],
        features=prep.features[view_idx],
        ov=ov,
        K=prep.K[view_idx],
        world_from_cam=prep.world_from_cam[view_idx],
        depth_m=depth,
    )


def depth_agrees(
    loaded: LoadedModel,
    uv: Tensor,  # (M, p, 2) pixel coordinates at the working size
    z: Tensor,  # (M, p) z-depth
    depth_m: Tensor,  # (M, H, W) at the working size, 0 = none
) -> Tensor:  # (M, p) bool
    """The DGM test of ``GovNeSF.sample_views`` for every (view, point): the view's depth at
    the point's pixel (nearest) agrees with the point's z within ``depth_mask_ratio``, or the
    view has no depth there (points outside the image: its clamped edge pixel)."""
    ratio = loaded.require_model().cfg.render.depth_mask_ratio
    m, height, width = depth_m.shape
    col = uv[..., 0].nan_to_num(0.0).floor().clamp(0, width - 1).long()
    row = uv[..., 1].nan_to_num(0.0).floor().clamp(0, height - 1).long()
    measured = depth_m.reshape(m, -1).gather(1, row * width + col)  # (M, p)
    has = torch.isfinite(measured) & (measured > 0)
    return ((z - measured).abs() <= ratio * measured) | ~has
