"""Shared helpers of the learned-model tests (runtime, render service, learned e2e)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapper.model.config import EncoderConfig, FusionConfig, ModelConfig, RenderConfig, VolumeConfig


def tiny_model_config(*, ov_dim: int = 4, max_voxels: int = 1024, n_samples: int = 8) -> ModelConfig:
    """A GovNeSF config small enough for random-init tests on 32x24 frames."""
    return ModelConfig(
        name="tiny",
        encoder=EncoderConfig(base_channels=8, blocks=(1, 1, 1), feature_dim=8),
        volume=VolumeConfig(
            unet_channels=(4, 8, 8), group_norm_groups=4, volume_feature_dim=4, max_voxels=max_voxels
        ),
        fusion=FusionConfig(hidden_dim=16, attention_dim=8, num_heads=2, ov_dim=ov_dim),
        render=RenderConfig(n_samples=n_samples, near_m=0.2, far_m=8.0),
        num_source_views=3,
        image_wh=(32, 24),
    )


def look_at(eye: Sequence[float], target: Sequence[float]) -> np.ndarray:
    """(4, 4) world_from_cam of an OpenCV camera at ``eye`` looking at ``target`` (world +z up)."""
    eye_a = np.asarray(eye, float)
    forward = np.asarray(target, float) - eye_a
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(forward, right), forward, eye_a
    return pose
