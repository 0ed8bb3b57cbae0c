"""mapper.training.augment: sensor effects on the sources, odometry-like pose error, a 2D model's
noisier OV maps, in the sampler."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.training.augment import motion_blur_kernel, ov_noise, perturb_poses, sensor_effects
from mapper.training.data import RaySampler, load_scene
from tests.mapper.training.test_data import tiny_model_config, write_tiny_scene


@pytest.mark.parametrize("length", [1.0, 3.0, 7.5, 12.0])
@pytest.mark.parametrize("angle", [0.0, 0.7, math.pi / 2])
def test_blur_kernel_is_a_normalised_line(length: float, angle: float) -> None:
    k = motion_blur_kernel(length, angle)
    assert k.shape[0] == k.shape[1] and k.shape[0] % 2 == 1 and k.shape[0] >= int(length)
    assert abs(float(k.sum()) - 1.0) < 1e-6 and (k >= 0).all()
    # a line through the centre: point-symmetric
    np.testing.assert_allclose(k, k[::-1, ::-1], atol=1e-6)
    with pytest.raises(ValueError, match="length_px"):
        motion_blur_kernel(float("nan"), 0.0)


def test_sensor_effects_keep_range_and_shape_and_are_seeded() -> None:
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.random((4, 3, 24, 32), dtype=np.float32))
    a = sensor_effects(x, np.random.default_rng(5), 1.0)
    b = sensor_effects(x, np.random.default_rng(5), 1.0)
    assert a.shape == x.shape and a.dtype == x.dtype
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    assert torch.equal(a, b)  # a pure function of the generator's state
    changed = [not torch.equal(sensor_effects(x, np.random.default_rng(s), 1.0), x) for s in range(8)]
    assert sum(changed) >= 6  # each effect is drawn with probability 1/2: all three skipped 1 in 8
    with pytest.raises(ValueError, match="shape"):
        sensor_effects(x[0], rng, 1.0)
    with pytest.raises(ValueError, match="strength"):
        sensor_effects(x, rng, -1.0)


def test_sensor_blur_smooths_and_keeps_the_mean() -> None:
    x = torch.from_numpy(np.random.default_rng(2).random((1, 3, 32, 32), dtype=np.float32))

    def variation(img: torch.Tensor) -> float:
        rows = (img[..., 1:, :] - img[..., :-1, :]).abs().sum()
        return float(rows + (img[..., 1:] - img[..., :-1]).abs().sum())

    blurred = 0
    for seed in range(64):  # the draws that blur and do nothing else
        blur, noise, jpeg = np.random.default_rng(seed).random(3) < 0.5
        if blur and not noise and not jpeg:
            y = sensor_effects(x, np.random.default_rng(seed), 2.0)
            assert variation(y) < 0.9 * variation(x)
            assert float(y.mean()) == pytest.approx(float(x.mean()), rel=0.02)
            blurred += 1
    assert blurred >= 4


def test_perturbed_poses_stay_rigid_with_the_drawn_error_size() -> None:
    base = torch.eye(4, dtype=torch.float64).repeat(4000, 1, 1)
    base[:, :3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    out = perturb_poses(base, np.random.default_rng(0), 0.02, 1.0)
    R = out[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R.transpose(1, 2) @ R, eye, atol=1e-9, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(4000, dtype=torch.float64), atol=1e-9, rtol=0)
    assert torch.equal(out[:, 3], base[:, 3])
    shift = (out[:, :3, 3] - base[:, :3, 3]).numpy()
    assert np.std(shift, axis=0) == pytest.approx([0.02] * 3, rel=0.08)
    angle = np.degrees(np.arccos(np.clip((np.trace(R.numpy(), axis1=1, axis2=2) - 1) / 2, -1, 1)))
    # the norm of a 3-d normal vector of std 1 degree per axis: mean sqrt(8/pi) = 1.596 degrees
    assert float(np.mean(angle)) == pytest.approx(math.sqrt(8 / math.pi), rel=0.05)
    assert torch.equal(perturb_poses(base, np.random.default_rng(0), 0.0, 0.0), base)
    with pytest.raises(ValueError, match="shape"):
        perturb_poses(base[0], np.random.default_rng(0), 0.01, 0.5)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("data") / "train" / "tiny_s0")


def test_sampler_degrades_sources_only_and_leaves_other_draws_unchanged(scene_dir: Path) -> None:
    s = load_scene(scene_dir)
    cfg = tiny_model_config()
    clean = RaySampler([s], cfg, rays_per_view=32, seed=3)
    noisy = RaySampler([s], cfg, rays_per_view=32, seed=3, sensor_prob=1.0, pose_noise_prob=1.0,
                       pose_noise_m=0.05, pose_noise_deg=2.0)
    off = RaySampler([s], cfg, rays_per_view=32, seed=3, sensor_prob=0.0, pose_noise_prob=0.0)
    for step in range(4):
        a, b, c = clean.sample(step, 0), noisy.sample(step, 0), off.sample(step, 0)
        # the target rays, their supervision and the sources chosen are those of the clean sampler
        assert torch.equal(a.origins, b.origins) and torch.equal(a.directions, b.directions)
        assert torch.equal(a.target_rgb, b.target_rgb) and a.target == b.target
        assert np.array_equal(a.sources.indices, b.sources.indices)
        assert torch.equal(a.sources.world_from_cam, c.sources.world_from_cam)
        assert torch.equal(a.sources.rgb, c.sources.rgb)
        again = noisy.sample(step, 0)
        assert torch.equal(b.sources.world_from_cam, again.sources.world_from_cam)
        assert torch.equal(b.sources.rgb, again.sources.rgb)
    moved = [not torch.equal(clean.sample(k, 0).sources.world_from_cam,
                             noisy.sample(k, 0).sources.world_from_cam) for k in range(4)]
    assert all(moved)
    with pytest.raises(ValueError, match="sensor_prob"):
        RaySampler([s], cfg, rays_per_view=8, sensor_prob=1.5)
    with pytest.raises(ValueError, match="pose_noise_m"):
        RaySampler([s], cfg, rays_per_view=8, pose_noise_m=-0.1)


def test_ov_noise_adds_bounded_noise_and_copies_whole_regions() -> None:
    rng = np.random.default_rng(0)
    ov = torch.from_numpy(rng.standard_normal((6, 16, 12, 16)).astype(np.float32))
    out = ov_noise(ov, np.random.default_rng(1), 1.0)
    assert out.shape == ov.shape and out.dtype == ov.dtype and not torch.equal(out, ov)
    assert torch.equal(ov_noise(ov, np.random.default_rng(1), 1.0), out)  # seeded
    scale = float(ov.norm(dim=1).mean())
    diff = out - ov
    for i in range(ov.shape[0]):  # away from confused regions the noise is at most 0.5 x the cell norm
        small = diff[i].abs() < 5.0 * 0.5 * scale / 4.0  # (D, h, w): within 5 sigma of the largest std
        assert float(small.float().mean()) > 0.5
    noise_only = ov_noise(torch.zeros(2, 4, 5, 5), np.random.default_rng(2), 1.0)
    assert torch.equal(noise_only, torch.zeros(2, 4, 5, 5))  # zero maps: zero norm, zero noise
    # confusion copies cells of the same map: with noise scaled to nothing the result is a re-arrangement
    flat = torch.arange(2 * 3 * 10 * 10, dtype=torch.float32).reshape(2, 3, 10, 10)
    for seed in range(8):
        got = ov_noise(flat * 1e6, np.random.default_rng(seed), 1e-9)
        for i in range(2):
            cells = {tuple(c) for c in (flat[i] * 1e6).reshape(3, -1).T.tolist()}
            assert all(tuple(np.round(c, -3)) in {tuple(np.round(x, -3)) for x in cells}
                       for c in got[i].reshape(3, -1).T.tolist())
    with pytest.raises(ValueError, match="ov"):
        ov_noise(ov[0], rng, 1.0)
    with pytest.raises(ValueError, match="strength"):
        ov_noise(ov, rng, 5.0)


def test_sampler_ov_noise_touches_only_the_sources_ov(scene_dir: Path) -> None:
    s = load_scene(scene_dir)
    cfg = tiny_model_config()
    clean = RaySampler([s], cfg, rays_per_view=32, seed=3)
    noisy = RaySampler([s], cfg, rays_per_view=32, seed=3, ov_noise_prob=1.0)
    changed = 0
    for step in range(4):
        a, b = clean.sample(step, 0), noisy.sample(step, 0)
        assert torch.equal(a.target_ov, b.target_ov) and torch.equal(a.target_rgb, b.target_rgb)
        assert torch.equal(a.sources.rgb, b.sources.rgb)
        assert np.array_equal(a.sources.indices, b.sources.indices)
        changed += not torch.equal(a.sources.ov, b.sources.ov)
        assert torch.equal(b.sources.ov, noisy.sample(step, 0).sources.ov)
    assert changed == 4
    with pytest.raises(ValueError, match="ov_noise_prob"):
        RaySampler([s], cfg, rays_per_view=8, ov_noise_prob=2.0)


def test_sampler_world_scale_scales_every_length_and_nothing_else(scene_dir: Path) -> None:
    """``world_scale_prob``: the example's camera centres, depths, rays' origins and surface distances
    scaled by one factor in [1 / max, max], the volume bounds made in that world; the images, OV
    maps and ray directions as they were."""
    from mapper.training.data import source_bounds

    s = load_scene(scene_dir)
    cfg = tiny_model_config()
    plain = RaySampler([s], cfg, rays_per_view=32, seed=5)
    scaled = RaySampler([s], cfg, rays_per_view=32, seed=5, world_scale_prob=1.0, world_scale_max=2.0)
    factors = []
    for step in range(6):
        a, b = plain.sample(step, 0), scaled.sample(step, 0)
        for name in ("target_ov", "target_rgb", "directions"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.equal(a.sources.rgb, b.sources.rgb) and torch.equal(a.sources.ov, b.sources.ov)
        ta, tb = a.sources.world_from_cam[:, :3, 3], b.sources.world_from_cam[:, :3, 3]
        f = float(tb.norm() / ta.norm())
        assert 0.5 - 1e-6 <= f <= 2.0 + 1e-6
        torch.testing.assert_close(tb, ta * f, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(b.sources.world_from_cam[:, :3, :3], a.sources.world_from_cam[:, :3, :3])
        torch.testing.assert_close(b.sources.depth_m, a.sources.depth_m * f, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(b.origins, a.origins * f, rtol=1e-5, atol=1e-6)
        assert a.target_t is not None and b.target_t is not None
        torch.testing.assert_close(b.target_t, a.target_t * f, rtol=1e-5, atol=1e-6)
        # the bounds of the depth points or of the frusta (4 m, as the sampler's default), in the scaled world
        want = [source_bounds(s, b.sources.indices, cfg, frustum_range_m=r, world_scale=f)
                for r in (None, 4.0)]
        assert b.sources.bounds in want
        factors.append(f)
    assert max(factors) / min(factors) > 1.1  # drawn per example
    assert torch.equal(plain.sample(0, 0).origins, RaySampler([s], cfg, rays_per_view=32, seed=5,
                                                              world_scale_prob=0.0).sample(0, 0).origins)
    with pytest.raises(ValueError, match="world_scale"):
        RaySampler([s], cfg, rays_per_view=8, world_scale_prob=0.5, world_scale_max=0.5)
