"""Real RGB-D scenes (colour + depth, no ov maps) in the training mix.

``write_tiny_rgbd`` writes what ``govnesf import`` makes of a real sequence: the wall scene of
test_data.py with colour, depth and poses but no ov maps and no ``gt/``, optionally at another
image size (intrinsics scaled with it).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from test_data import (
    K_TINY,
    OV_DIM,
    WALL_Y_M,
    H,
    W,
    _wall_xz,
    camera_pose,
    tiny_model_config,
    write_tiny_scene,
)

from mapper.model.field import GovNeSF
from mapper.training.data import (
    DEFAULT_OV_DIM,
    RaySampler,
    TrainSample,
    drop_frames,
    held_out_positions,
    load_scene,
    resize_view,
)
from mapper.training.train import TrainConfig, train, train_step
from protocol.messages import Frame
from protocol.recording import RecordingWriter


def render_rgbd(pose: np.ndarray, w: int, h: int, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """rgb (h, w, 3) uint8 and depth (h, w) of the test wall (smooth texture, as test_data's)."""
    x, z = _wall_xz(pose, w, h, K)
    rgb = np.stack(
        [0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(4 * z), 0.5 + 0.3 * np.sin(2 * (x + z))], -1
    )
    depth = np.full((h, w), WALL_Y_M - pose[1, 3], np.float32)
    return (rgb * 255).round().astype(np.uint8), depth


def write_tiny_rgbd(
    out: Path,
    n_frames: int = 5,
    seed: int = 7,
    scale: int = 1,
    *,
    depth: bool = True,
    ov_frames: tuple[int, ...] = (),
) -> Path:
    """A recording without ov maps (frames listed in ``ov_frames`` get one), ``scale`` x the test size."""
    out.mkdir(parents=True)
    w, h, K = W * scale, H * scale, K_TINY * scale
    xs = np.linspace(-1.2, 1.2, n_frames) + np.random.default_rng(seed).uniform(-0.02, 0.02, n_frames)
    with RecordingWriter(out / "frames.govrec", meta={"source_format": "test"}) as rec:
        for i, x in enumerate(xs):
            pose = camera_pose(float(x), 0.9)
            rgb, d = render_rgbd(pose, w, h, K)
            ov = np.zeros((h // 4, w // 4, OV_DIM), np.float16) if i in ov_frames else None
            rec.write(
                Frame(
                    seq=i,
                    stamp_ns=i * 100_000_000,
                    width=w,
                    height=h,
                    K=K,
                    world_from_cam=pose,
                    rgb=rgb,
                    depth_m=d if depth else None,
                    ov=ov,
                    ov_space="minilm-l6-v2" if ov is not None else None,
                )
            )
    return out


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("realmix")
    write_tiny_scene(root / "train" / "tiny_s0", n_frames=6, seed=0)
    write_tiny_rgbd(root / "real" / "room_a", n_frames=5, seed=7)
    write_tiny_rgbd(root / "big" / "room_b", n_frames=4, seed=8, scale=2)
    return root


def test_recording_without_ov_loads_only_with_require_ov_false(roots: Path, tmp_path: Path) -> None:
    path = roots / "real" / "room_a"
    with pytest.raises(ValueError, match="frame 0 has depth=True, ov=False.*require_ov=False"):
        load_scene(path)
    s = load_scene(path, require_ov=False)
    assert not s.has_ov and s.num_frames == 5 and s.image_wh == (W, H)
    assert s.ov.shape == (5, H // 4, W // 4, DEFAULT_OV_DIM) and s.ov.dtype == np.float16
    assert not s.ov.any() and s.class_names == []
    s8 = load_scene(path, require_ov=False, ov_shape=(3, 5, OV_DIM))
    assert s8.ov.shape == (5, 3, 5, OV_DIM) and s8.ov_dim == OV_DIM
    np.testing.assert_allclose(s8.points_m.reshape(-1, 3)[:, 1], WALL_Y_M, atol=1e-4)  # depth is used
    assert load_scene(roots / "train" / "tiny_s0", require_ov=False).has_ov  # a sim scene is unchanged
    with pytest.raises(ValueError, match="depth=False.*training needs depth"):
        load_scene(write_tiny_rgbd(tmp_path / "no_depth", 3, depth=False), require_ov=False)
    with pytest.raises(ValueError, match="2 frames have ov maps and 1"):
        load_scene(write_tiny_rgbd(tmp_path / "mixed", 3, ov_frames=(0, 2)), require_ov=False)


def test_resize_scales_K_with_the_image(roots: Path) -> None:
    big = load_scene(roots / "big" / "room_b", require_ov=False)
    small = load_scene(roots / "big" / "room_b", require_ov=False, image_wh=(W, H))
    assert big.image_wh == (2 * W, 2 * H) and small.image_wh == (W, H)
    assert small.rgb.shape == (4, H, W, 3) and small.depth_m.shape == (4, H, W)
    np.testing.assert_allclose(small.K, np.tile(K_TINY, (4, 1)))
    # a world point on the wall projects to the same place of the image before and after
    pose = big.world_from_cam[1]
    cam_from_world = np.linalg.inv(pose)
    p_cam = cam_from_world[:3, :3] @ np.array([0.3, WALL_Y_M, 1.2]) + cam_from_world[:3, 3]

    def project(K: np.ndarray) -> np.ndarray:
        return np.array([K[0] * p_cam[0] / p_cam[2] + K[2], K[1] * p_cam[1] / p_cam[2] + K[3]])

    uv_big, uv_small = project(big.K[1]), project(small.K[1])
    np.testing.assert_allclose(uv_small, uv_big * np.array([W / (2 * W), H / (2 * H)]), atol=1e-9)
    # ... and the resized pixels there show what a camera of that size sees (area average of the
    # smooth texture; depth nearest, still the wall)
    expect_rgb, _ = render_rgbd(pose, W, H, K_TINY)
    err = np.abs(small.rgb[1].astype(int) - expect_rgb.astype(int))
    assert err.max() <= 3, err.max()
    col, row = (uv_small // 1).astype(int)
    assert abs(int(small.rgb[1][row, col, 0]) - int(expect_rgb[row, col, 0])) <= 2
    np.testing.assert_allclose(small.points_m.reshape(-1, 3)[:, 1], WALL_Y_M, atol=1e-4)
    np.testing.assert_array_equal(small.depth_m, big.depth_m[:, 1::2, 1::2])
    # the helper keeps the size when it already fits
    rgb0, depth0 = big.rgb[0], big.depth_m[0]
    rgb, depth, K, _ = resize_view(rgb0, depth0, big.K[0], big.image_wh)
    assert rgb is rgb0 and depth is depth0 and np.array_equal(K, big.K[0])


def _samplers(roots: Path, weight: float, **kw: Any) -> tuple[RaySampler, RaySampler]:
    cfg = tiny_model_config()
    sim = load_scene(roots / "train" / "tiny_s0")
    real = load_scene(roots / "real" / "room_a", require_ov=False, ov_shape=(H // 4, W // 4, OV_DIM))
    plain = RaySampler([sim], cfg, rays_per_view=16, seed=5, **kw)
    mixed = RaySampler([sim], cfg, rays_per_view=16, seed=5, extra_scenes=[real], extra_weight=weight, **kw)
    return plain, mixed


def _same(a: TrainSample, b: TrainSample) -> bool:
    names = ("origins", "directions", "target_rgb", "target_ov", "target_t")
    src = ("rgb", "ov", "depth_m", "K", "world_from_cam")
    return (
        all(torch.equal(getattr(a, n), getattr(b, n)) for n in names)
        and all(torch.equal(getattr(a.sources, n), getattr(b.sources, n)) for n in src)
        and a.seed == b.seed
        and a.sources.bounds == b.sources.bounds
    )


def test_mixed_sampler_draws_both_kinds_deterministically(roots: Path) -> None:
    plain, mixed = _samplers(roots, 0.5, frustum_bounds_prob=0.5, photometric_prob=0.5)
    kinds = []
    for step in range(12):
        for item in range(2):
            s = mixed.sample(step, item)
            kinds.append(s.has_ov)
            assert s.has_ov == (s.scene == "tiny_s0")
            assert _same(s, mixed.sample(step, item))  # a pure function of (seed, step, item)
            if s.has_ov:  # examples from the main scenes are those of a sampler without extras
                assert _same(s, plain.sample(step, item))
            else:
                assert s.target_ov.shape == (16, OV_DIM) and not s.target_ov.any()
                assert s.sources.ov.shape == (3, OV_DIM, H // 4, W // 4) and not s.sources.ov.any()
                assert s.target_t is not None and bool((s.target_t > 0).all()) and s.target_rgb.max() > 0
    assert 4 <= sum(kinds) <= 20, kinds  # both kinds, about half each
    with pytest.raises(ValueError, match="extra_weight"):
        RaySampler(plain.scenes, plain.cfg, rays_per_view=4, extra_weight=0.5)
    with pytest.raises(ValueError, match="ov_shape"):
        RaySampler(
            plain.scenes,
            plain.cfg,
            rays_per_view=4,
            extra_scenes=[load_scene(roots / "real" / "room_a", require_ov=False)],
        )


def test_extra_weight_zero_leaves_the_samples_unchanged(roots: Path) -> None:
    plain, mixed = _samplers(roots, 0.0, frustum_bounds_prob=0.5, photometric_prob=0.5)
    for step, item in ((0, 0), (0, 1), (3, 0), (7, 1), (11, 0)):
        a, b = plain.sample(step, item), mixed.sample(step, item)
        assert a.has_ov and b.has_ov and _same(a, b)


def test_train_step_on_ov_less_examples_masks_every_ov_term(roots: Path) -> None:
    torch.set_num_threads(1)
    _, mixed = _samplers(roots, 1.0)  # every example from the real scene
    cfg = TrainConfig(
        preset="tiny",
        batch_views=2,
        rays_per_view=16,
        warmup_steps=0,
        depth_weight=1.0,
        surface_weight=0.5,
        point_ov_weight=1.0,
        visibility_weight=0.5,
    )
    torch.manual_seed(0)
    model = GovNeSF(tiny_model_config())
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    stats = train_step(model, opt, mixed, cfg, 0, 0, 1, torch.device("cpu"))
    assert stats["ov"] == 0.0 and stats["point_ov"] == 0.0
    for key in ("color", "depth", "surface", "visibility", "loss", "grad_norm"):
        assert np.isfinite(stats[key]), (key, stats)
    assert stats["color"] > 0 and stats["depth"] > 0 and stats["surface"] > 0
    expect = stats["color"] + stats["depth"] + 0.5 * stats["surface"] + 0.5 * stats["visibility"]
    assert stats["loss"] == pytest.approx(expect, rel=1e-6)
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())
    # the same step on the simulated scene reports its OV terms
    sim = RaySampler(mixed.scenes, mixed.cfg, rays_per_view=16)
    with_ov = train_step(model, opt, sim, cfg, 0, 0, 1, torch.device("cpu"))
    assert with_ov["ov"] > 0


def test_config_errors_and_a_short_mixed_run(roots: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"extra_train_weight = 1\.5 out of range: must be in \[0, 1\]"):
        TrainConfig(extra_train_dirs=["x"], extra_train_weight=1.5)
    with pytest.raises(ValueError, match="extra_train_weight = 0.3 .*0 when extra_train_dirs is empty"):
        TrainConfig(extra_train_weight=0.3)
    with pytest.raises(ValueError, match="extra_train_dirs = 'data/real' .*a list of folder paths"):
        TrainConfig(extra_train_dirs="data/real")  # type: ignore[arg-type]
    base: dict[str, Any] = dict(
        preset="tiny",
        train_dir=str(roots / "train"),
        val_dir="",
        max_steps=2,
        batch_views=2,
        rays_per_view=16,
        warmup_steps=0,
        threads=1,
        log_every=1,
    )
    missing = TrainConfig(**base, out_dir=str(tmp_path / "a"), extra_train_dirs=[str(tmp_path / "nowhere")])
    with pytest.raises(FileNotFoundError, match="extra_train_dirs: folder .*nowhere does not exist"):
        train(missing, model_cfg=tiny_model_config(), progress=False)
    run = TrainConfig(
        **base,
        out_dir=str(tmp_path / "b"),
        extra_train_dirs=[str(roots / "real"), str(roots / "big")],  # a root of scenes, resized on load
        extra_train_weight=0.5,
    )
    result = train(run, model_cfg=tiny_model_config(), progress=False)
    assert result["step"] == 2 and all(np.isfinite(v) for v in result["train"].values())
    start = json.loads((tmp_path / "b" / "log.jsonl").read_text().splitlines()[0])
    assert start["train_scenes"] == 1 and start["extra_train_scenes"] == 2


def test_held_out_frames_of_a_real_sequence_never_train(roots: Path, tmp_path: Path) -> None:
    """``extra_holdout_every`` drops the evaluation's held-out poses (and neighbours) from the mix."""
    mask = held_out_positions(211, 10, 2)
    # every multiple of 10 and the two frames on each side of it go; the rest stay
    assert mask[[0, 1, 2, 8, 9, 10, 12, 208, 210]].all() and not mask[[3, 7, 13, 17, 203, 207]].any()
    assert mask.sum() == 3 + sum(5 for _ in range(10, 210, 10)) + 3  # 0, 10 .. 200, 210 (edges cut)
    assert not held_out_positions(7, 0, 2).any()
    with pytest.raises(ValueError, match="must be >= 0"):
        held_out_positions(7, -1, 0)

    scene = load_scene(roots / "real" / "room_a", require_ov=False)  # 5 frames
    kept = drop_frames(scene, held_out_positions(scene.num_frames, 4, 0))  # drops 0 and 4
    assert kept.num_frames == 3 and not kept.has_ov
    np.testing.assert_array_equal(kept.world_from_cam, scene.world_from_cam[1:4])
    np.testing.assert_array_equal(kept.rgb, scene.rgb[1:4])
    np.testing.assert_array_equal(kept.depth_m, scene.depth_m[1:4])
    assert kept.ov.shape == (3, *scene.ov.shape[1:]) and not kept.ov.any() and kept.ov.base is not None
    with pytest.raises(ValueError, match="would keep 1 frame"):
        drop_frames(scene, np.arange(5) != 2)
    with pytest.raises(ValueError, match="mask of shape"):
        drop_frames(scene, np.zeros(4, bool))
    with pytest.raises(ValueError, match="extra_holdout_radius = 2 out of range"):
        TrainConfig(extra_holdout_every=4, extra_holdout_radius=2)

    run = TrainConfig(
        preset="tiny",
        train_dir=str(roots / "train"),
        val_dir="",
        max_steps=1,
        batch_views=2,
        rays_per_view=16,
        warmup_steps=0,
        threads=1,
        log_every=1,
        out_dir=str(tmp_path / "h"),
        extra_train_dirs=[str(roots / "real")],
        extra_train_weight=0.5,
        extra_holdout_every=4,
        extra_holdout_radius=0,
    )
    train(run, model_cfg=tiny_model_config(), progress=False)
    start = json.loads((tmp_path / "h" / "log.jsonl").read_text().splitlines()[0])
    assert start["extra_train_frames"] == [3]
