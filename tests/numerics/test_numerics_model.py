"""Stiff / extreme cases for the network.

All views masked for a point; a point at a source camera centre; the query direction equal to a
source direction; absurdly far points; gradcheck of the field in float64; no NaN/Inf forward or
backward.
"""

from __future__ import annotations

import torch

from mapper.model.config import EncoderConfig, FusionConfig, ModelConfig, RenderConfig, VolumeConfig
from mapper.model.field import GovNeSF, SourceViews
from mapper.model.fusion import FusionNet
from mapper.model.ops.cost_volume import VolumeBounds

CFG = ModelConfig(
    name="numerics",
    encoder=EncoderConfig(base_channels=4, blocks=(1, 1, 1), feature_dim=4),
    volume=VolumeConfig(unet_channels=(4, 4, 4), group_norm_groups=2, volume_feature_dim=3, max_voxels=64),
    fusion=FusionConfig(hidden_dim=8, attention_dim=4, num_heads=2, ov_dim=3),
    render=RenderConfig(n_samples=4, near_m=0.5, far_m=3.0),
    num_source_views=2,
    image_wh=(8, 6),
)
BOUNDS = VolumeBounds((-1.0, -1.0, 0.0), 0.5, (4, 4, 4))


def views_for(model: GovNeSF, dtype: torch.dtype = torch.float32) -> SourceViews:
    g = torch.Generator().manual_seed(0)
    n = 2
    poses = torch.eye(4, dtype=dtype).repeat(n, 1, 1)
    poses[1, 0, 3] = 0.4
    return SourceViews(
        rgb=torch.rand(n, 3, 6, 8, generator=g).to(dtype),
        features=torch.randn(n, 4, 2, 2, generator=g).to(dtype),
        ov=torch.randn(n, 3, 2, 2, generator=g).to(dtype),
        K=torch.tensor([6.0, 6.0, 4.0, 3.0], dtype=dtype).expand(n, 4),
        world_from_cam=poses,
    )


def test_all_views_masked_forward_and_backward_are_finite() -> None:
    torch.manual_seed(0)
    fusion = FusionNet(4, 3, CFG.fusion)
    P, N = 5, 3
    rgb = torch.rand(P, N, 3, requires_grad=True)
    feats = torch.randn(P, N, 4, requires_grad=True)
    v = torch.randn(P, 3, requires_grad=True)
    dirs = torch.nn.functional.normalize(torch.randn(P, N, 3), dim=-1)
    mask = torch.zeros(P, N, dtype=torch.bool)
    mask[0] = True  # one point seen by all, the others by none
    out = fusion(rgb, feats, v, dirs, mask, dirs[:, 0])
    assert out.valid.tolist() == [True, False, False, False, False]
    assert out.color_weights is not None
    assert torch.all(out.color_weights[1:] == 0) and torch.all(out.ov_weights[1:] == 0)
    total = out.color_weights.sum() + out.ov_weights.sum() + out.x_att.sum()
    total.backward()
    for leaf in (rgb, feats, v):
        assert leaf.grad is not None and torch.isfinite(leaf.grad).all()
    for name, p in fusion.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


def test_degenerate_directions_and_far_points_stay_finite() -> None:
    torch.manual_seed(0)
    model = GovNeSF(CFG)
    views = views_for(model)
    volume = torch.randn(3, *BOUNDS.dims, requires_grad=True)
    points = torch.tensor(
        [
            [[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, 0.0, 1.0]],  # at camera centres, then a normal point
            [[0.0, 0.0, 1e6], [1e30, 0.0, 1.0], [0.2, 0.0, -3.0]],  # far, absurd, behind every camera
        ]
    )
    # Query directions equal to the source direction (unit(d_q - d_src) of a zero vector).
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    out = model(views, volume, BOUNDS, points, dirs)
    for t in (out.sigma, out.rgb, out.ov):
        assert torch.isfinite(t).all()
    assert out.valid[1, 2].item() is False
    (out.sigma.sum() + out.rgb.sum() + out.ov.sum()).backward()
    assert volume.grad is not None and torch.isfinite(volume.grad).all()
    for name, p in model.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


def test_gradcheck_field_float64() -> None:
    torch.manual_seed(0)
    model = GovNeSF(CFG).double()
    views = views_for(model, torch.float64)
    bounds = VolumeBounds((-1.0, -1.0, 0.0), 1.0, (2, 2, 3))
    volume = torch.randn(3, *bounds.dims, dtype=torch.float64, requires_grad=True)
    ov_maps = views.ov.clone().requires_grad_()
    points = torch.tensor([[[0.1, 0.05, 1.3], [0.3, -0.2, 2.1]]], dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.tensor([[0.1, 0.0, 1.0]], dtype=torch.float64), dim=-1)

    def field(vol: torch.Tensor, ov: torch.Tensor) -> tuple[torch.Tensor, ...]:
        v = SourceViews(views.rgb, views.features, ov, views.K, views.world_from_cam)
        out = model(v, vol, bounds, points, dirs)
        return out.sigma, out.rgb, out.ov

    assert torch.autograd.gradcheck(field, (volume, ov_maps), atol=1e-6, rtol=1e-4, fast_mode=True)
