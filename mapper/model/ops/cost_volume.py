"""Cost volume: per-voxel mean and variance of the 2D features of the views that see the voxel.

Two implementations of the same quantity:

* ``build_cost_volume`` -- batch, differentiable, readable (training; reference in the tests).
* ``CostVolume`` -- incremental, for the streaming node: ``add_view`` / ``remove_view`` update
  float64 running sums (count n, sum s, sum of squares q) of only the voxels the view sees, so
  ``mean = s / n`` and ``variance = q / n - mean^2`` (population variance, clamped at 0).

A voxel counts a view only if its centre projects inside that view's image with ``z > eps``;
views that do not see a voxel do not enter its statistics (the official code let them add
zeros to the variance).

Grid convention: ``VolumeBounds.origin_m`` is the MIN CORNER of the grid; voxel (i, j, k) spans
``origin + [i, i+1) * voxel_size`` (etc.) and its centre is ``origin + (i + 0.5) * voxel_size``.
Tensors are laid out (C, X, Y, Z) with world x, y, z along dims 1, 2, 3.

Memory trade-off of ``CostVolume``: per view it keeps the view's INPUTS (feature map C x h x w,
K, pose) and recomputes the voxel samples on removal, instead of storing the voxel indices and
sampled features it contributed (M x (C + 1) numbers, M up to X*Y*Z). At the paper's sizes
(C=32, 80x60 map, 25,600 voxels) that is 0.6 MB instead of up to 3.4 MB a view, it is
independent of the volume size, and it lets ``rebuild`` move the volume to new bounds. The cost
is one projection + sampling pass on removal (as cheap as the add).
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.checks import check_shape
from mapper.model.ops.geometry import in_view, invert_pose, project_points, sample_bilinear, scale_uv

__all__ = [
    "CostVolume",
    "VolumeBounds",
    "bounds_from_points",
    "build_cost_volume",
    "cost_volume_features",
    "sample_volume",
    "voxel_view_samples",
]


@dataclass(frozen=True)
class VolumeBounds:
    """An axis-aligned voxel grid in the world frame."""

    origin_m: tuple[float, float, float]
    """Min corner of the grid (m)."""
    voxel_size_m: float
    """Edge length of a cubic voxel (m)."""
    dims: tuple[int, int, int]
    """Number of voxels (X, Y, Z)."""

    def __post_init__(self) -> None:
        if len(self.origin_m) != 3 or not all(math.isfinite(v) for v in self.origin_m):
            raise ValueError(f"origin_m must be 3 finite numbers, got {self.origin_m}")
        if not (math.isfinite(self.voxel_size_m) and self.voxel_size_m > 0):
            raise ValueError(f"voxel_size_m {self.voxel_size_m} out of range: must be > 0")
        if len(self.dims) != 3 or min(self.dims) < 1:
            raise ValueError(f"dims {self.dims} out of range: three integers >= 1")

    @property
    def num_voxels(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]

    @property
    def max_corner_m(self) -> tuple[float, float, float]:
        return tuple(o + d * self.voxel_size_m for o, d in zip(self.origin_m, self.dims, strict=True))  # type: ignore[return-value]

    def voxel_centers(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
        """(X*Y*Z, 3) voxel centres in the world frame, flattened in (x, y, z) C order."""
        axes = [
            (torch.arange(n, dtype=torch.float64, device=device) + 0.5) * self.voxel_size_m + o
            for n, o in zip(self.dims, self.origin_m, strict=True)
        ]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # (X, Y, Z, 3)
        return grid.reshape(-1, 3).to(dtype)


def bounds_from_points(
    points_m: Tensor,
    *,
    voxel_size_m: float | None = None,
    max_voxels: int = 40 * 40 * 16,
    min_voxel_size_m: float = 0.04,
    margin_m: float = 0.2,
    quantile: float = 0.01,
    dims_multiple: int = 4,
) -> VolumeBounds:
    """Choose a volume that covers observed points (bounds follow the scene).

    The extent is the [quantile, 1 - quantile] range of the points per axis (robust to stray
    depth) plus ``margin_m``. Without a given ``voxel_size_m``, the voxel size is the smallest
    size on the ladder ``min_voxel_size_m * 2^(k/4)`` for which the grid has at most
    ``max_voxels`` voxels; a ladder (not a continuous value) and an origin snapped to a multiple
    of the voxel size keep the grid stable while the observed bounds grow little by little.
    Dims are rounded up to ``dims_multiple`` (the 3D U-Net halves the grid twice).

    Args:
        points_m: (N, 3) world points (non-finite rows are ignored), N >= 1 finite.

    Returns:
        VolumeBounds.
    """
    check_shape(points_m, "N 3", "points_m")
    pts = points_m.detach().to(torch.float64)
    pts = pts[torch.isfinite(pts).all(dim=-1)]
    if pts.shape[0] == 0:
        raise ValueError("bounds_from_points needs at least one finite point, got none")
    if not 0.0 <= quantile < 0.5:
        raise ValueError(f"quantile {quantile} out of range [0, 0.5)")
    if max_voxels < dims_multiple**3:
        raise ValueError(f"max_voxels {max_voxels} out of range: must be >= {dims_multiple**3}")
    if pts.shape[0] > 1_000_000:  # torch.quantile size limit; a strided subset is plenty
        pts = pts[:: pts.shape[0] // 1_000_000 + 1]
    lo = torch.quantile(pts, quantile, dim=0) - margin_m
    hi = torch.quantile(pts, 1.0 - quantile, dim=0) + margin_m

    def grid_for(size: float) -> tuple[tuple[float, float, float], tuple[int, int, int]]:
        origin = torch.floor(lo / size) * size
        counts = torch.ceil((hi - origin) / size).clamp_min(1)
        counts = torch.ceil(counts / dims_multiple) * dims_multiple
        return tuple(origin.tolist()), tuple(int(c) for c in counts.tolist())  # type: ignore[return-value]

    if voxel_size_m is not None:
        origin, dims = grid_for(voxel_size_m)
        return VolumeBounds(origin, float(voxel_size_m), dims)
    extent = (hi - lo).clamp_min(min_voxel_size_m)
    ideal = float((extent.prod() / max_voxels) ** (1.0 / 3.0))
    k = max(0, math.floor(4 * math.log2(max(ideal, min_voxel_size_m) / min_voxel_size_m)))
    while True:
        size = min_voxel_size_m * 2.0 ** (k / 4)
        origin, dims = grid_for(size)
        if dims[0] * dims[1] * dims[2] <= max_voxels:
            return VolumeBounds(origin, size, dims)
        k += 1


def voxel_view_samples(
    bounds: VolumeBounds,
    features: Tensor,
    K: Tensor,
    world_from_cam: Tensor,
    image_wh: tuple[int, int],
    voxel_centers: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The voxels one view sees and the features it gives them.

    Args:
        features: (C, h, w) feature map of the view (any resolution covering the image).
        K: (4,) intrinsics for the image of size ``image_wh = (W, H)``.
        world_from_cam: (4, 4).
        voxel_centers: (X*Y*Z, 3) precomputed ``bounds.voxel_centers`` (optional).

    Returns:
        indices: (M,) long flat voxel indices whose centre projects inside the image, z > eps.
        values: (M, C) bilinearly sampled features there.
    """
    centers = (
        bounds.voxel_centers(features.dtype, features.device) if voxel_centers is None else voxel_centers
    )
    uv, z = project_points(centers, K.to(centers), invert_pose(world_from_cam.to(centers)))
    visible = in_view(uv, z, image_wh[0], image_wh[1])
    indices = visible.nonzero().squeeze(-1)
    uv_f = scale_uv(uv[indices], image_wh, (features.shape[-1], features.shape[-2]))
    values, _ = sample_bilinear(features, uv_f)
    return indices, values


def build_cost_volume(
    bounds: VolumeBounds,
    features: Tensor,
    K: Tensor,
    world_from_cam: Tensor,
    image_wh: tuple[int, int],
) -> tuple[Tensor, Tensor, Tensor]:
    """Batch (differentiable) cost volume from N views.

    Args:
        features: (N, C, h, w); K: (N, 4); world_from_cam: (N, 4, 4); image_wh: (W, H).

    Returns:
        mean: (C, X, Y, Z), variance: (C, X, Y, Z) over the views that see each voxel (0 where
        none does), count: (X, Y, Z) number of such views (float).
    """
    check_shape(features, "N C h w", "features")
    n_views, channels = features.shape[:2]
    centers = bounds.voxel_centers(features.dtype, features.device)  # (V, 3)
    uv, z = project_points(
        centers.expand(n_views, -1, -1), K.to(centers), invert_pose(world_from_cam.to(centers))
    )  # (N, V, 2), (N, V)
    mask = in_view(uv, z, image_wh[0], image_wh[1]).to(features.dtype)  # (N, V)
    uv_f = scale_uv(uv, image_wh, (features.shape[-1], features.shape[-2]))
    values, _ = sample_bilinear(features, uv_f)  # (N, V, C)
    count = mask.sum(dim=0)  # (V,)
    denom = count.clamp_min(1.0).unsqueeze(-1)
    mean = (values * mask.unsqueeze(-1)).sum(dim=0) / denom  # (V, C)
    var = (((values - mean) ** 2) * mask.unsqueeze(-1)).sum(dim=0) / denom
    shape = (channels, *bounds.dims)
    return mean.T.reshape(shape), var.T.reshape(shape), count.reshape(bounds.dims)


def cost_volume_features(mean: Tensor, variance: Tensor, count: Tensor) -> Tensor:
    """Network input from cost-volume statistics.

    Args:
        mean, variance: (C, X, Y, Z); count: (X, Y, Z).

    Returns:
        (2C + 1, X, Y, Z): ``[mean, exp(-variance), 1 - 1 / (1 + count)]``. For unseen voxels the
        agreement channel ``exp(-variance)`` is 0 (not 1, which would claim perfect agreement) and
        the last channel, 0 for unseen voxels and rising towards 1 with more views, tells the
        network how much evidence there is.
    """
    seen = (count > 0).to(mean.dtype)
    agreement = torch.exp(-variance) * seen
    support = (1.0 - 1.0 / (1.0 + count)).to(mean.dtype)
    return torch.cat([mean, agreement, support.unsqueeze(0)], dim=0)


def sample_volume(volume: Tensor, bounds: VolumeBounds, points_m: Tensor) -> tuple[Tensor, Tensor]:
    """Trilinearly sample a (C, X, Y, Z) volume at world points.

    Voxel values sit at voxel centres; between the outermost centres and the grid faces the face
    value is replicated; outside the grid the result is 0 and ``inside`` is False.

    Args:
        volume: (C, X, Y, Z); points_m: (..., 3).

    Returns:
        values: (..., C) and inside: (...,) bool (point within the closed grid box).
    """
    check_shape(volume, "C X Y Z", "volume (C, bounds.dims)", dict(zip("XYZ", bounds.dims, strict=True)))
    lead = points_m.shape[:-1]
    pts = points_m.reshape(-1, 3)
    origin = pts.new_tensor(bounds.origin_m)
    dims = pts.new_tensor(bounds.dims)
    cont = (pts - origin) / bounds.voxel_size_m  # continuous voxel coordinates, faces at 0 and dims
    inside = ((cont >= 0) & (cont <= dims)).all(dim=-1)
    norm = (2.0 * cont / dims - 1.0).clamp(-2.0, 2.0)
    # grid_sample's last grid dim is (W, H, D) = (Z, Y, X) for an input laid out (C, X, Y, Z).
    grid = norm.flip(-1).reshape(1, -1, 1, 1, 3).to(volume.dtype)
    out = F.grid_sample(
        volume.unsqueeze(0), grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    values = out.reshape(volume.shape[0], -1).T * inside.unsqueeze(-1).to(volume.dtype)
    return values.reshape(*lead, volume.shape[0]), inside.reshape(lead)


@dataclass
class _StoredView:
    features: Tensor  # (C, h, w) on the volume's device, float32
    K: Tensor  # (4,)
    world_from_cam: Tensor  # (4, 4)
    image_wh: tuple[int, int]


class CostVolume:
    """Incrementally updated cost volume (streaming node; no autograd).

    Example:
        >>> import torch
        >>> bounds = VolumeBounds((-1.0, -1.0, 1.0), 0.5, (4, 4, 4))
        >>> volume = CostVolume(bounds, feature_dim=2)
        >>> K = torch.tensor([8.0, 8.0, 4.0, 3.0])
        >>> volume.add_view("kf0", torch.ones(2, 6, 8), K, torch.eye(4), (8, 6))  # voxels touched
        44
        >>> volume.as_tensor().shape
        torch.Size([5, 4, 4, 4])
        >>> volume.remove_view("kf0"), int(volume.as_tensor()[-1].sum())
        (44, 0)
    """

    def __init__(self, bounds: VolumeBounds, feature_dim: int, device: torch.device | str = "cpu") -> None:
        if feature_dim < 1:
            raise ValueError(f"feature_dim {feature_dim} out of range: must be >= 1")
        self.feature_dim = feature_dim
        self.device = torch.device(device)
        self._views: dict[Hashable, _StoredView] = {}
        self._set_bounds(bounds)

    def _set_bounds(self, bounds: VolumeBounds) -> None:
        self.bounds = bounds
        n_vox = bounds.num_voxels
        self._count = torch.zeros(n_vox, dtype=torch.float64, device=self.device)
        self._sum = torch.zeros(n_vox, self.feature_dim, dtype=torch.float64, device=self.device)
        self._sumsq = torch.zeros_like(self._sum)
        self._centers = bounds.voxel_centers(torch.float32, self.device)

    @property
    def view_ids(self) -> list[Hashable]:
        return list(self._views)

    def __len__(self) -> int:
        return len(self._views)

    def _samples(self, view: _StoredView) -> tuple[Tensor, Tensor]:
        indices, values = voxel_view_samples(
            self.bounds,
            view.features,
            view.K,
            view.world_from_cam,
            view.image_wh,
            voxel_centers=self._centers,
        )
        return indices, values.to(torch.float64)

    @torch.no_grad()
    def add_view(
        self,
        view_id: Hashable,
        features: Tensor,
        K: Tensor,
        world_from_cam: Tensor,
        image_wh: tuple[int, int],
    ) -> int:
        """Add a view's features to the voxels it sees.

        Args:
            view_id: unique key (e.g. keyframe id); features: (C, h, w); K: (4,) for the image of
            ``image_wh = (W, H)`` pixels; world_from_cam: (4, 4).

        Returns:
            number of voxels the view touched.
        """
        if view_id in self._views:
            raise ValueError(f"view {view_id!r} is already in the cost volume; remove it first")
        check_shape(features, "C h w", f"features must have shape ({self.feature_dim}, h, w)",
                    {"C": self.feature_dim})
        check_shape(K, "4", "K")
        check_shape(world_from_cam, "4 4", "world_from_cam")
        if len(image_wh) != 2 or min(image_wh) < 1:
            raise ValueError(f"image_wh {image_wh} out of range: (W, H) with W, H >= 1")
        view = _StoredView(
            features.detach().to(self.device, torch.float32),
            K.detach().to(self.device, torch.float32),
            world_from_cam.detach().to(self.device, torch.float32),
            (int(image_wh[0]), int(image_wh[1])),
        )
        indices, values = self._samples(view)
        self._count.index_add_(0, indices, torch.ones_like(indices, dtype=torch.float64))
        self._sum.index_add_(0, indices, values)
        self._sumsq.index_add_(0, indices, values * values)
        self._views[view_id] = view
        return int(indices.numel())

    @torch.no_grad()
    def remove_view(self, view_id: Hashable) -> int:
        """Remove a view's contribution (recomputed from its stored inputs); returns voxels touched."""
        if view_id not in self._views:
            raise KeyError(f"view {view_id!r} is not in the cost volume (have {len(self._views)} views)")
        view = self._views.pop(view_id)
        indices, values = self._samples(view)
        self._count.index_add_(0, indices, -torch.ones_like(indices, dtype=torch.float64))
        self._sum.index_add_(0, indices, -values)
        self._sumsq.index_add_(0, indices, -values * values)
        # Voxels no view sees any more are reset exactly (no float residue left behind).
        empty = indices[self._count[indices] <= 0.5]
        self._count[empty] = 0.0
        self._sum[empty] = 0.0
        self._sumsq[empty] = 0.0
        return int(indices.numel())

    @torch.no_grad()
    def rebuild(self, bounds: VolumeBounds | None = None) -> None:
        """Recompute everything from the stored views, optionally on new bounds."""
        views = self._views
        self._views = {}
        self._set_bounds(self.bounds if bounds is None else bounds)
        for view_id, view in views.items():
            self.add_view(view_id, view.features, view.K, view.world_from_cam, view.image_wh)

    def statistics(self) -> tuple[Tensor, Tensor, Tensor]:
        """mean (C, X, Y, Z), variance (C, X, Y, Z), count (X, Y, Z), all float32."""
        count = self._count
        denom = count.clamp_min(1.0).unsqueeze(-1)
        mean = self._sum / denom
        var = (self._sumsq / denom - mean * mean).clamp_min(0.0)
        shape = (self.feature_dim, *self.bounds.dims)
        return (
            mean.T.reshape(shape).float(),
            var.T.reshape(shape).float(),
            count.reshape(self.bounds.dims).float(),
        )

    def as_tensor(self, include_count: bool = True) -> Tensor:
        """(2C [+ 1], X, Y, Z) float32: [mean, variance (, count)]."""
        mean, var, count = self.statistics()
        parts = [mean, var] + ([count.unsqueeze(0)] if include_count else [])
        return torch.cat(parts, dim=0)

    def network_input(self) -> Tensor:
        """(2C + 1, X, Y, Z) float32 ``cost_volume_features`` (what the 3D U-Net consumes)."""
        return cost_volume_features(*self.statistics())
