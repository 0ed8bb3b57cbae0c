"""mapper.training.data: scenes from recordings, source selection, deterministic ray batches.

``write_tiny_scene`` (also used by test_train.py) writes a small synthetic recording: cameras
side by side looking at a textured wall 3 m away, with depth, 8-d OV maps and novel views.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.model.config import EncoderConfig, FusionConfig, ModelConfig, RenderConfig, VolumeConfig
from mapper.model.ops.cost_volume import VolumeBounds
from mapper.training.data import (
    RaySampler,
    find_scenes,
    load_scene,
    select_sources,
    source_batch,
    validation_views,
)
from protocol.messages import Frame
from protocol.recording import RecordingWriter

W, H, OV_DIM, WALL_Y_M = 64, 48, 8, 3.0
K_TINY = np.array([40.0, 40.0, 32.0, 24.0])
CLASS_NAMES = [f"class{i}" for i in range(24)]


def tiny_model_config() -> ModelConfig:
    """A very small network for tests (64 x 48 images, 8-d OV features)."""
    return ModelConfig(
        name="tiny",
        encoder=EncoderConfig(base_channels=4, blocks=(1, 1, 1), feature_dim=4),
        volume=VolumeConfig(
            unet_channels=(4, 8, 8), group_norm_groups=4, volume_feature_dim=4, max_voxels=8 * 8 * 8
        ),
        fusion=FusionConfig(hidden_dim=8, attention_dim=8, num_heads=2, ov_dim=OV_DIM),
        render=RenderConfig(n_samples=8, near_m=0.2, far_m=5.0),
        num_source_views=3,
        image_wh=(W, H),
    )


def camera_pose(x_m: float, z_m: float = 1.0) -> np.ndarray:
    """(4, 4) world_from_cam of a camera at (x, 0, z) looking along world +y (z up)."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: cam x, y, z
    pose[:3, 3] = [x_m, 0.0, z_m]
    return pose


def _wall_xz(pose: np.ndarray, w: int, h: int, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (x, z) on the wall seen by each pixel centre, (h, w) each."""
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    depth = WALL_Y_M - pose[1, 3]
    x = pose[0, 3] + (u - K[2]) / K[0] * depth
    z = pose[2, 3] - (v - K[3]) / K[1] * depth
    return x, z


def render_wall(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """rgb (H, W, 3) uint8, depth (H, W), ov (H/4, W/4, D) float16, label (H, W) of the wall."""
    x, z = _wall_xz(pose, W, H, K_TINY)
    rgb = np.stack(
        [0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(4 * z), 0.5 + 0.3 * np.sin(2 * (x + z))], -1
    )
    label = (x > 0).astype(np.int32)  # class 0 left of x = 0, class 1 right of it
    xo, _ = _wall_xz(pose, W // 4, H // 4, K_TINY / np.array([4, 4, 4, 4]))
    ov = np.zeros((H // 4, W // 4, OV_DIM), np.float32)
    ov[..., 0] = xo <= 0
    ov[..., 1] = xo > 0
    ov[..., 2] = 0.1
    depth = np.full((H, W), WALL_Y_M - pose[1, 3], np.float32)
    return (rgb * 255).round().astype(np.uint8), depth, ov.astype(np.float16), label


def write_tiny_scene(out: Path, n_frames: int = 6, seed: int = 0) -> Path:
    """A synthetic scene folder in the `govnesf sim record` layout (frames.govrec + gt/)."""
    (out / "gt").mkdir(parents=True)
    rng = np.random.default_rng(seed)
    xs = np.linspace(-1.5, 1.5, n_frames) + rng.uniform(-0.02, 0.02, n_frames)
    with RecordingWriter(out / "frames.govrec", meta={"class_names": CLASS_NAMES}) as rec:
        for i, x in enumerate(xs):
            pose = camera_pose(float(x))
            rgb, depth, ov, _ = render_wall(pose)
            rec.write(
                Frame(
                    seq=i,
                    stamp_ns=i * 100_000_000,
                    width=W,
                    height=H,
                    K=K_TINY,
                    world_from_cam=pose,
                    rgb=rgb,
                    depth_m=depth,
                    ov=ov,
                    ov_space="minilm-l6-v2",
                )
            )
    novel = [camera_pose(float(x), 1.05) for x in (-0.1, 0.15)]
    renders = [render_wall(p) for p in novel]
    np.savez(
        out / "gt" / "novel_views.npz",
        K=np.stack([K_TINY] * len(novel)),
        world_from_cam=np.stack(novel),
        rgb=np.stack([r[0] for r in renders]),
        depth_m=np.stack([r[1] for r in renders]),
        label=np.stack([r[3] for r in renders]),
        instance=np.stack([r[3] for r in renders]),
        stream_index=np.zeros(len(novel), np.int32),
    )
    (out / "gt" / "class_names.json").write_text(json.dumps(CLASS_NAMES))
    return out


def write_text_embeddings(val_dir: Path) -> None:
    """The class text-embedding cache ``govnesf train`` reads (here: class i <-> axis i)."""
    emb = np.zeros((20, OV_DIM), np.float32)
    emb[np.arange(20), np.arange(20) % OV_DIM] = 1.0
    emb[2:] += 0.01 * np.arange(18)[:, None]
    np.savez(val_dir / "text_embeddings_minilm-l6-v2.npz", names=np.array(CLASS_NAMES[:20]), embeddings=emb)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("data") / "train" / "tiny_s0")


def test_load_scene_shapes(scene_dir: Path) -> None:
    assert find_scenes(scene_dir.parent) == [scene_dir]
    s = load_scene(scene_dir, with_novel_views=True)
    assert s.rgb.shape == (6, H, W, 3) and s.rgb.dtype == np.uint8
    assert s.depth_m.shape == (6, H, W)
    assert s.ov.shape == (6, H // 4, W // 4, OV_DIM) and s.ov.dtype == np.float16
    assert s.K.shape == (6, 4) and s.world_from_cam.shape == (6, 4, 4)
    # depth back-projects onto the wall y = 3
    pts = s.points_m.reshape(-1, 3)
    np.testing.assert_allclose(pts[:, 1], WALL_Y_M, atol=1e-4)
    assert s.novel is not None and s.novel.label.shape == (2, H, W)
    assert s.class_names == CLASS_NAMES


def test_find_scenes_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="make_train_data"):
        find_scenes(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="no scenes"):
        find_scenes(tmp_path)


def test_select_sources_nearest_first_and_excludes_target(scene_dir: Path) -> None:
    s = load_scene(scene_dir)
    src = select_sources(s, s.K[2], s.world_from_cam[2], 3, exclude=2)
    assert 2 not in src.tolist() and len(src) == 3
    assert set(src[:2].tolist()) == {1, 3}  # the neighbours see most of frame 2's wall
    with pytest.raises(ValueError, match="num_sources"):
        select_sources(s, s.K[2], s.world_from_cam[2], 0)


def test_ray_sampler_shapes_and_determinism(scene_dir: Path) -> None:
    s = load_scene(scene_dir)
    cfg = tiny_model_config()
    sampler = RaySampler([s], cfg, rays_per_view=50, seed=3)
    a, b, c = sampler.sample(5, 1), sampler.sample(5, 1), sampler.sample(6, 1)
    assert a.origins.shape == (50, 3) and a.directions.shape == (50, 3)
    assert a.target_rgb.shape == (50, 3) and a.target_ov.shape == (50, OV_DIM)
    assert a.sources.rgb.shape == (3, 3, H, W) and a.sources.ov.shape == (3, OV_DIM, H // 4, W // 4)
    assert a.target not in a.sources.indices.tolist()
    torch.testing.assert_close(a.directions.norm(dim=-1), torch.ones(50))
    assert torch.equal(a.directions, b.directions) and a.seed == b.seed  # pure function of (step, item)
    assert not torch.equal(a.directions, c.directions)
    # supervision: the OV target is one-hot class 0 / 1 by the side of the wall the ray hits
    hit = a.origins + a.directions * (WALL_Y_M / a.directions[:, 1:2])
    far_from_edge = (hit[:, 0].abs() > 0.4).numpy()
    expect = (hit[:, 0] > 0).float().numpy()
    np.testing.assert_allclose(a.target_ov[far_from_edge, 1].numpy(), expect[far_from_edge], atol=1e-3)
    # the volume covers the wall the sources see
    bounds: VolumeBounds = a.sources.bounds
    assert bounds.origin_m[1] <= WALL_Y_M <= bounds.max_corner_m[1]
    assert np.prod(bounds.dims) <= cfg.volume.max_voxels


def test_ray_sampler_rejects_mismatched_ov_dim(scene_dir: Path) -> None:
    s = load_scene(scene_dir)
    cfg = tiny_model_config()
    bad = ModelConfig(
        **{**cfg.__dict__, "fusion": FusionConfig(hidden_dim=8, attention_dim=8, num_heads=2, ov_dim=16)}
    )
    with pytest.raises(ValueError, match="ov features"):
        RaySampler([s], bad, rays_per_view=8)
    with pytest.raises(ValueError, match="rays_per_view"):
        RaySampler([s], cfg, rays_per_view=0)


def test_validation_views_pick_overlapping_sources(scene_dir: Path) -> None:
    s = load_scene(scene_dir, with_novel_views=True)
    views = validation_views([s], 3, views_per_scene=1)
    assert len(views) == 1 and len(views[0].source_indices) == 3
    with pytest.raises(ValueError, match="novel views"):
        validation_views([load_scene(scene_dir)], 3)


def test_frustum_bounds_augmentation_covers_the_source_frusta(scene_dir: Path) -> None:
    s = load_scene(scene_dir)
    cfg = tiny_model_config()
    idx = np.array([1, 3])
    depth_b = source_batch(s, idx, cfg).bounds
    frustum_b = source_batch(s, idx, cfg, frustum_range_m=3.0).bounds
    centres = s.world_from_cam[idx, :3, 3]
    far = centres + 3.0 * s.world_from_cam[idx, :3, 2]  # 3 m along each optical axis
    for p in np.concatenate([centres, far]):
        assert np.all(np.asarray(frustum_b.origin_m) - 1e-6 <= p)
        assert np.all(p <= np.asarray(frustum_b.max_corner_m) + 1e-6)
    assert depth_b != frustum_b
    always = RaySampler([s], cfg, rays_per_view=8, frustum_bounds_prob=1.0, frustum_range_m=3.0)
    never = RaySampler([s], cfg, rays_per_view=8)
    a, b = always.sample(0, 0), never.sample(0, 0)
    assert a.sources.bounds != b.sources.bounds
    with pytest.raises(ValueError, match="frustum_bounds_prob"):
        RaySampler([s], cfg, rays_per_view=8, frustum_bounds_prob=1.5)
