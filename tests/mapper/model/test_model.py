"""Tests for mapper.model: presets, FusionNet masking, field behaviour, DGM, losses, autocast."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from mapper.model.config import (
    PRESETS,
    EncoderConfig,
    FusionConfig,
    ModelConfig,
    RenderConfig,
    VolumeConfig,
    get_preset,
)
from mapper.model.encoder2d import ImageEncoder
from mapper.model.field import GovNeSF, SourceViews, render_depth_maps, render_image, render_rays
from mapper.model.fusion import CrossViewAttention, masked_softmax
from mapper.model.losses import distortion_loss, govnesf_loss, ov_cosine_loss
from mapper.model.ops.cost_volume import CostVolume, VolumeBounds, build_cost_volume, cost_volume_features
from mapper.model.ops.geometry import pixel_rays, sample_bilinear, scale_uv
from mapper.model.ops.rendering import Rays
from mapper.model.unet3d import VolumeUNet

TINY = ModelConfig(
    name="tiny",
    encoder=EncoderConfig(base_channels=8, blocks=(1, 1, 1), feature_dim=8),
    volume=VolumeConfig(unet_channels=(4, 8, 8), group_norm_groups=4, volume_feature_dim=4, max_voxels=512),
    fusion=FusionConfig(hidden_dim=16, attention_dim=8, num_heads=2, ov_dim=6),
    render=RenderConfig(n_samples=8, near_m=0.5, far_m=3.5),
    num_source_views=3,
    image_wh=(32, 24),
)
W, H = TINY.image_wh
BOUNDS = VolumeBounds((-1.0, -1.0, 0.5), 0.25, (8, 8, 12))


def make_views(model: GovNeSF, n: int = 3, depth: torch.Tensor | None = None, seed: int = 0) -> SourceViews:
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(n, 3, H, W, generator=g)
    ov = torch.randn(n, TINY.fusion.ov_dim, 6, 8, generator=g)
    K = torch.tensor([28.0, 28.0, W / 2, H / 2]).expand(n, 4)
    poses = torch.eye(4).repeat(n, 1, 1)
    poses[:, 0, 3] = torch.linspace(-0.3, 0.3, n)  # cameras side by side, looking along +z
    return model.make_source_views(rgb, ov, K, poses, depth)


@pytest.fixture(scope="module")
def model() -> GovNeSF:
    torch.manual_seed(0)
    return GovNeSF(TINY).eval()


def test_presets_match_the_brief() -> None:
    paper = get_preset("paper")
    assert (
        paper.encoder.base_channels == 64
        and paper.encoder.feature_dim == 32
        and paper.encoder.norm == "instance"
    )
    assert paper.volume.unet_channels == (16, 32, 64)
    assert (paper.fusion.hidden_dim, paper.fusion.attention_dim, paper.fusion.num_heads) == (64, 32, 8)
    assert (paper.render.n_samples, paper.render.near_m, paper.render.far_m) == (64, 0.2, 8.0)
    assert paper.num_source_views == 30 and paper.image_wh == (320, 240)
    small = get_preset("cpu-small")
    assert small.image_wh == (160, 120) and small.num_source_views <= 8 and 32 <= small.render.n_samples <= 48
    assert get_preset("cpu-small", ov_dim=12).fusion.ov_dim == 12
    assert set(PRESETS) == {"cpu-small", "gpu-medium", "paper"}
    medium = get_preset("gpu-medium")  # cpu-small's inputs (so its data and the node's frames fit)
    assert (medium.image_wh, medium.num_source_views) == (small.image_wh, small.num_source_views)
    assert medium.volume.max_voxels > small.volume.max_voxels and medium.render.n_samples == 48
    sizes = {name: sum(p.numel() for p in GovNeSF(cfg).parameters()) for name, cfg in PRESETS.items()}
    assert sizes["cpu-small"] < 500_000 < 5_000_000 < sizes["paper"]  # tiny vs ResNet-34-sized encoder
    assert sizes["cpu-small"] < sizes["gpu-medium"] < sizes["paper"]
    with pytest.raises(ValueError, match="unknown model preset 'huge'"):
        get_preset("huge")
    with pytest.raises(ValueError, match="num_heads 3 must divide attention_dim 32"):
        FusionConfig(num_heads=3)


def test_encoder_and_unet_shapes_for_odd_sizes() -> None:
    enc = ImageEncoder(TINY.encoder)
    assert enc(torch.rand(2, 3, 30, 42)).shape == (2, 8, 8, 11)
    unet = VolumeUNet(5, TINY.volume)
    assert unet(torch.rand(1, 5, 5, 6, 7)).shape == (1, 4, 5, 6, 7)


def test_masked_softmax_partial_all_masked_and_extremes() -> None:
    logits = torch.tensor([[1.0, 2.0, 3.0], [1e30, -1e30, 0.0], [5.0, 5.0, 5.0]], requires_grad=True)
    mask = torch.tensor([[True, False, True], [True, True, False], [False, False, False]])
    weights, valid = masked_softmax(logits, mask)
    assert valid.tolist() == [True, True, False]
    assert weights[0, 1] == 0 and weights[0].sum().item() == pytest.approx(1.0)
    assert weights[1].tolist() == [1.0, 0.0, 0.0]
    assert weights[2].tolist() == [0.0, 0.0, 0.0]
    (weights * torch.arange(3.0)).sum().backward()
    assert logits.grad is not None and torch.isfinite(logits.grad).all()
    assert logits.grad[2].abs().sum() == 0


def test_attention_ignores_masked_views() -> None:
    torch.manual_seed(1)
    att = CrossViewAttention(8, 2)
    x = torch.randn(4, 5, 8)
    mask = torch.tensor([[True, True, False, True, False]]).expand(4, 5)
    y1 = att(x, mask)
    x2 = x.clone()
    x2[:, [2, 4]] = torch.randn(4, 2, 8) * 100  # change only the masked views
    y2 = att(x2, mask)
    torch.testing.assert_close(y1[:, [0, 1, 3]], y2[:, [0, 1, 3]])
    none = att(x, torch.zeros(4, 5, dtype=torch.bool))  # the extra token keeps it finite
    assert torch.isfinite(none).all()


def test_field_outputs_shapes_validity_and_unseen_points(model: GovNeSF) -> None:
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    points = torch.tensor([[[0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 9.0]]])  # seen, behind, outside vol
    out = model(views, volume, BOUNDS, points, torch.tensor([[0.0, 0.0, 1.0]]))
    assert out.sigma.shape == (1, 3) and out.rgb.shape == (1, 3, 3) and out.ov.shape == (1, 3, 6)
    assert out.valid[0].tolist() == [True, False, True]
    assert out.rgb[0, 1].abs().sum() == 0 and out.ov[0, 1].abs().sum() == 0  # no view: zero, not NaN
    assert out.sigma[0, 0] > 0 and out.sigma[0, 2] == 0  # sigma is 0 outside the volume
    for t in (out.sigma, out.rgb, out.ov):
        assert torch.isfinite(t).all()


def test_constant_colour_scene_blends_to_that_colour(model: GovNeSF) -> None:
    views = make_views(model)
    views.rgb[:] = torch.tensor([0.2, 0.5, 0.7]).reshape(1, 3, 1, 1)
    volume = model.build_volume(views, BOUNDS)
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(4, 5, 3, generator=g) * torch.tensor([0.4, 0.3, 1.5]) + torch.tensor([-0.2, -0.15, 1.0])
    out = model(
        views, volume, BOUNDS, pts, torch.nn.functional.normalize(torch.randn(4, 3, generator=g), dim=-1)
    )
    assert out.valid.all()
    torch.testing.assert_close(out.rgb, torch.tensor([0.2, 0.5, 0.7]).expand(4, 5, 3))


def test_ov_is_source_view_agnostic_and_point_mode_matches(model: GovNeSF) -> None:
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    pts = torch.tensor([[[0.1, 0.0, 1.5], [-0.1, 0.1, 2.5]]])
    a = model(views, volume, BOUNDS, pts, torch.tensor([[0.0, 0.0, 1.0]]))
    b = model(
        views, volume, BOUNDS, pts, torch.nn.functional.normalize(torch.tensor([[0.5, 0.2, 1.0]]), dim=-1)
    )
    torch.testing.assert_close(a.ov, b.ov)
    assert not torch.allclose(a.rgb, b.rgb)  # colour weights do depend on the query direction
    point = model.query_points(views, volume, BOUNDS, pts[0])
    torch.testing.assert_close(point.ov, a.ov[0])
    assert point.num_views.tolist() == [3, 3] and point.valid.all()


def test_depth_guided_masking(model: GovNeSF) -> None:
    depth = torch.zeros(3, H, W)
    depth[0] = 2.0  # agrees with a point at z = 2.0
    depth[1] = 1.0  # occluder in front: |2 - 1| > 0.25 * 1 -> masked
    # view 2 has no depth (0): never masked
    views = make_views(model, depth=depth)
    volume = model.build_volume(views, BOUNDS)
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.4]])  # 2.4: |2.4 - 2| = 0.4 <= 0.5 keeps view 0
    with_dgm = model.query_points(views, volume, BOUNDS, pts, depth_guided_masking=True)
    without = model.query_points(views, volume, BOUNDS, pts, depth_guided_masking=False)
    assert without.num_views.tolist() == [3, 3]
    assert with_dgm.num_views.tolist() == [2, 2]
    far = model.query_points(
        views, volume, BOUNDS, torch.tensor([[0.0, 0.0, 3.0]]), depth_guided_masking=True
    )
    assert far.num_views.tolist() == [1]  # view 0: |3 - 2| > 0.5 masked; view 1 masked; view 2 kept


def test_ov_loss_does_not_reach_the_density_but_colour_loss_does() -> None:
    torch.manual_seed(0)
    model = GovNeSF(TINY)
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    origins, dirs = pixel_rays(views.K[0], views.world_from_cam[0], W, H)
    rays = Rays(origins.reshape(-1, 3)[::7], dirs.reshape(-1, 3)[::7])
    out = render_rays(
        model, views, volume, BOUNDS, rays, stratified=True, generator=torch.Generator().manual_seed(0)
    )
    target_ov = torch.randn_like(out.ov)
    ov_cosine_loss(out.ov, target_ov).backward(retain_graph=True)
    density_grads = [p.grad for p in model.density.parameters()]
    assert all(g is None or g.abs().sum() == 0 for g in density_grads)
    fusion_grad = model.fusion.mlp_s[0].weight.grad
    assert fusion_grad is not None and fusion_grad.abs().sum() > 0  # the OV branch does learn
    model.zero_grad()
    loss = govnesf_loss(out.rgb, torch.rand_like(out.rgb), out.ov, target_ov, ov_weight=0.5)
    loss.total.backward()
    assert loss.total.item() == pytest.approx(loss.color.item() + 0.5 * loss.ov.item())
    density_grad = model.density.mlp[0].weight.grad
    assert density_grad is not None and density_grad.abs().sum() > 0
    assert model.encoder.head.weight.grad is not None  # gradients reach the encoder via the cost volume


def test_bf16_autocast_forward_on_cpu(model: GovNeSF) -> None:
    views = make_views(model)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        volume = model.build_volume(views, BOUNDS)
        origins, dirs = pixel_rays(views.K[0], views.world_from_cam[0], W, H)
        rays = Rays(origins.reshape(-1, 3)[:20], dirs.reshape(-1, 3)[:20])
        out = render_rays(model, views, volume, BOUNDS, rays)
    ref = render_rays(model, views, model.build_volume(views, BOUNDS), BOUNDS, rays)
    for t in (out.rgb, out.ov, out.depth_m, out.opacity):
        assert torch.isfinite(t).all()
    torch.testing.assert_close(out.rgb.float(), ref.rgb, atol=0.1, rtol=0.1)


def test_distill_mode_regresses_ov() -> None:
    torch.manual_seed(0)
    model = GovNeSF(TINY, mode="distill")
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0]])
    out = model.query_points(views, volume, BOUNDS, pts)
    assert out.ov.shape == (2, 6) and out.valid.tolist() == [True, False]
    assert out.ov[1].abs().sum() == 0
    out.ov.sum().backward()
    assert model.distill is not None and model.distill.mlp[0].weight.grad is not None
    with pytest.raises(ValueError, match="mode 'nope'"):
        GovNeSF(TINY, mode="nope")  # type: ignore[arg-type]


def test_distill_head_sizes() -> None:
    """Default sizes keep the first checkpoints' parameter names; wider / deeper heads regress the
    same output shape; bad sizes are refused."""
    default = GovNeSF(TINY, mode="distill").distill
    assert default is not None
    names = sorted(n for n, _ in default.named_parameters())
    assert names == ["mlp.0.bias", "mlp.0.weight", "mlp.2.bias", "mlp.2.weight"]
    assert default.mlp[0].out_features == 2 * TINY.fusion.hidden_dim
    big_cfg = replace(TINY, fusion=replace(TINY.fusion, distill_hidden_dim=40, distill_layers=3))
    torch.manual_seed(0)
    model = GovNeSF(big_cfg, mode="distill")
    assert model.distill is not None
    linears = [m for m in model.distill.mlp if isinstance(m, torch.nn.Linear)]
    assert [m.out_features for m in linears] == [40, 40, 40, TINY.fusion.ov_dim]
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    out = model.query_points(views, volume, BOUNDS, torch.tensor([[0.0, 0.0, 2.0]]))
    assert out.ov.shape == (1, TINY.fusion.ov_dim) and torch.isfinite(out.ov).all()
    for bad in ({"distill_hidden_dim": -1}, {"distill_layers": 0}):
        with pytest.raises(ValueError, match="fusion sizes"):
            replace(TINY.fusion, **bad)


def test_incremental_cost_volume_feeds_the_same_network_input(model: GovNeSF) -> None:
    views = make_views(model)
    feats = views.features.detach()
    incremental = CostVolume(BOUNDS, feature_dim=feats.shape[1])
    for i in range(len(views)):
        incremental.add_view(i, feats[i], views.K[i], views.world_from_cam[i], views.image_wh)
    batch = cost_volume_features(
        *build_cost_volume(BOUNDS, feats, views.K, views.world_from_cam, views.image_wh)
    )
    torch.testing.assert_close(incremental.network_input(), batch, atol=1e-5, rtol=1e-5)


def test_source_views_validate_shapes() -> None:
    with pytest.raises(ValueError, match=r"K \(N, 4\)"):
        SourceViews(
            torch.rand(2, 3, 4, 4),
            torch.rand(2, 8, 1, 1),
            torch.rand(2, 6, 1, 1),
            torch.rand(3, 4),
            torch.eye(4).repeat(2, 1, 1),
        )


def test_clip_to_volume_samples_only_inside_the_bounds(model: GovNeSF) -> None:
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    origins, dirs = pixel_rays(views.K[1], views.world_from_cam[1], W, H)
    rays = Rays(origins.reshape(-1, 3)[::5], dirs.reshape(-1, 3)[::5])
    clipped = render_rays(model, views, volume, BOUNDS, rays, clip_to_volume=True)
    full = render_rays(model, views, volume, BOUNDS, rays, clip_to_volume=False)
    pts = rays.origins[:, None] + clipped.t[..., None] * rays.directions[:, None]
    lo, hi = torch.tensor(BOUNDS.origin_m), torch.tensor(BOUNDS.max_corner_m)
    assert ((pts >= lo - 1e-5) & (pts <= hi + 1e-5)).all()
    full_pts = rays.origins[:, None] + full.t[..., None] * rays.directions[:, None]
    assert not ((full_pts >= lo) & (full_pts <= hi)).all()  # without clipping, samples fall outside
    assert torch.isfinite(clipped.rgb).all() and torch.isfinite(clipped.depth_m).all()


def test_weight_threshold_prunes_appearance_but_keeps_the_result(model: GovNeSF) -> None:
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    origins, dirs = pixel_rays(views.K[0], views.world_from_cam[0], W, H)
    rays = Rays(origins.reshape(-1, 3)[::9], dirs.reshape(-1, 3)[::9])
    exact = render_rays(model, views, volume, BOUNDS, rays)
    pruned = render_rays(model, views, volume, BOUNDS, rays, weight_threshold=1e-3)
    assert (exact.weights <= 1e-3).any()  # something was actually pruned
    dropped = (exact.weights * (exact.weights <= 1e-3)).sum(dim=-1, keepdim=True)  # weight left out
    assert ((pruned.rgb - exact.rgb).abs() <= dropped + 1e-6).all()  # colours are in [0, 1]
    torch.testing.assert_close(pruned.depth_m, exact.depth_m)
    nothing = render_rays(model, views, volume, BOUNDS, rays, weight_threshold=2.0)  # keeps no sample
    assert nothing.rgb.abs().sum() == 0 and torch.isfinite(nothing.ov).all()
    with pytest.raises(ValueError, match="weight_threshold -1"):
        render_rays(model, views, volume, BOUNDS, rays, weight_threshold=-1)


def test_chunked_point_queries_and_whole_image_rendering_match_unchunked(model: GovNeSF) -> None:
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    g = torch.Generator().manual_seed(7)
    pts = torch.rand(23, 3, generator=g) * torch.tensor([2.0, 2.0, 3.0]) - torch.tensor([1.0, 1.0, 0.0])
    whole = model.query_points(views, volume, BOUNDS, pts)
    chunked = model.query_points(views, volume, BOUNDS, pts, chunk_size=5)
    torch.testing.assert_close(chunked.ov, whole.ov)
    assert torch.equal(chunked.num_views, whole.num_views)
    image = render_image(
        model, views, volume, BOUNDS, views.K[0], views.world_from_cam[0], (W, H), chunk_rays=100
    )
    assert image.rgb.shape == (H, W, 3) and image.ov.shape == (H, W, 6) and image.depth_m.shape == (H, W)
    origins, dirs = pixel_rays(views.K[0], views.world_from_cam[0], W, H)
    row = render_rays(model, views, volume, BOUNDS, Rays(origins[5], dirs[5]))
    torch.testing.assert_close(image.rgb[5], row.rgb)
    torch.testing.assert_close(image.depth_m[5], row.depth_m)


def test_tiny_model_overfits_a_view() -> None:
    """Gradients flow end to end: a few AdamW steps lower the colour + OV loss clearly."""
    torch.manual_seed(0)
    model = GovNeSF(TINY)
    views = make_views(model, seed=1)
    target_ov_map = views.ov[0]
    origins, dirs = pixel_rays(views.K[0], views.world_from_cam[0], W, H)
    idx = torch.arange(0, W * H, 7)
    rays = Rays(origins.reshape(-1, 3)[idx], dirs.reshape(-1, 3)[idx])
    target_rgb = views.rgb[0].permute(1, 2, 0).reshape(-1, 3)[idx]
    uv = torch.stack([idx % W, idx // W], dim=-1).float() + 0.5
    target_ov, _ = sample_bilinear(target_ov_map, scale_uv(uv, (W, H), (8, 6)))
    optim = torch.optim.AdamW(model.parameters(), lr=5e-3)
    losses = []
    for _ in range(12):
        views = model.make_source_views(views.rgb, views.ov, views.K, views.world_from_cam)
        out = render_rays(model, views, model.build_volume(views, BOUNDS), BOUNDS, rays)
        loss = govnesf_loss(out.rgb, target_rgb, out.ov, target_ov, ov_weight=1.0)
        optim.zero_grad()
        loss.total.backward()
        optim.step()
        losses.append(loss.total.item())
    assert all(torch.isfinite(torch.tensor(losses)))
    assert min(losses[-3:]) < 0.6 * losses[0]


def test_render_depth_maps_equal_the_depth_of_full_renders(model: GovNeSF) -> None:
    views = make_views(model)
    volume = model.build_volume(views, BOUNDS)
    depth, opacity = render_depth_maps(model, volume, BOUNDS, views.K[:2], views.world_from_cam[:2], W, H,
                                       min_opacity=0.0)
    assert depth.shape == (2, H, W) and opacity.shape == (2, H, W)
    for i in range(2):
        origins, dirs = pixel_rays(views.K[i], views.world_from_cam[i], W, H)
        rays = Rays(origins.reshape(-1, 3), dirs.reshape(-1, 3))
        full = render_rays(model, views, volume, BOUNDS, rays, clip_to_volume=True)
        hit = full.t[:, -1] > full.t[:, 0] + 1e-4  # rays that cross the volume
        z = full.depth_m * (rays.directions @ views.world_from_cam[i, :3, 2])
        torch.testing.assert_close(depth[i].reshape(-1)[hit], z[hit], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(opacity[i].reshape(-1)[hit], full.opacity[hit], atol=1e-6, rtol=1e-5)
        assert bool((opacity[i].reshape(-1)[~hit] == 0).all())
    strict, _ = render_depth_maps(model, volume, BOUNDS, views.K[:1], views.world_from_cam[:1], W, H,
                                  min_opacity=1.1)
    assert not strict.any()  # no pixel reaches an opacity above 1: all "no surface"


def test_distortion_loss_prefers_one_sharp_interval_and_matches_a_float64_reference() -> None:
    t = torch.linspace(1.0, 5.0, 9).expand(3, 9).clone()
    sharp = torch.zeros(3, 9)
    sharp[:, 4] = 1.0
    two = torch.zeros(3, 9)
    two[:, 1] = two[:, 7] = 0.5
    flat = torch.full((3, 9), 1.0 / 9)
    ls, lt, lf = distortion_loss(sharp, t), distortion_loss(two, t), distortion_loss(flat, t)
    assert 0 < ls < lf < lt  # one surface < spread < two separated surfaces
    # float64 reference of sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 d_i for one ray
    w = two[0].double()
    s = (t[0].double() - 1.0) / 4.0
    d = torch.full((9,), 0.125, dtype=torch.float64)
    ref = (w[:, None] * w[None, :] * (s[:, None] - s[None, :]).abs()).sum() + (w * w * d).sum() / 3
    assert abs(float(lt) - float(ref)) < 1e-6
    w_req = flat.clone().requires_grad_(True)
    distortion_loss(w_req, t).backward()
    assert w_req.grad is not None and bool(torch.isfinite(w_req.grad).all())
    with pytest.raises(ValueError, match="same"):
        distortion_loss(flat, t[:, :5])


@pytest.mark.parametrize("layout", ["pnc", "ncp"])
def test_blend_matches_a_float64_reference_in_both_memory_layouts(layout: str) -> None:
    from mapper.model.fusion import blend

    g = torch.Generator().manual_seed(0)
    P, N, C = 37, 5, 11
    w = torch.rand(P, N, generator=g, dtype=torch.float64)
    base = torch.rand(P, N, C, generator=g, dtype=torch.float64)
    values = base if layout == "pnc" else base.permute(1, 2, 0).contiguous().permute(2, 0, 1)
    assert (values.stride(0) == 1) == (layout == "ncp")
    ref = (w[..., None] * base).sum(1)
    torch.testing.assert_close(blend(w, values), ref)
    torch.testing.assert_close(blend(w.float(), values.float()), ref.float())
    w_req = w.clone().requires_grad_(True)
    v_req = values.detach().clone().requires_grad_(True) if layout == "pnc" else \
        base.permute(1, 2, 0).contiguous().requires_grad_(True)
    v_in = v_req if layout == "pnc" else v_req.permute(2, 0, 1)
    assert torch.autograd.gradcheck(lambda a, b: blend(a, b if layout == "pnc" else b.permute(2, 0, 1)),
                                    (w_req, v_req))
    assert blend(w_req, v_in).shape == (P, C)
    with torch.no_grad():  # the fast path (inference) and the autograd path agree
        torch.testing.assert_close(blend(w_req, v_in), ref)
