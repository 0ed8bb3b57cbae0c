"""Tests for mapper.training.evaluate and `govnesf evaluate` on a tiny synthetic scene with known answers.

The scene: a labelled floor (z = 0) seen by four cameras 2 m above it looking straight down; the
OV maps are the exact text embedding of the label under each pixel, so a correct pipeline
classifies every point away from the label boundaries perfectly.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from mapper.model.baselines import average_features
from mapper.model.checkpoint import save_checkpoint
from mapper.model.config import EncoderConfig, FusionConfig, ModelConfig, RenderConfig, VolumeConfig
from mapper.model.field import GovNeSF, SourceViews
from mapper.model.ops.cost_volume import VolumeBounds
from mapper.training import evaluate as ev
from mapper.training.cli_eval import main as eval_main
from mapper.training.data import Scene
from mapper.training.metrics import NUM_SCANNET_CLASSES

W, H = 64, 48
K = np.array([40.0, 40.0, 32.0, 24.0])  # a pixel is 5 cm on the floor from 2 m
HEIGHT_M = 2.0
CENTRES = np.array([[-0.3, -0.2], [0.3, -0.2], [-0.3, 0.2], [0.3, 0.2]])
D = 8

TINY = ModelConfig(
    name="tiny",
    encoder=EncoderConfig(base_channels=8, blocks=(1, 1, 1), feature_dim=8),
    volume=VolumeConfig(unet_channels=(4, 8, 8), group_norm_groups=4, volume_feature_dim=4, max_voxels=512),
    fusion=FusionConfig(hidden_dim=16, attention_dim=8, num_heads=2, ov_dim=D),
    render=RenderConfig(n_samples=8, near_m=0.5, far_m=3.5),
    num_source_views=3,
    image_wh=(W, H),
)


def floor_label(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Three regions: 0 (x < 0), 1 (x >= 0, y < 0), 2 (x >= 0, y >= 0)."""
    return np.where(x < 0, 0, np.where(y < 0, 1, 2))


def down_pose(cx: float, cy: float) -> np.ndarray:
    """world_from_cam of a camera at (cx, cy, 2 m) looking down: cam x = world x, cam y = -world y."""
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = [cx, cy, HEIGHT_M]
    return pose


def text_embeddings() -> torch.Tensor:
    """(20, D) distinct unit vectors: classes 0..D-1 one-hot, the rest random (never the answer)."""
    g = torch.Generator().manual_seed(0)
    emb = torch.randn(NUM_SCANNET_CLASSES, D, generator=g) * 0.1
    emb[:D] = torch.eye(D)
    return emb / emb.norm(dim=1, keepdim=True)


def pixel_floor(pose: np.ndarray, w: int, h: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """World x, y of the floor under each pixel centre of a (h, w) map (stride full-res pixels)."""
    u = (np.arange(w) + 0.5) * stride
    v = (np.arange(h) + 0.5) * stride
    uu, vv = np.meshgrid(u, v)
    x = pose[0, 3] + (uu - K[2]) / K[0] * HEIGHT_M
    y = pose[1, 3] - (vv - K[3]) / K[1] * HEIGHT_M
    return x, y


def make_scene(ov_stride: int = 2) -> ev.EvalScene:
    emb = text_embeddings().numpy()
    poses = np.stack([down_pose(*c) for c in CENTRES])
    n = len(poses)
    rgb = np.zeros((n, H, W, 3), np.uint8)
    ov = np.zeros((n, H // ov_stride, W // ov_stride, D), np.float16)
    for k, pose in enumerate(poses):
        x, y = pixel_floor(pose, W, H, 1)
        rgb[k] = (np.stack([x, y, x * y], -1) * 60 + 128).clip(0, 255).astype(np.uint8)
        xs, ys = pixel_floor(pose, W // ov_stride, H // ov_stride, ov_stride)
        ov[k] = emb[floor_label(xs, ys)]
    depth = np.full((n, H, W), HEIGHT_M, np.float32)
    # Points on a grid at least 0.3 m (several OV cells) from every label boundary, seen by all views.
    g = np.arange(-0.7, 0.71, 0.05)
    px, py = np.meshgrid(g, g)
    px, py = px.reshape(-1), py.reshape(-1)
    far = (np.abs(px) >= 0.3) & ((px < 0) | (np.abs(py) >= 0.3))
    px, py = px[far], py[far]
    xyz = np.stack([px, py, np.zeros_like(px)], -1).astype(np.float32)
    # (F, M, 3) depth points as mapper.training.data back-projects them (bounds, source selection).
    grid = np.stack([np.stack([*pixel_floor(p, W // 8, H // 8, 8), np.zeros((H // 8, W // 8))], -1)
                     .reshape(-1, 3) for p in poses]).astype(np.float32)
    data = Scene(name="floor", rgb=rgb, depth_m=depth, ov=ov, K=np.tile(K, (n, 1)), world_from_cam=poses,
                 points_m=grid, class_names=[f"class{i}" for i in range(NUM_SCANNET_CLASSES)])
    novel_pose = down_pose(0.05, 0.0)
    nx, ny = pixel_floor(novel_pose, W, H, 1)
    novel_ov = emb[floor_label(*pixel_floor(novel_pose, W // 2, H // 2, 2))][None].astype(np.float16)
    novel = ev.NovelViews(K=K[None].copy(), world_from_cam=novel_pose[None], rgb=rgb[:1].copy(),
                          label=floor_label(nx, ny)[None], ov=novel_ov)
    return ev.EvalScene(data=data, style="apartment", seed=7, gt_depth_m=depth, points_xyz=xyz,
                        points_label=floor_label(px, py).astype(np.int64),
                        points_n_views=np.full(len(px), n, np.int64), novel=novel)


@pytest.fixture(scope="module")
def scene() -> ev.EvalScene:
    return make_scene()


def tiny_model(uniform: bool = False, seed: int = 0) -> GovNeSF:
    torch.manual_seed(seed)
    model = GovNeSF(TINY).eval()
    if uniform:  # constant OV logits: the softmax blend is the plain mean over the views that see a point
        last = model.fusion.mlp_s[-1]
        torch.nn.init.zeros_(last.weight)
        torch.nn.init.zeros_(last.bias)
    return model


def sources(model: GovNeSF, scene: ev.EvalScene) -> tuple[SourceViews, VolumeBounds, torch.Tensor]:
    views, bounds = ev.scene_sources(model, scene)
    with torch.no_grad():
        volume = model.build_volume(views, bounds)
    return views, bounds, volume


def random_points(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(n, 3, generator=g) * torch.tensor([6.0, 5.0, 2.0]) - torch.tensor([3.0, 2.5, 1.0])
    return p


def test_blend_points_equals_query_points(scene: ev.EvalScene) -> None:
    model = tiny_model()
    views, bounds, volume = sources(model, scene)
    pts = random_points(300)
    for dgm in (False, True):
        ref = model.query_points(views, volume, bounds, pts, depth_guided_masking=dgm)
        got = ev.blend_points(model, views, volume, bounds, pts, depth_guided_masking=dgm, chunk_size=64)
        assert torch.equal(got.valid, ref.valid)
        assert torch.equal(got.num_views, ref.num_views)
        assert torch.allclose(got.ov, ref.ov, atol=1e-5)
        w = got.weights.sum(1)
        assert torch.allclose(w[got.valid], torch.ones_like(w[got.valid]), atol=1e-5)
        assert bool((got.weights[~got.mask] == 0).all())
    assert bool(ref.valid.any()) and bool((~ref.valid).any())  # both cases exercised


def test_uniform_weights_equal_averaging(scene: ev.EvalScene) -> None:
    model = tiny_model(uniform=True)
    views, bounds, volume = sources(model, scene)
    pts = random_points(200, seed=3)
    got = ev.blend_points(model, views, volume, bounds, pts)
    avg_views = [(scene.ov[k], scene.K[k], scene.world_from_cam[k], (W, H), None) for k in range(len(scene))]
    ref, n_ref = average_features(pts, avg_views, use_depth=False, border_px=0.0)
    assert torch.equal(got.num_views, n_ref)
    ok = got.valid
    blended = torch.nn.functional.normalize(got.ov[ok], dim=1)
    assert torch.allclose(blended, ref[ok], atol=1e-4)


def test_views_per_point_keeps_the_nearest(scene: ev.EvalScene) -> None:
    model = tiny_model()
    views, bounds, volume = sources(model, scene)
    pts = torch.from_numpy(scene.points_xyz[:50]) + torch.tensor([0.013, 0.007, 0.0])  # no distance ties
    got = ev.blend_points(model, views, volume, bounds, pts, views_per_point=2)
    assert got.mask.shape[1] == 2 and bool((got.num_views == 2).all())
    dist = torch.cdist(pts, torch.from_numpy(scene.world_from_cam[:, :3, 3]).float())
    nearest = dist.argsort(dim=1)[:, :2]
    assert torch.equal(got.view_index.sort(dim=1).values, nearest.sort(dim=1).values)
    with pytest.raises(ValueError, match="views_per_point 0"):
        ev.blend_points(model, views, volume, bounds, pts, views_per_point=0)
    sel = ev.nearest_view_selection(pts, torch.from_numpy(scene.K).float(),
                                    torch.from_numpy(scene.world_from_cam).float(), (W, H), 1, border_px=0.0)
    assert torch.equal(sel.T.float().argmax(dim=1), dist.argmin(dim=1)) and bool((sel.sum(0) == 1).all())


def test_perfect_features_give_perfect_3d_scores(scene: ev.EvalScene) -> None:
    settings = ev.EvalSettings(do_2d=False, max_points=None, averaging_borders_px=(10.0, 0.0))
    res = ev.evaluate_scene(scene, {"uniform": tiny_model(uniform=True)}, text_embeddings(), settings)["3d"]
    for name in ("Averaging (no depth)", "Averaging + depth test", "Averaging, GT-visible views (oracle)",
                 "Averaging (no depth), 0 px border", "uniform (no depth)", "uniform + DGM",
                 "Averaging + point occlusion (no depth input)",
                 "Averaging + point occlusion (no depth input), 0 px border",
                 "uniform + point occlusion (no depth input)"):
        s = res[name].scores()
        assert s.miou == pytest.approx(1.0) and s.oacc == pytest.approx(1.0), name
        assert s.num_valid == len(scene.points_xyz)
        assert res[name].extra["occluded_weight"] == pytest.approx(0.0)  # a floor occludes nothing
    # Three classes present: IoU defined for exactly those.
    assert np.isfinite(res["Averaging (no depth)"].scores().iou).sum() == 3


def test_point_occlusion_depths_hide_a_point_under_the_floor(scene: ev.EvalScene) -> None:
    floor = torch.from_numpy(scene.points_xyz)
    hidden = torch.tensor([[-0.6, 0.0, -0.7]])  # under floor points in every view: 2.7 m, floor 2 m
    xyz = torch.cat([floor, hidden])
    Kt, poses = torch.from_numpy(scene.K).float(), torch.from_numpy(scene.world_from_cam).float()
    inside, visible = ev.gt_visibility(xyz, Kt, poses, torch.from_numpy(scene.gt_depth_m))
    sp = ev.ScenePoints(gt=np.zeros(len(xyz), np.int64), xyz=xyz, K=Kt, world_from_cam=poses,
                        in_image=inside, visible=visible)  # fmt: skip
    depth = ev.point_occlusion_depths(sp, scene.image_wh, 3.0)
    assert depth.shape == (len(scene), H, W) and depth.dtype == torch.float32
    uv, z, mask = ev.candidate_views(dataclasses.replace(sources(tiny_model(), scene)[0], depth_m=depth), xyz,
                                     depth_guided_masking=True)
    assert not mask[-1].any()  # every view sees the floor in front of it
    assert mask[:-1].all()  # the floor points pass in every view: nothing is in front of them
    assert torch.allclose(z[:, :-1], torch.full_like(z[:, :-1], HEIGHT_M), atol=1e-4)


def test_occluded_weight_counts_views_that_do_not_see_the_point(scene: ev.EvalScene) -> None:
    pts = torch.tensor([[-0.5, 0.0, 0.0], [-0.5, 0.0, -0.5]])  # on the floor; 0.5 m under it (hidden)
    inside, visible = ev.gt_visibility(pts, torch.from_numpy(scene.K).float(),
                                       torch.from_numpy(scene.world_from_cam).float(),
                                       torch.from_numpy(scene.gt_depth_m))
    assert bool(inside.all())
    assert visible[0].all() and not visible[1].any()


def test_2d_scores_and_summary(scene: ev.EvalScene) -> None:
    settings = ev.EvalSettings(do_3d=False)
    res = ev.evaluate_scene(scene, {"tiny": tiny_model()}, text_embeddings(), settings)
    two = res["2d"]
    s = two["SimLSeg at the GT novel view"].scores()
    assert s.oacc > 0.95  # exact features; only pixels within half an OV cell of a boundary can flip
    assert {"psnr", "ssim", "seconds"} <= set(two["tiny"].extra)
    summary = ev.summarise({"floor": res}, {"floor": "apartment"}, scene.class_names)
    block = summary["styles"]["apartment"]["2d"]["SimLSeg at the GT novel view"]
    assert block["miou"] == pytest.approx(s.miou) and block["scenes"] == 1
    text = ev.format_report(summary)
    assert "Table 1" in text and f"{100 * s.miou:.1f}" in text
    json.dumps(summary)  # JSON-able


def test_psnr_ssim_known_values() -> None:
    g = torch.Generator().manual_seed(0)
    img = torch.rand(24, 32, 3, generator=g)
    assert ev.psnr(img, img) == float("inf")
    assert ev.psnr((img * 0.5 + 0.1), (img * 0.5 + 0.2)) == pytest.approx(20.0)  # MSE 0.01
    assert ev.ssim(img, img) == pytest.approx(1.0)
    assert ev.ssim(img, 1.0 - img) < 0.0  # anti-correlated structure
    noisy = (img + 0.05 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    assert 0.5 < ev.ssim(img, noisy) < 1.0
    with pytest.raises(ValueError, match="SSIM window"):
        ev.ssim(img[:5, :5], img[:5, :5])


# ---- CLI -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("ckpt") / "tiny"
    return str(save_checkpoint(path, tiny_model(), metadata={"preset": "tiny", "step": 0}))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "--checkpoint"),
        (["--checkpoint", "CKPT", "--data", "DATA", "--views-per-point", "0"], "'all' or a positive integer"),
        (["--checkpoint", "CKPT", "--data", "DATA", "--max-points", "-3"], "positive integer"),
        (["--checkpoint", "CKPT", "--data", "DATA", "--no-2d", "--no-3d"], "nothing to evaluate"),
        (["--checkpoint", "CKPT", "--data", "DATA", "--weight-threshold", "2"], "out of range"),
        (["--checkpoint", "CKPT", "--data", "DATA", "--averaging-border-px", "-1"], "out of range"),
        (["--checkpoint", "CKPT", "--data", "MISSING"], "no such directory"),
        (["--checkpoint", "CKPT", "--data", "DATA"], "neither a recorded scene"),
        (["--checkpoint", "NOCKPT", "--data", "SCENE", "--no-2d"], "not found"),
    ],
)
def test_cli_argument_errors(argv: list[str], message: str, checkpoint: str, tmp_path,
                             capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "frames.govrec").write_bytes(b"")
    (tmp_path / "empty").mkdir()
    subs = {"CKPT": checkpoint, "DATA": str(tmp_path / "empty"), "MISSING": str(tmp_path / "nope"),
            "NOCKPT": str(tmp_path / "nothing.json"), "SCENE": str(tmp_path / "scene")}
    code = eval_main([subs.get(a, a) for a in argv])
    assert code == 2
    assert message in capsys.readouterr().err


def test_cli_rejects_a_distill_model_as_the_main_checkpoint(tmp_path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    torch.manual_seed(0)
    path = save_checkpoint(tmp_path / "d", GovNeSF(TINY, mode="distill"), metadata={"step": 0})
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "frames.govrec").write_bytes(b"")
    assert eval_main(["--checkpoint", str(path), "--data", str(tmp_path / "scene")]) == 2
    assert "--distill" in capsys.readouterr().err


def test_render_view_stride_is_a_pixel_subgrid(scene: ev.EvalScene) -> None:
    model = tiny_model()
    views, bounds, volume = sources(model, scene)
    args = (model, views, volume, bounds, scene.novel.K[0], scene.novel.world_from_cam[0], (W, H))
    with torch.no_grad():
        rgb1, ov1 = ev.render_view(*args, pixel_stride=1, chunk_rays=500)
        rgb2, ov2 = ev.render_view(*args, pixel_stride=2, chunk_rays=500)
    assert rgb1.shape == (H, W, 3) and ov2.shape == (H // 2, W // 2, D)
    assert torch.allclose(rgb2, rgb1[1::2, 1::2], atol=1e-5)
    assert torch.allclose(ov2, ov1[1::2, 1::2], atol=1e-5)
    with pytest.raises(ValueError, match="pixel_stride 0"):
        ev.render_view(*args, pixel_stride=0)


def test_view_weight_fn_reweights_and_ones_change_nothing(scene: ev.EvalScene) -> None:
    model = tiny_model()
    views, bounds, volume = sources(model, scene)
    pts = random_points(200, seed=5)
    base = ev.blend_points(model, views, volume, bounds, pts)
    same = ev.blend_points(model, views, volume, bounds, pts,
                           view_weight_fn=lambda p, i, s: torch.ones(i.shape))
    assert torch.allclose(same.ov, base.ov, atol=1e-6)
    assert torch.allclose(same.weights, base.weights, atol=1e-6)

    def first_only(p: torch.Tensor, idx: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(idx.shape)
        out[:, 0] = 1.0
        return out

    one = ev.blend_points(model, views, volume, bounds, pts, view_weight_fn=first_only)
    ok = one.valid
    assert torch.allclose(one.weights[ok, 0], torch.ones(int(ok.sum())), atol=1e-6)
    assert bool((one.weights[ok, 1:] == 0).all())
    zero = ev.blend_points(model, views, volume, bounds, pts,
                           view_weight_fn=lambda p, i, s: torch.zeros(i.shape))
    assert torch.allclose(zero.weights, base.weights)  # all-zero multipliers keep the learned weights


def test_view_transmittance_is_a_non_increasing_probability_along_a_ray(scene: ev.EvalScene) -> None:
    model = tiny_model()
    views, bounds, volume = sources(model, scene)
    centre = torch.tensor([0.0, 0.0, 3.0])
    direction = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0]), dim=0)
    pts = centre + direction * torch.linspace(0.05, 5.0, 40)[:, None]  # (40, 3) along one ray
    T = ev.view_transmittance(model, volume, bounds, pts, centre.expand(40, 1, 3), n_samples=512)
    assert T.shape == (40, 1) and bool(((T > 0) & (T <= 1)).all())
    # farther points see through at least as much density (up to the midpoint rule's error)
    assert bool((T[:, 0].diff() <= 2e-3).all()), T[:, 0].diff().max()
    stop = 1.5 * bounds.voxel_size_m
    near = (pts - centre).norm(dim=1) <= stop
    assert bool(near.any()) and bool((T[near, 0] == 1).all())  # shorter than the stop: nothing in between


# ---- renders at measured surfaces, depth error, pixels a source sees (2D protocol) -----------------
def _floor_views(scene: ev.EvalScene) -> tuple[GovNeSF, SourceViews, VolumeBounds, torch.Tensor, tuple]:
    model = tiny_model()
    views, bounds, volume = sources(model, scene)
    at = (scene.novel.K[0], scene.novel.world_from_cam[0], (W, H))
    return model, views, bounds, volume, at


def test_render_view_full_at_known_surfaces(scene: ev.EvalScene) -> None:
    model, views, bounds, volume, (Kn, pose, wh) = _floor_views(scene)
    args = (model, views, volume, bounds, Kn, pose, wh)
    floor = np.full((H, W), HEIGHT_M, np.float32)
    floor[:4] = 0.0  # a band without a surface: marched
    with torch.no_grad():
        rgb, ov, z, at = ev.render_view_full(*args, pixel_stride=2, chunk_rays=100, surface_depth_m=floor)
        marched_rgb, marched_ov = ev.render_view(*args, pixel_stride=2, chunk_rays=100)
        _, _, marched_z, none = ev.render_view_full(*args, pixel_stride=2, chunk_rays=100)
        # the surface pixels: one appearance evaluation at the floor point of each ray
        origins, dirs = ev.pixel_rays(torch.tensor(Kn).float(), torch.tensor(pose).float(), W, H)
        o, d = origins[1::2, 1::2].reshape(-1, 3), dirs[1::2, 1::2].reshape(-1, 3)
        t = HEIGHT_M / (d @ torch.tensor(pose).float()[:3, 2])
        pts = o + t[:, None] * d
        v, _ = ev.sample_volume(volume, bounds, pts)
        ref_rgb, ref_ov, _ = model.appearance(views, v, pts, d, False)
    assert at.shape == (H // 2, W // 2) and not at[:2].any() and at[2:].all() and not none.any()
    torch.testing.assert_close(z[2:], torch.full_like(z[2:], HEIGHT_M))
    torch.testing.assert_close(rgb.reshape(-1, 3)[at.reshape(-1)], ref_rgb[at.reshape(-1)], atol=1e-5, rtol=0)
    torch.testing.assert_close(ov.reshape(-1, D)[at.reshape(-1)], ref_ov[at.reshape(-1)], atol=1e-5, rtol=0)
    # the other pixels are marched exactly as render_view marches them, depth from the march
    torch.testing.assert_close(rgb[:2], marched_rgb[:2], atol=1e-6, rtol=0)
    torch.testing.assert_close(ov[:2], marched_ov[:2], atol=1e-6, rtol=0)
    torch.testing.assert_close(z[:2], marched_z[:2], atol=1e-5, rtol=0)
    assert torch.isfinite(marched_z).all() and (marched_z >= 0).all()
    with pytest.raises(ValueError, match="surface_depth_m shape"):
        ev.render_view_full(*args, surface_depth_m=floor[:-1])


def test_sources_surface_depth_and_seen_pixels_of_the_floor(scene: ev.EvalScene) -> None:
    import dataclasses

    _, views, _, _, (Kn, pose, wh) = _floor_views(scene)
    z = ev.sources_surface_depth(views, Kn, pose, wh, footprint_m=0.05)
    has = z > 0
    assert z.shape == (H, W) and has.mean() > 0.9
    np.testing.assert_allclose(z[has], HEIGHT_M, atol=1e-4)
    assert not ev.sources_surface_depth(dataclasses.replace(views, depth_m=None), Kn, pose, wh, 0.05).any()
    true = np.full((H, W), HEIGHT_M, np.float32)
    seen = ev.seen_by_sources(views, Kn, pose, wh, true, pixel_stride=2)
    assert seen.shape == (H // 2, W // 2) and bool(seen.all())  # the sources cover the floor
    assert not ev.seen_by_sources(views, Kn, pose, wh, 0.5 * true).any()  # above the floor: hidden
    true[:, :10] = 0.0
    assert not ev.seen_by_sources(views, Kn, pose, wh, true)[:, :10].any()  # no true depth: not counted
    with pytest.raises(ValueError, match="needs the source views' depth"):
        ev.seen_by_sources(dataclasses.replace(views, depth_m=None), Kn, pose, wh, true)


def test_2d_rows_at_measured_surfaces(scene: ev.EvalScene) -> None:
    import dataclasses

    novel = dataclasses.replace(scene.novel, depth_m=np.full((1, H, W), HEIGHT_M, np.float32))
    with_depth = dataclasses.replace(scene, novel=novel)
    settings = ev.EvalSettings(do_3d=False)
    res = ev.evaluate_scene(with_depth, {"tiny": tiny_model()}, text_embeddings(), settings)
    two = res["2d"]
    surf = two["tiny at measured surfaces (depth input)"].extra
    marched = two["tiny"].extra
    assert surf["depth_median_rel_err"] < 1e-3 and surf["surface_share"] > 0.9
    assert marched["surface_share"] == 0.0 and np.isfinite(marched["depth_median_rel_err"])
    assert surf["seen_share"] > 0.95 and np.isfinite(surf["psnr_seen"])  # all but the image border
    text = ev.format_report(ev.summarise({"floor": res}, {"floor": "apartment"}, scene.class_names))
    assert "at measured surfaces (depth input)" in text and "PSNR where a source sees" in text
    off = ev.evaluate_scene(with_depth, {"tiny": tiny_model()}, text_embeddings(),
                            ev.EvalSettings(do_3d=False, surface_renders=False))["2d"]
    assert "tiny at measured surfaces (depth input)" not in off
