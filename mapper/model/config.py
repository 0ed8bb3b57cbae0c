"""Typed configuration of the GOV-NeSF network, with named presets.

Presets:

* ``cpu-small`` -- tiny; meant to train on 2 CPU cores within about an hour on 160x120 images.
* ``gpu-medium`` -- ``cpu-small``'s inputs (8 views, 160x120) with twice its widths, two blocks per
  encoder stage, 48 samples a ray and a 3.4 times finer voxel budget; meant for a GPU
  (docs/how-to/train.md, runs G1-G3); it still runs on a CPU, a few times slower.
* ``paper`` -- the paper's / official code's sizes (ResNet-34-style encoder, 30 source views,
  320x240, 64 samples a ray between 0.2 and 8 m, 512-d OV features).

Examples:
    >>> cfg = get_preset("cpu-small")
    >>> cfg.encoder.feature_dim, cfg.render.n_samples
    (16, 32)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

__all__ = [
    "PRESETS",
    "EncoderConfig",
    "FusionConfig",
    "ModelConfig",
    "RenderConfig",
    "VolumeConfig",
    "get_preset",
]


@dataclass(frozen=True)
class EncoderConfig:
    """2D image encoder (ResNet-style UNet, output at stride 4)."""

    base_channels: int = 64
    """Channels of the stem and of the stride-4 decoder output (paper: 64)."""
    blocks: tuple[int, int, int] = (3, 4, 6)
    """Residual blocks at strides 4, 8, 16 (ResNet-34 stages 1-3: 3, 4, 6)."""
    feature_dim: int = 32
    """Per-view feature after the final 1x1 projection (paper: 64 -> 32)."""
    norm: Literal["instance", "batch", "none"] = "instance"
    """Normalisation in the encoder (paper: InstanceNorm)."""

    def __post_init__(self) -> None:
        if self.base_channels < 1 or self.feature_dim < 1 or min(self.blocks) < 1:
            raise ValueError(f"encoder sizes must be >= 1, got {self}")


@dataclass(frozen=True)
class VolumeConfig:
    """Cost volume and 3D U-Net."""

    unet_channels: tuple[int, int, int] = (16, 32, 64)
    """Channels of the three 3D U-Net levels (paper: 16, 32, 64)."""
    group_norm_groups: int = 4
    """Groups of the GroupNorm layers (must divide every level's channels)."""
    volume_feature_dim: int = 16
    """Channels of the volume feature V_a the FusionNet and density MLP sample."""
    max_voxels: int = 40 * 40 * 16
    """Voxel budget when the bounds are chosen from the scene (paper grid: 40 x 40 x 16)."""
    min_voxel_size_m: float = 0.04
    """Smallest voxel edge the bounds helper may choose (m)."""
    margin_m: float = 0.2
    """Margin added around the observed points when choosing bounds (m)."""

    def __post_init__(self) -> None:
        if any(c % self.group_norm_groups for c in self.unet_channels):
            raise ValueError(
                f"group_norm_groups {self.group_norm_groups} must divide unet_channels {self.unet_channels}"
            )
        if self.volume_feature_dim < 1 or self.max_voxels < 64:
            raise ValueError(f"volume sizes out of range: {self}")


@dataclass(frozen=True)
class FusionConfig:
    """FusionNet (cross-view attention blending) and density MLP."""

    hidden_dim: int = 64
    """First width of MLP_a (paper: 64)."""
    attention_dim: int = 32
    """Width after MLP_a and inside the cross-view attention (paper: 32)."""
    num_heads: int = 8
    """Heads of the linear attention (paper: 8); must divide attention_dim."""
    ov_dim: int = 512
    """Dimension of the open-vocabulary features blended (LSeg: 512, minilm-l6-v2: 384)."""
    density_activation: Literal["softplus", "trunc_exp"] = "softplus"
    """sigma = softplus(x) (smooth, gradient never dies, no overflow) or a shifted, clamped exp."""
    density_bias_init: float = -1.0
    """Initial bias of the density output (softplus(-1) = 0.31 / m: semi-transparent start)."""
    distill_hidden_dim: int = 0
    """Width of the Distill head's hidden layers (0: ``2 * hidden_dim``, the first checkpoints')."""
    distill_layers: int = 1
    """Hidden layers of the Distill head (1: the first checkpoints')."""
    range_encoding: bool = False
    """Feed each view's camera-to-point distance to the blend (``x^n += RE(log r^n)``, next to
    the direction encoding DE): 2D OV models see near surfaces better than far ones. Off: the
    paper's inputs (and the checkpoints made before it)."""

    def __post_init__(self) -> None:
        if self.attention_dim % self.num_heads:
            raise ValueError(f"num_heads {self.num_heads} must divide attention_dim {self.attention_dim}")
        if self.ov_dim < 1 or self.hidden_dim < 1 or self.distill_hidden_dim < 0 or self.distill_layers < 1:
            raise ValueError(f"fusion sizes out of range: {self}")


@dataclass(frozen=True)
class RenderConfig:
    """Ray sampling."""

    n_samples: int = 64
    """Samples a ray (paper: 64 uniform, no hierarchical sampling)."""
    near_m: float = 0.2
    """Near bound along the ray (m)."""
    far_m: float = 8.0
    """Far bound along the ray (m)."""
    depth_mask_ratio: float = 0.25
    """Depth Guided Masking: mask a view where |point depth - measured depth| > ratio * measured."""

    def __post_init__(self) -> None:
        if self.n_samples < 1 or not 0 <= self.near_m < self.far_m:
            raise ValueError(f"render settings out of range: {self}")


@dataclass(frozen=True)
class ModelConfig:
    """Everything that defines a GOV-NeSF network and how it is fed."""

    name: str = "custom"
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    volume: VolumeConfig = field(default_factory=VolumeConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    num_source_views: int = 30
    """Source views a step / a query (paper: 30)."""
    image_wh: tuple[int, int] = (320, 240)
    """Image size (W, H) the network is trained on (paper: 320 x 240)."""

    def __post_init__(self) -> None:
        if self.num_source_views < 1 or len(self.image_wh) != 2 or min(self.image_wh) < 1:
            raise ValueError(
                f"model settings out of range: num_source_views {self.num_source_views} (>= 1), "
                f"image_wh {self.image_wh} ((W, H) >= 1 px)"
            )


PRESETS: dict[str, ModelConfig] = {
    "cpu-small": ModelConfig(
        name="cpu-small",
        encoder=EncoderConfig(base_channels=16, blocks=(1, 1, 1), feature_dim=16, norm="instance"),
        volume=VolumeConfig(
            unet_channels=(8, 16, 32), group_norm_groups=4, volume_feature_dim=8, max_voxels=32 * 32 * 16
        ),
        fusion=FusionConfig(hidden_dim=32, attention_dim=16, num_heads=4, ov_dim=384),
        render=RenderConfig(n_samples=32, near_m=0.2, far_m=8.0),
        num_source_views=8,
        image_wh=(160, 120),
    ),
    "gpu-medium": ModelConfig(
        name="gpu-medium",
        encoder=EncoderConfig(base_channels=32, blocks=(2, 2, 2), feature_dim=32, norm="instance"),
        volume=VolumeConfig(
            unet_channels=(16, 32, 64), group_norm_groups=4, volume_feature_dim=16, max_voxels=48 * 48 * 24
        ),
        fusion=FusionConfig(hidden_dim=64, attention_dim=32, num_heads=8, ov_dim=384),
        render=RenderConfig(n_samples=48, near_m=0.2, far_m=8.0),
        num_source_views=8,
        image_wh=(160, 120),
    ),
    "paper": ModelConfig(
        name="paper",
        encoder=EncoderConfig(base_channels=64, blocks=(3, 4, 6), feature_dim=32, norm="instance"),
        volume=VolumeConfig(unet_channels=(16, 32, 64), group_norm_groups=4, volume_feature_dim=16),
        fusion=FusionConfig(hidden_dim=64, attention_dim=32, num_heads=8, ov_dim=512),
        render=RenderConfig(n_samples=64, near_m=0.2, far_m=8.0),
        num_source_views=30,
        image_wh=(320, 240),
    ),
}


def get_preset(name: str, *, ov_dim: int | None = None, **overrides: Any) -> ModelConfig:
    """A preset by name, optionally with the OV dimension and top-level fields replaced."""
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; choose one of {sorted(PRESETS)}")
    cfg = PRESETS[name]
    if ov_dim is not None:
        cfg = replace(cfg, fusion=replace(cfg.fusion, ov_dim=int(ov_dim)))
    return replace(cfg, **overrides) if overrides else cfg
