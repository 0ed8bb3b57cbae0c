"""The GOV-NeSF field: source views + volume features -> density, colour and OV features at points.

Pipeline for query points p (R rays x S samples):

1. Project p into every source view; a view counts for p only if p is in front of it and inside
   its image (and, with Depth Guided Masking, if p's depth agrees with the view's depth map).
2. Bilinearly sample rgb, 2D feature and OV feature there; trilinearly sample v = V_a(p).
3. FusionNet blends colours (query-direction dependent) and OV features (source-view agnostic);
   sigma = DensityMLP(v), 0 outside the volume.

``render_rays`` composites along rays; the OV features are composited with DETACHED weights so
the OV loss never trains the density (2D OV maps are not view-consistent). It, ``render_depth_maps``
and the node's runtime all march with ``mapper.model.render.march_rays`` (the one ray marcher).

Point mode (``query_points``): the source-view-agnostic OV feature at given points, each a single
sample (3D segmentation). Distill mode (``mode="distill"``): the OV feature is regressed by
``DistillHead`` instead of blended (the paper's Distill baseline).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapper.checks import check_shape
from mapper.model.config import ModelConfig
from mapper.model.encoder2d import ImageEncoder
from mapper.model.fusion import (
    DensityMLP,
    DistillHead,
    FusionNet,
    blend,
    blend_from_maps,
    cosines_from_maps,
)
from mapper.model.ops.cost_volume import VolumeBounds, build_cost_volume, cost_volume_features, sample_volume
from mapper.model.ops.geometry import (
    DEFAULT_EPS,
    camera_centers,
    in_view,
    invert_pose,
    pixel_rays,
    project_points,
    sample_bilinear,
    sample_nearest,
    scale_uv,
)
from mapper.model.ops.rendering import Rays
from mapper.model.render import march_rays
from mapper.model.unet3d import VolumeUNet

if TYPE_CHECKING:
    from mapper.model.ops.sample_kernel import PairArgs

__all__ = [
    "FieldOutputs",
    "GovNeSF",
    "OVMaps",
    "PointOutputs",
    "RenderOutputs",
    "SourceViews",
    "default_device",
    "render_image",
    "render_depth_maps",
    "render_rays",
]


def default_device() -> torch.device:
    """CUDA when available, else CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


@dataclass
class SourceViews:
    """N posed source views with their sampled maps."""

    rgb: Tensor
    """(N, 3, H, W) colours in [0, 1]."""
    features: Tensor
    """(N, F, h, w) 2D encoder features (any resolution covering the image)."""
    ov: Tensor
    """(N, D, h_ov, w_ov) open-vocabulary feature maps (any resolution covering the image)."""
    K: Tensor
    """(N, 4) intrinsics [fx, fy, cx, cy] for the (W, H) image."""
    world_from_cam: Tensor
    """(N, 4, 4) camera-to-world poses."""
    depth_m: Tensor | None = None
    """(N, H_d, W_d) optional z-depth maps (m); 0 or non-finite = no measurement."""
    _channel_last: tuple[Tensor, Tensor, Tensor] | None = field(default=None, init=False, repr=False,
                                                                compare=False)

    def __post_init__(self) -> None:
        n = self.rgb.shape[0]
        checks = [
            (self.rgb.ndim == 4 and self.rgb.shape[1] == 3, "rgb (N, 3, H, W)", self.rgb.shape),
            (
                self.features.ndim == 4 and self.features.shape[0] == n,
                "features (N, F, h, w)",
                self.features.shape,
            ),
            (self.ov.ndim == 4 and self.ov.shape[0] == n, "ov (N, D, h, w)", self.ov.shape),
            (tuple(self.K.shape) == (n, 4), "K (N, 4)", self.K.shape),
            (
                tuple(self.world_from_cam.shape) == (n, 4, 4),
                "world_from_cam (N, 4, 4)",
                self.world_from_cam.shape,
            ),
        ]
        if self.depth_m is not None:
            checks.append(
                (
                    self.depth_m.ndim == 3 and self.depth_m.shape[0] == n,
                    "depth_m (N, H, W)",
                    self.depth_m.shape,
                )
            )
        for ok, expected, got in checks:
            if not ok:
                raise ValueError(f"SourceViews: expected {expected} with N={n}, got {tuple(got)}")

    @property
    def image_wh(self) -> tuple[int, int]:
        return int(self.rgb.shape[-1]), int(self.rgb.shape[-2])

    def channel_last(self) -> tuple[Tensor, Tensor, Tensor]:
        """``rgb``, ``features`` and ``ov`` as (N * h * w, C) channel-last, view-major tables (the
        layout of ``fusion.blend_from_maps``), made once per SourceViews (the maps must not change)."""
        if self._channel_last is None:
            rgb, features, ov = (m.permute(0, 2, 3, 1).reshape(-1, m.shape[1]).contiguous()
                                 for m in (self.rgb, self.features, self.ov))
            self._channel_last = (rgb, features, ov)
        return self._channel_last

    def __len__(self) -> int:
        return int(self.rgb.shape[0])


@dataclass
class PointViewSamples:
    """What each source view says about each point."""

    rgb: Tensor  # (P, N, 3)
    features: Tensor  # (P, N, F)
    ov: Tensor  # (P, N, D)
    mask: Tensor  # (P, N) bool: the view sees the point (and passes depth masking)
    source_dirs: Tensor  # (P, N, 3) unit directions source camera -> point
    uv: Tensor | None = None  # (P, N, 2) pixel coordinates in the source images (sample_views)
    source_range: Tensor | None = None  # (P, N) distances (m) source camera -> point


@dataclass
class OVMaps:
    """The source views' OV maps as one gather table, for :meth:`GovNeSF.point_outputs` to blend
    without sampling them first (``fusion.blend_from_maps``): sample the views with a 1-channel
    dummy ``ov`` and pass this instead."""

    table: Tensor  # (M * h * w, D) channel-last, view-major
    map_wh: tuple[int, int]  # (w, h) of each OV map
    view_idx: Tensor  # (N,) or (P, N) long: the table view behind each sampled slot
    image_wh: tuple[int, int]  # (W, H) of the images ``uv`` is in


@dataclass
class FieldOutputs:
    """Field values at R x S query points."""

    sigma: Tensor
    """(R, S) density (1/m), 0 outside the volume."""
    rgb: Tensor
    """(R, S, 3) blended colour (0 where no view sees the point)."""
    ov: Tensor
    """(R, S, D) blended (or, in distill mode, regressed) OV feature."""
    valid: Tensor
    """(R, S) bool: at least one source view sees the point."""


@dataclass
class PointOutputs:
    """Point-mode OV features."""

    ov: Tensor
    """(P, D) source-view-agnostic OV feature (0 where no view sees the point)."""
    valid: Tensor
    """(P,) bool: at least one view sees the point."""
    num_views: Tensor
    """(P,) long: number of views that see the point (evaluation keeps points seen by > 1)."""
    ov_weights: Tensor | None = None
    """(P, N) the OV blending weights over the source views (blend mode; None for Distill)."""


@dataclass
class RenderOutputs:
    """Per-ray rendering results."""

    rgb: Tensor  # (R, 3)
    ov: Tensor  # (R, D), composited with detached weights
    depth_m: Tensor  # (R,) expected distance along the unit ray direction
    opacity: Tensor  # (R,)
    weights: Tensor  # (R, S)
    t: Tensor  # (R, S) sample distances along the rays (m)
    valid_fraction: Tensor  # (R,) fraction of samples some view sees


class GovNeSF(nn.Module):
    """The network: 2D encoder, 3D U-Net, FusionNet, density MLP (and the Distill head)."""

    def __init__(self, cfg: ModelConfig, mode: Literal["blend", "distill"] = "blend") -> None:
        super().__init__()
        if mode not in ("blend", "distill"):
            raise ValueError(f"mode {mode!r} not supported: use 'blend' or 'distill'")
        self.cfg = cfg
        self.mode = mode
        f = cfg.encoder.feature_dim
        dv = cfg.volume.volume_feature_dim
        self.encoder = ImageEncoder(cfg.encoder)
        self.unet = VolumeUNet(2 * f + 1, cfg.volume)
        self.fusion = FusionNet(f, dv, cfg.fusion)
        self.density = DensityMLP(dv, cfg.fusion)
        self.distill = DistillHead(dv, cfg.fusion) if mode == "distill" else None
        self.compiled_sampling = True
        """Let ``sample_views_indexed`` run the compiled CPU kernel where it applies (off: the
        torch path, for comparisons)."""

    # ---- per-view and per-volume stages -------------------------------------------------------
    def encode(self, rgb: Tensor) -> Tensor:
        """(N, 3, H, W) -> (N, F, H/4, W/4) 2D features."""
        return self.encoder(rgb)

    def make_source_views(
        self, rgb: Tensor, ov: Tensor, K: Tensor, world_from_cam: Tensor, depth_m: Tensor | None = None
    ) -> SourceViews:
        """Encode images and bundle them: rgb (N, 3, H, W), ov (N, D, h, w), K (N, 4), poses (N, 4, 4)."""
        return SourceViews(rgb, self.encode(rgb), ov, K, world_from_cam, depth_m)

    def volume_features(self, cost_input: Tensor) -> Tensor:
        """(2F + 1, X, Y, Z) cost-volume network input -> (Dv, X, Y, Z) volume features V_a."""
        return self.unet(cost_input.unsqueeze(0)).squeeze(0)

    def build_volume(self, views: SourceViews, bounds: VolumeBounds) -> Tensor:
        """Differentiable batch cost volume from the views -> (Dv, X, Y, Z)."""
        mean, var, count = build_cost_volume(
            bounds, views.features, views.K, views.world_from_cam, views.image_wh
        )
        return self.volume_features(cost_volume_features(mean, var, count))

    # ---- per-point stages ---------------------------------------------------------------------
    def sample_views(
        self, views: SourceViews, points: Tensor, depth_guided_masking: bool
    ) -> PointViewSamples:
        """Project P points (P, 3) into the N views and sample them."""
        n = len(views)
        wh = views.image_wh
        pts = points.to(views.K.dtype).unsqueeze(0).expand(n, -1, -1)  # (N, P, 3)
        uv, z = project_points(pts, views.K, invert_pose(views.world_from_cam))  # (N, P, 2), (N, P)
        mask = in_view(uv, z, wh[0], wh[1])
        if depth_guided_masking and views.depth_m is not None:
            d_wh = (views.depth_m.shape[-1], views.depth_m.shape[-2])
            measured, _ = sample_nearest(views.depth_m.unsqueeze(1), scale_uv(uv, wh, d_wh))
            measured = measured.squeeze(-1)  # (N, P)
            has_depth = torch.isfinite(measured) & (measured > 0)
            # |range_p - range_m| > r * range_m  <=>  |z_p - z_m| > r * z_m on the same pixel ray.
            agrees = (z - measured).abs() <= self.cfg.render.depth_mask_ratio * measured
            mask = mask & (agrees | ~has_depth)
        rgb, _ = sample_bilinear(views.rgb, uv)
        feat, _ = sample_bilinear(
            views.features, scale_uv(uv, wh, (views.features.shape[-1], views.features.shape[-2]))
        )
        ov, _ = sample_bilinear(views.ov, scale_uv(uv, wh, (views.ov.shape[-1], views.ov.shape[-2])))
        centres = camera_centers(views.world_from_cam)  # (N, 3)
        offsets = pts - centres.unsqueeze(1)  # (N, P, 3)
        dist = offsets.norm(dim=-1)  # (N, P)
        dirs = offsets / dist.clamp_min(1e-9).unsqueeze(-1)  # = F.normalize(offsets, eps=1e-9)
        return PointViewSamples(
            rgb=rgb.transpose(0, 1),
            features=feat.transpose(0, 1),
            ov=ov.transpose(0, 1),
            mask=mask.transpose(0, 1),
            source_dirs=dirs.transpose(0, 1),
            uv=uv.transpose(0, 1),
            source_range=dist.transpose(0, 1),
        )

    def sample_views_indexed(
        self,
        views: SourceViews,
        view_idx: Tensor,
        slot_mask: Tensor,
        points: Tensor,
        depth_guided_masking: bool,
        *,
        sample_ov: bool = True,
    ) -> PointViewSamples:
        """Like ``sample_views``, but every point has its own N source views out of ``views``.

        Args:
            views: M source views (nothing is copied out of their maps).
            view_idx: (P, N) long, the views of each point (indices into ``views``).
            slot_mask: (P, N) bool, False for padding slots (masked, as a view that does not see
                the point; the network then treats the point as if the slot were absent).
            points: (P, 3).
            sample_ov: False when the OV features are blended from the maps afterwards
                (``OVMaps``): ``ov`` is then an empty (P, N, 0) tensor and the OV maps are not read.

        Each map is sampled once per view for all the (point, slot) pairs that use it, so a batch
        of points with different view sets costs one network pass instead of one per view set;
        the values equal ``sample_views`` on each point's own views. With ``sample_ov=False`` on
        the CPU in float32 without autograd (and ``compiled_sampling``) every pair is done by one
        compiled kernel (:mod:`mapper.model.ops.sample_kernel`): the same masks, the samples up to
        float rounding, and 0 colour and features in masked slots (which the network never reads).
        """
        P, N = view_idx.shape
        wh = views.image_wh
        if self.compiled_sampling and _sample_kernel_applies(views, points, sample_ov):
            return self._sample_pairs_compiled(views, view_idx, slot_mask, points, depth_guided_masking)
        # slot-major pairs (n * P + p): the samples come out P-fastest, the layout of
        # ``sample_views`` (grid_sample's (N, C, P)) that ``blend``'s fast path wants
        flat_v = view_idx.T.reshape(-1)
        pts = points.to(views.K.dtype)[None].expand(N, P, 3).reshape(N * P, 1, 3)
        cam_from_world = invert_pose(views.world_from_cam)  # (M, 4, 4)
        uv, z = project_points(pts, views.K[flat_v], cam_from_world[flat_v])  # (N*P, 1, 2), (N*P, 1)
        uv, z = uv[:, 0], z[:, 0]
        mask = in_view(uv, z, wh[0], wh[1]) & slot_mask.T.reshape(-1)
        # every pair's bilinear sample of its own view's maps, all views at once: blend_from_maps
        # with one slot a pair, of weight 1, over the views' channel-last maps
        bufs = []  # (C, N*P) each
        ones = uv.new_ones(N * P, 1)
        n_maps = 3 if sample_ov else 2  # rgb, features[, ov]
        images = (views.rgb, views.features, views.ov)[:n_maps]
        for image, table in zip(images, views.channel_last()[:n_maps], strict=True):
            map_wh = (image.shape[-1], image.shape[-2])
            at = scale_uv(uv, wh, map_wh)[:, None]  # (N*P, 1, 2)
            out = blend_from_maps(table, map_wh, flat_v[:, None], at, ones)  # (N*P, C)
            bufs.append(out.T.to(uv.dtype))
        if depth_guided_masking and views.depth_m is not None:
            d_wh = (views.depth_m.shape[-1], views.depth_m.shape[-2])
            at = scale_uv(uv, wh, d_wh)
            col = at[:, 0].floor().clamp(0, d_wh[0] - 1).long()  # sample_nearest
            row = at[:, 1].floor().clamp(0, d_wh[1] - 1).long()
            measured = views.depth_m.reshape(-1)[flat_v * (d_wh[0] * d_wh[1]) + row * d_wh[0] + col]
            has_depth = torch.isfinite(measured) & (measured > 0)
            agrees = (z - measured).abs() <= self.cfg.render.depth_mask_ratio * measured
            mask = mask & (agrees | ~has_depth)
        centres = camera_centers(views.world_from_cam)[flat_v]  # (N*P, 3)
        offsets = pts[:, 0] - centres
        dist = offsets.norm(dim=-1)  # (N*P,)
        dirs = offsets / dist.clamp_min(1e-9).unsqueeze(-1)

        def per_point(buf: Tensor) -> Tensor:  # (C, N*P) -> (P, N, C), P fastest
            return buf.reshape(buf.shape[0], N, P).permute(2, 1, 0)

        if not sample_ov:
            bufs.append(uv.new_zeros(0, N * P))
        rgb, feat, ov = (per_point(b) for b in bufs)
        return PointViewSamples(
            rgb=rgb,
            features=feat,
            ov=ov,
            mask=mask.reshape(N, P).T,
            source_dirs=dirs.reshape(N, P, 3).transpose(0, 1),
            uv=uv.reshape(N, P, 2).transpose(0, 1),
            source_range=dist.reshape(N, P).T,
        )

    def _sample_pairs_compiled(
        self, views: SourceViews, view_idx: Tensor, slot_mask: Tensor, points: Tensor, depth_masking: bool
    ) -> PointViewSamples:
        """``sample_views_indexed(..., sample_ov=False)`` by the compiled CPU kernel
        (:func:`mapper.model.ops.sample_kernel.sample_pairs`): the same masks, the samples up to
        float rounding, 0 colour and features where masked."""
        from mapper.model.ops.sample_kernel import sample_pairs

        P, N = view_idx.shape
        if points.shape != (P, 3) or slot_mask.shape != (P, N):
            raise ValueError(f"points {tuple(points.shape)} / slot_mask {tuple(slot_mask.shape)} do not fit "
                             f"view_idx {tuple(view_idx.shape)}")
        pairs = self._pair_args(views, view_idx, depth_masking)
        samples, mask, dirs, dist, uv = sample_pairs(
            points.numpy(), view_idx.T.numpy(), slot_mask.T.numpy(), pairs, threads=torch.get_num_threads())
        per_point = torch.from_numpy(samples).reshape(-1, N, P).permute(2, 1, 0)  # (P, N, 3 + F), P fastest
        return PointViewSamples(
            rgb=per_point[..., :3],
            features=per_point[..., 3:],
            ov=per_point.new_zeros(P, N, 0),
            mask=torch.from_numpy(mask).reshape(N, P).T,
            source_dirs=torch.from_numpy(dirs).reshape(3, N, P).permute(2, 1, 0),  # P fastest, as samples
            uv=torch.from_numpy(uv).reshape(N, P, 2).transpose(0, 1),
            source_range=torch.from_numpy(dist).reshape(N, P).T,
        )

    def _pair_args(self, views: SourceViews, view_idx: Tensor, depth_masking: bool) -> PairArgs:
        """The compiled per-pair sampling's cameras and maps (:func:`mapper.model.ops.sample_kernel.
        pair_args`) of ``views``; ``ValueError`` unless ``view_idx`` indexes them."""
        from mapper.model.ops.sample_kernel import pair_args

        if view_idx.numel() and not (0 <= int(view_idx.min()) and int(view_idx.max()) < len(views)):
            raise ValueError(f"view_idx must index the {len(views)} views, got {int(view_idx.min())}.."
                             f"{int(view_idx.max())}")
        rgb_t, feat_t, _ = views.channel_last()
        depth = None
        if depth_masking and views.depth_m is not None:
            d = views.depth_m
            depth = (d.to(torch.float32).numpy(), (int(d.shape[-1]), int(d.shape[-2])))
        return pair_args(
            invert_pose(views.world_from_cam).to(torch.float32).numpy(), views.K.to(torch.float32).numpy(),
            camera_centers(views.world_from_cam).to(torch.float32).numpy(), views.image_wh, DEFAULT_EPS,
            (rgb_t.numpy(), (int(views.rgb.shape[-1]), int(views.rgb.shape[-2]))),
            (feat_t.numpy(), (int(views.features.shape[-1]), int(views.features.shape[-2]))),
            depth, self.cfg.render.depth_mask_ratio,
        )

    def forward(
        self,
        views: SourceViews,
        volume: Tensor,
        bounds: VolumeBounds,
        points: Tensor,
        view_dirs: Tensor,
        *,
        depth_guided_masking: bool = False,
    ) -> FieldOutputs:
        """Field at query points.

        Args:
            views: N source views; volume: (Dv, X, Y, Z) volume features over ``bounds``.
            points: (R, S, 3) world points; view_dirs: (R, 3) or (R, S, 3) unit query directions.
            depth_guided_masking: mask views whose depth map disagrees (views without depth
                there are not masked).
        """
        R, S, _ = points.shape
        flat = points.reshape(R * S, 3)
        dirs = view_dirs.unsqueeze(1).expand(R, S, 3) if view_dirs.ndim == 2 else view_dirs
        sigma, v = self.density_at(volume, bounds, flat)
        rgb, ov, valid = self.appearance(views, v, flat, dirs.reshape(R * S, 3), depth_guided_masking)
        return FieldOutputs(
            sigma=sigma.reshape(R, S),
            rgb=rgb.reshape(R, S, 3),
            ov=ov.reshape(R, S, -1),
            valid=valid.reshape(R, S),
        )

    def density_at(self, volume: Tensor, bounds: VolumeBounds, points: Tensor) -> tuple[Tensor, Tensor]:
        """Density and volume feature at (P, 3) points -> sigma (P,) (0 outside), v (P, Dv)."""
        v, inside = sample_volume(volume, bounds, points)
        sigma = self.density(v)
        return sigma * inside.to(sigma.dtype), v

    def appearance(
        self,
        views: SourceViews,
        v: Tensor,
        points: Tensor,
        view_dirs: Tensor,
        depth_guided_masking: bool,
        *,
        ov_maps: OVMaps | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Blended colour (P, 3), OV feature (P, D) and validity (P,) at (P, 3) points.

        Args:
            v: (P, Dv) volume features at the points; view_dirs: (P, 3) unit query directions.
            ov_maps: blend the OV features from these maps (``views.ov`` may then be a dummy).
        """
        samples = self.sample_views(views, points, depth_guided_masking)
        return self.fuse_samples(samples, v, view_dirs, ov_maps=ov_maps)

    def fuse_samples(
        self, samples: PointViewSamples, v: Tensor, view_dirs: Tensor, *, ov_maps: OVMaps | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """FusionNet + blending over sampled views: rgb (P, 3), OV (P, D), valid (P,).

        Args:
            samples: what P points see in N views (``sample_views`` or ``sample_views_indexed``);
            v: (P, Dv) volume features; view_dirs: (P, 3) unit query directions.
            ov_maps: blend the OV features straight from the maps (as in :meth:`point_outputs`).
        """
        fused = self.fusion(
            samples.rgb, samples.features, v, samples.source_dirs, samples.mask, view_dirs,
            samples.source_range,
        )
        assert fused.color_weights is not None
        rgb = blend(fused.color_weights, samples.rgb)
        if self.distill is not None:
            ov = self.distill(fused.x_att, samples.mask, v) * fused.valid.unsqueeze(-1)
        else:
            ov = self._blend_ov(samples, fused.ov_weights, ov_maps)
        return rgb, ov, fused.valid

    @staticmethod
    def _blend_ov(samples: PointViewSamples, weights: Tensor, ov_maps: OVMaps | None) -> Tensor:
        """(P, D) OV blend: from ``samples.ov``, or from ``ov_maps`` at ``samples.uv``."""
        if ov_maps is None:
            return blend(weights, samples.ov)
        uv = GovNeSF._maps_uv(samples, ov_maps)
        return blend_from_maps(ov_maps.table, ov_maps.map_wh, ov_maps.view_idx, uv, weights)

    @staticmethod
    def _maps_uv(samples: PointViewSamples, ov_maps: OVMaps) -> Tensor:
        """(P, N, 2) the samples' pixel coordinates in ``ov_maps``' resolution."""
        if samples.uv is None:
            raise ValueError("blending from ov_maps needs samples with uv (sample_views)")
        return scale_uv(samples.uv, ov_maps.image_wh, ov_maps.map_wh)

    def _point_weights(
        self, samples: PointViewSamples, v: Tensor, fusion: FusionNet | None
    ) -> tuple[Tensor, Tensor]:
        """OV weights (P, N) and validity (P,) of ``fusion`` (default the model's FusionNet)."""
        net = self.fusion if fusion is None else fusion
        return net.point_weights(samples.rgb, samples.features, v, samples.source_dirs, samples.mask,
                                 samples.source_range)

    def query_points(
        self,
        views: SourceViews,
        volume: Tensor,
        bounds: VolumeBounds,
        points: Tensor,
        *,
        depth_guided_masking: bool = False,
        chunk_size: int | None = None,
        ov_maps: OVMaps | None = None,
        fusion: FusionNet | None = None,
    ) -> PointOutputs:
        """Point mode: source-view-agnostic OV feature at (P, 3) points, each a single sample.

        ``chunk_size`` bounds memory (about chunk_size x N x (D + F + 6) floats at a time).
        ``ov_maps``: blend the OV features from these maps (``views.ov`` may then be a dummy).
        ``fusion``: the network that weighs the views (default the model's FusionNet; see
        :meth:`point_outputs`).
        """
        if chunk_size is not None:
            if chunk_size < 1:
                raise ValueError(f"chunk_size {chunk_size} out of range: must be >= 1")
            parts = [
                self.query_points(
                    views,
                    volume,
                    bounds,
                    points[i : i + chunk_size],
                    depth_guided_masking=depth_guided_masking,
                    ov_maps=ov_maps,
                    fusion=fusion,
                )
                for i in range(0, points.shape[0], chunk_size)
            ]
            if not parts:
                return self.query_points(
                    views, volume, bounds, points, depth_guided_masking=depth_guided_masking, ov_maps=ov_maps,
                    fusion=fusion,
                )
            return PointOutputs(
                ov=torch.cat([p.ov for p in parts]),
                valid=torch.cat([p.valid for p in parts]),
                num_views=torch.cat([p.num_views for p in parts]),
                ov_weights=None
                if parts[0].ov_weights is None
                else torch.cat([p.ov_weights for p in parts if p.ov_weights is not None]),
            )
        samples = self.sample_views(views, points, depth_guided_masking)
        v, _ = sample_volume(volume, bounds, points.to(volume.dtype))
        return self.point_outputs(samples, v, ov_maps=ov_maps, fusion=fusion)

    def point_outputs(
        self,
        samples: PointViewSamples,
        v: Tensor,
        *,
        ov_maps: OVMaps | None = None,
        fusion: FusionNet | None = None,
    ) -> PointOutputs:
        """Point mode over sampled views (``sample_views`` or ``sample_views_indexed``) and
        (P, Dv) volume features: the source-view-agnostic OV feature of each point.

        ``ov_maps``: blend the OV features straight from the views' maps at ``samples.uv``
        (``sample_views``' samples; their ``ov`` is then ignored) instead of from ``samples.ov``:
        the same result up to float rounding, without the (P, N, D) samples.
        ``fusion``: the network whose OV weights blend the views, in place of the model's own
        FusionNet: a smaller point head distilled from it (:mod:`mapper.model.point_head`) that
        takes the same inputs. Not used in ``distill`` mode (the Distill head reads the model's
        own attention features)."""
        if self.distill is not None:
            fused = self.fusion(samples.rgb, samples.features, v, samples.source_dirs, samples.mask, None,
                                samples.source_range)
            ov = self.distill(fused.x_att, samples.mask, v) * fused.valid.unsqueeze(-1)
            return PointOutputs(ov=ov, valid=fused.valid, num_views=samples.mask.sum(dim=1), ov_weights=None)
        weights, valid = self._point_weights(samples, v, fusion)
        ov = self._blend_ov(samples, weights, ov_maps)
        return PointOutputs(ov=ov, valid=valid, num_views=samples.mask.sum(dim=1), ov_weights=weights)

    def point_cosines(
        self,
        samples: PointViewSamples,
        v: Tensor,
        texts: Tensor,
        *,
        ov_maps: OVMaps | None = None,
        fusion: FusionNet | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Each text's cosine with each point's OV feature: ``F.normalize(point_outputs(...).ov)
        @ texts.T`` (arguments as :meth:`point_outputs`; texts (T, D)), without the (P, D)
        features where the blend comes from ``ov_maps`` (:func:`fusion.cosines_from_maps`).

        Returns:
            cosines (P, T) (0 where no view sees the point), valid (P,) bool, num_views (P,) long.
        """
        if self.distill is not None or ov_maps is None:
            out = self.point_outputs(samples, v, ov_maps=ov_maps, fusion=fusion)
            return F.normalize(out.ov, dim=-1) @ texts.to(out.ov.dtype).T, out.valid, out.num_views
        uv = self._maps_uv(samples, ov_maps)  # (checked before the network runs)
        weights, valid = self._point_weights(samples, v, fusion)
        cos = cosines_from_maps(ov_maps.table, ov_maps.map_wh, ov_maps.view_idx, uv, weights, texts)
        return cos, valid, samples.mask.sum(dim=1)

    def answer_kernel_applies(self, views: SourceViews, points: Tensor, ov: Tensor,
                              fusion: FusionNet | None = None) -> bool:
        """:meth:`point_cosines_indexed` runs as one compiled CPU pass: blend mode, the compiled
        sampling and point kernels switched on, everything (``ov``: the OV maps or their table) on
        the CPU in float32, no gradient."""
        net = self.fusion if fusion is None else fusion
        return (
            self.distill is None
            and self.compiled_sampling
            and net.fast_inference
            and net.point_kernel
            and _sample_kernel_applies(views, points, sample_ov=False)
            and ov.device.type == "cpu"
            and ov.dtype == torch.float32
        )

    def point_cosines_indexed(
        self,
        views: SourceViews,
        view_idx: Tensor,  # (P, N) long: each point's views (indices into ``views``)
        slot_mask: Tensor,  # (P, N) bool: False for padding slots
        points: Tensor,  # (P, 3)
        depth_guided_masking: bool,
        v: Tensor,  # (P, Dv) volume features at the points
        texts: Tensor,  # (T, D) unit text embeddings
        ov_maps: OVMaps,  # the OV maps of ``views`` (``ov_maps.view_idx`` is not read: ``view_idx`` is)
        *,
        fusion: FusionNet | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``point_cosines(sample_views_indexed(views, view_idx, slot_mask, points,
        depth_guided_masking, sample_ov=False), v, texts, ov_maps=..., fusion=fusion)`` as one
        compiled pass (:mod:`mapper.model.ops.answer_kernel`): the same cosines without the
        pairs' samples ever leaving per-block buffers. Only where :meth:`answer_kernel_applies`.

        Returns:
            cosines (P, T) (0 where no view sees the point), valid (P,) bool, num_views (P,) long.
        """
        return self._answer_indexed(views, view_idx, slot_mask, points, depth_guided_masking, v, texts,
                                    ov_maps, fusion)

    def point_features_indexed(
        self,
        views: SourceViews,
        view_idx: Tensor,  # (P, N) long
        slot_mask: Tensor,  # (P, N) bool
        points: Tensor,  # (P, 3)
        depth_guided_masking: bool,
        v: Tensor,  # (P, Dv)
        ov_maps: OVMaps,
        *,
        fusion: FusionNet | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`point_cosines_indexed`'s pass for the features themselves: ``point_outputs``'
        ``ov`` (P, D) (0 rows where no view sees the point), valid (P,) bool, num_views (P,) long."""
        return self._answer_indexed(views, view_idx, slot_mask, points, depth_guided_masking, v, None,
                                    ov_maps, fusion)

    def _answer_indexed(
        self, views: SourceViews, view_idx: Tensor, slot_mask: Tensor, points: Tensor,
        depth_guided_masking: bool, v: Tensor, texts: Tensor | None, ov_maps: OVMaps,
        fusion: FusionNet | None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        from mapper.model.ops.answer_kernel import answer_points

        net = self.fusion if fusion is None else fusion
        if not self.answer_kernel_applies(views, points, ov_maps.table, fusion):
            raise ValueError("the one-pass point answers need the compiled CPU path (answer_kernel_applies)")
        P, N = view_idx.shape
        if points.shape != (P, 3) or slot_mask.shape != (P, N) or v.shape[0] != P:
            raise ValueError(f"points {tuple(points.shape)} / slot_mask {tuple(slot_mask.shape)} / volume "
                             f"features {tuple(v.shape)} do not fit view_idx {tuple(view_idx.shape)}")
        if tuple(ov_maps.image_wh) != tuple(views.image_wh):
            raise ValueError(f"ov_maps are for {ov_maps.image_wh} images, the views are {views.image_wh}")
        pairs = self._pair_args(views, view_idx, depth_guided_masking)
        cos, valid, num_views = answer_points(
            net.point_kernel_weights(), points.numpy(), view_idx.T.numpy(), slot_mask.T.numpy(), pairs,
            v.to(torch.float32).numpy(), (ov_maps.table.numpy(), ov_maps.map_wh),
            None if texts is None else texts.to(torch.float32).numpy(), threads=torch.get_num_threads(),
        )
        return torch.from_numpy(cos), torch.from_numpy(valid), torch.from_numpy(num_views)


def _sample_kernel_applies(views: SourceViews, points: Tensor, sample_ov: bool) -> bool:
    """``sample_views_indexed`` takes the compiled kernel: CPU float32 maps and points, no OV
    samples asked for, no gradient to record."""
    tensors = (views.rgb, views.features, views.K, views.world_from_cam, points)
    return (
        not sample_ov
        and not torch.is_grad_enabled()
        and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
    )


def render_rays(
    model: GovNeSF,
    views: SourceViews,
    volume: Tensor,
    bounds: VolumeBounds,
    rays: Rays,
    *,
    n_samples: int | None = None,
    near_m: float | Tensor | None = None,
    far_m: float | Tensor | None = None,
    stratified: bool = False,
    generator: torch.Generator | None = None,
    depth_guided_masking: bool = False,
    clip_to_volume: bool = False,
    weight_threshold: float = 0.0,
) -> RenderOutputs:
    """Volume-render R rays (defaults from ``model.cfg.render``) with the one marcher,
    :func:`mapper.model.render.march_rays`.

    ``clip_to_volume`` (empty-space skipping): sample only the part of [near, far] inside the
    volume's bounds (density is 0 outside it); rays that miss the volume keep [near, far].
    Off by default so that training matches the paper's uniform sampling.

    ``weight_threshold`` > 0: density first (cheap: volume lookup + MLP), then the expensive
    per-view appearance (projection, sampling, FusionNet) only for samples whose rendering weight
    reaches it; the others contribute 0 colour / OV. This is an approximation (it drops the
    colour gradient through those tiny weights); 0 (default) is exact.
    """
    if weight_threshold < 0:
        raise ValueError(f"weight_threshold {weight_threshold} out of range: must be >= 0")
    rc = model.cfg.render
    like = rays.origins
    box = (like.new_tensor(bounds.origin_m), like.new_tensor(bounds.max_corner_m)) if clip_to_volume else None

    def density(points: Tensor) -> tuple[Tensor, Tensor]:
        return model.density_at(volume, bounds, points)

    def appearance(points: Tensor, view_dirs: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return model.appearance(views, v, points, view_dirs, depth_guided_masking)

    out = march_rays(
        rays,
        density,
        appearance,
        n_samples=rc.n_samples if n_samples is None else n_samples,
        near_m=rc.near_m if near_m is None else near_m,
        far_m=rc.far_m if far_m is None else far_m,
        stratified=stratified,
        generator=generator,
        box=box,
        min_weight=weight_threshold,
    )
    assert out.rgb is not None and out.ov is not None
    return RenderOutputs(
        rgb=out.rgb,
        ov=out.ov,
        depth_m=out.depth_m,
        opacity=out.opacity,
        weights=out.weights,
        t=out.t,
        valid_fraction=out.valid.float().mean(dim=-1),
    )


@torch.no_grad()
def render_depth_maps(
    model: GovNeSF,
    volume: Tensor,
    bounds: VolumeBounds,
    K: Tensor,
    world_from_cam: Tensor,
    width: int,
    height: int,
    *,
    n_samples: int | None = None,
    min_opacity: float = 0.5,
    chunk_rays: int = 16384,
) -> tuple[Tensor, Tensor]:
    """The model's z-depth seen from N cameras: a depth-only march (no source views needed) on
    ``[near_m, far_m]`` clipped to the volume box; rays that miss the box render nothing.

    Args:
        volume: (Dv, X, Y, Z) over ``bounds``; K: (N, 4) for (width, height); world_from_cam: (N, 4, 4).
        n_samples: samples per ray inside the volume (default ``model.cfg.render.n_samples``).
        min_opacity: pixels whose accumulated opacity is below this get depth 0 (no surface).

    Returns:
        depth_m: (N, height, width) z-depth along each optical axis (0 = none); opacity: same shape.
    """
    if chunk_rays < 1:
        raise ValueError(f"chunk_rays {chunk_rays} out of range: must be >= 1")
    check_shape(world_from_cam, "N 4 4", "world_from_cam", check_shape(K, "N 4", "K"))
    rc = model.cfg.render
    n = K.shape[0]
    depth = torch.zeros(n, height, width, device=volume.device)
    opacity = torch.zeros(n, height, width, device=volume.device)
    box = (volume.new_tensor(bounds.origin_m), volume.new_tensor(bounds.max_corner_m))
    S = rc.n_samples if n_samples is None else n_samples

    def density(points: Tensor) -> tuple[Tensor, Tensor]:
        return model.density_at(volume, bounds, points)

    for i in range(n):
        origins, dirs = pixel_rays(K[i].to(volume.dtype), world_from_cam[i].to(volume.dtype), width, height)
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        axis = world_from_cam[i, :3, 2].to(volume.dtype)
        z_all, op_all = [], []
        for j in range(0, origins.shape[0], chunk_rays):
            o, d = origins[j : j + chunk_rays], dirs[j : j + chunk_rays]
            out = march_rays(
                Rays(o, d), density, None, n_samples=S, near_m=rc.near_m, far_m=rc.far_m,
                box=box, skip_missed=True,
            )  # fmt: skip
            z = out.depth_m * (d @ axis)
            z_all.append(torch.where(out.opacity >= min_opacity, z, torch.zeros_like(z)))
            op_all.append(out.opacity)
        depth[i] = torch.cat(z_all).reshape(height, width)
        opacity[i] = torch.cat(op_all).reshape(height, width)
    return depth, opacity


def render_image(
    model: GovNeSF,
    views: SourceViews,
    volume: Tensor,
    bounds: VolumeBounds,
    K: Tensor,
    world_from_cam: Tensor,
    image_wh: tuple[int, int],
    *,
    chunk_rays: int = 4096,
    **render_kwargs: Any,
) -> RenderOutputs:
    """Render a whole novel view in ray chunks.

    Args:
        K: (4,) intrinsics for ``image_wh = (W, H)``; world_from_cam: (4, 4).
        render_kwargs: forwarded to ``render_rays`` (n_samples, clip_to_volume, ...).

    Returns:
        RenderOutputs with per-pixel fields shaped (H, W, ...) instead of (R, ...).
    """
    if chunk_rays < 1:
        raise ValueError(f"chunk_rays {chunk_rays} out of range: must be >= 1")
    width, height = image_wh
    origins, dirs = pixel_rays(K, world_from_cam, width, height)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    parts = [
        render_rays(
            model,
            views,
            volume,
            bounds,
            Rays(origins[i : i + chunk_rays], dirs[i : i + chunk_rays]),
            **render_kwargs,
        )
        for i in range(0, origins.shape[0], chunk_rays)
    ]

    def cat(name: str) -> Tensor:
        joined = torch.cat([getattr(p, name) for p in parts])
        return joined.reshape(height, width, *joined.shape[1:])

    return RenderOutputs(
        rgb=cat("rgb"),
        ov=cat("ov"),
        depth_m=cat("depth_m"),
        opacity=cat("opacity"),
        weights=cat("weights"),
        t=cat("t"),
        valid_fraction=cat("valid_fraction"),
    )
