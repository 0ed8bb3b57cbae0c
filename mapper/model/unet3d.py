"""3-level 3D U-Net with GroupNorm: cost volume -> volume features V_a.

(2C + 1, X, Y, Z) -> (volume_feature_dim, X, Y, Z). Levels at full, 1/2 and 1/4 resolution with
``unet_channels`` maps each (paper: 16, 32, 64). Odd grid sizes work (the decoder resizes to the
skip's size); the output is a plain linear map (no softmax, unlike the official code's test path).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapper.checks import check_shape
from mapper.model.config import VolumeConfig

__all__ = ["VolumeUNet"]


class _ConvBlock(nn.Sequential):
    def __init__(self, in_ch: int, out_ch: int, groups: int, stride: int = 1) -> None:
        super().__init__(
            nn.Conv3d(in_ch, out_ch, 3, stride, 1, bias=False),
            nn.GroupNorm(groups, out_ch),
            nn.ReLU(inplace=True),
            nn.Conv3d(out_ch, out_ch, 3, 1, 1, bias=False),
            nn.GroupNorm(groups, out_ch),
            nn.ReLU(inplace=True),
        )


class VolumeUNet(nn.Module):
    """(B, in_channels, X, Y, Z) -> (B, volume_feature_dim, X, Y, Z)."""

    def __init__(self, in_channels: int, cfg: VolumeConfig) -> None:
        super().__init__()
        c1, c2, c3 = cfg.unet_channels
        g = cfg.group_norm_groups
        self.enc1 = _ConvBlock(in_channels, c1, g)
        self.enc2 = _ConvBlock(c1, c2, g, stride=2)
        self.enc3 = _ConvBlock(c2, c3, g, stride=2)
        self.dec2 = _ConvBlock(c3 + c2, c2, g)
        self.dec1 = _ConvBlock(c2 + c1, c1, g)
        self.head = nn.Conv3d(c1, cfg.volume_feature_dim, 1)

    @staticmethod
    def _up_cat(x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(x, size=skip.shape[-3:], mode="trilinear", align_corners=False)
        return torch.cat([x, skip], dim=1)

    def forward(self, volume: Tensor) -> Tensor:
        check_shape(volume, "B C X Y Z", "volume")
        x1 = self.enc1(volume)
        x2 = self.enc2(x1)
        x3 = self.enc3(x2)
        y = self.dec2(self._up_cat(x3, x2))
        y = self.dec1(self._up_cat(y, x1))
        return self.head(y)
