"""2D image encoder: a ResNet-style UNet with InstanceNorm, output at stride 4.

Layout (``EncoderConfig``): stem 7x7/2 conv -> residual stages at strides 4, 8, 16 with
``base, 2 base, 4 base`` channels (ResNet-34 uses 3, 4, 6 blocks) -> decoder upsampling to
stride 8 and 4 with skip connections -> ``base`` channels at stride 4 -> 1x1 projection to
``feature_dim`` (paper: 64 -> 32). Any input size works: the decoder resizes to the skip's size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapper.checks import check_shape
from mapper.model.config import EncoderConfig

__all__ = ["ImageEncoder"]


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "instance":
        return nn.InstanceNorm2d(channels, affine=True, track_running_stats=False)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    return nn.Identity()


class _BasicBlock(nn.Module):
    def __init__(self, in_ch: int, out_ch: int, stride: int, norm: str) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride, 1, bias=False)
        self.norm1 = _norm(norm, out_ch)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, 1, 1, bias=False)
        self.norm2 = _norm(norm, out_ch)
        self.skip: nn.Module = nn.Identity()
        if stride != 1 or in_ch != out_ch:
            self.skip = nn.Sequential(nn.Conv2d(in_ch, out_ch, 1, stride, bias=False), _norm(norm, out_ch))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = self.norm2(self.conv2(y))
        return F.relu(y + self.skip(x))


def _stage(in_ch: int, out_ch: int, blocks: int, stride: int, norm: str) -> nn.Sequential:
    layers = [_BasicBlock(in_ch, out_ch, stride, norm)]
    layers += [_BasicBlock(out_ch, out_ch, 1, norm) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class ImageEncoder(nn.Module):
    """(N, 3, H, W) images in [0, 1] -> (N, feature_dim, ceil(H/4), ceil(W/4)) features."""

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        c = cfg.base_channels
        self.cfg = cfg
        self.stem = nn.Sequential(
            nn.Conv2d(3, c, 7, 2, 3, bias=False), _norm(cfg.norm, c), nn.ReLU(inplace=True)
        )
        self.stage1 = _stage(c, c, cfg.blocks[0], 2, cfg.norm)  # stride 4
        self.stage2 = _stage(c, 2 * c, cfg.blocks[1], 2, cfg.norm)  # stride 8
        self.stage3 = _stage(2 * c, 4 * c, cfg.blocks[2], 2, cfg.norm)  # stride 16
        self.up3 = nn.Sequential(
            nn.Conv2d(4 * c + 2 * c, 2 * c, 3, 1, 1, bias=False),
            _norm(cfg.norm, 2 * c),
            nn.ReLU(inplace=True),
        )
        self.up2 = nn.Sequential(
            nn.Conv2d(2 * c + c, c, 3, 1, 1, bias=False), _norm(cfg.norm, c), nn.ReLU(inplace=True)
        )
        self.head = nn.Conv2d(c, cfg.feature_dim, 1)

    @staticmethod
    def _up_cat(x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return torch.cat([x, skip], dim=1)

    def forward(self, rgb: Tensor) -> Tensor:
        check_shape(rgb, "N 3 H W", "rgb")
        x = (rgb - 0.45) / 0.25  # roughly zero-mean, unit-variance input
        x1 = self.stage1(self.stem(x))
        x2 = self.stage2(x1)
        x3 = self.stage3(x2)
        y = self.up3(self._up_cat(x3, x2))
        y = self.up2(self._up_cat(y, x1))
        return self.head(y)
