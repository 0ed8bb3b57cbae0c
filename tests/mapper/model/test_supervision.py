"""Geometry and visibility supervision from depth (mapper.model.supervision): exact small cases."""

from __future__ import annotations

import math

import pytest
import torch

from mapper.checks import ShapeError
from mapper.model.ops.geometry import pixel_rays
from mapper.model.supervision import (
    ray_depth_loss,
    ray_distance,
    surface_loss,
    surface_points,
    visibility_loss,
    visibility_targets,
)

W, H = 16, 12
K1 = torch.tensor([[10.0, 10.0, 8.0, 6.0]], dtype=torch.float64)


def pose_at(x: float, y: float, z: float) -> torch.Tensor:
    """Camera at (x, y, z) looking along world +z (optical frame = world axes)."""
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([x, y, z], dtype=torch.float64)
    return pose


def test_ray_distance_puts_surface_points_on_the_plane() -> None:
    pose = pose_at(0.3, -0.2, 0.0)
    origins, dirs = pixel_rays(K1[0], pose, W, H)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    z = torch.full((W * H,), 2.0, dtype=torch.float64)
    z[0] = 0.0  # no depth at one pixel
    t = ray_distance(z, dirs, pose[:3, 2])
    assert t[0] == 0
    pts = surface_points(origins[1:], dirs[1:], t[1:])
    torch.testing.assert_close(pts[:, 2], torch.full_like(pts[:, 2], 2.0))
    assert bool((t[1:] >= 2.0 - 1e-12).all())


def test_ray_depth_loss_is_relative_and_skips_rays_without_target() -> None:
    pred = torch.tensor([1.1, 4.0, 9.0])
    target = torch.tensor([1.0, 5.0, 0.0])
    assert float(ray_depth_loss(pred, target)) == pytest.approx((0.1 + 0.2) / 2, rel=1e-5)
    assert float(ray_depth_loss(pred[2:], target[2:])) == 0.0  # nothing to supervise


def test_surface_loss_bounds_and_band() -> None:
    t = torch.linspace(0.2, 6.0, 30).expand(3, 30).contiguous()
    target = torch.tensor([3.0, 3.0, 0.0])
    at_surface = torch.zeros(3, 30)
    at_surface[:, (t[0] - 3.0).abs().argmin()] = 1.0
    assert float(surface_loss(at_surface, t, target)) == pytest.approx(0.0, abs=1e-6)
    in_front = torch.zeros(3, 30)
    in_front[:, 0] = 1.0
    assert float(surface_loss(in_front, t, target)) == pytest.approx(2.0)
    behind = torch.zeros(3, 30)
    behind[:, -1] = 1.0  # behind the surface: not free space, but not at the surface either
    assert float(surface_loss(behind, t, target)) == pytest.approx(1.0)
    for _ in range(5):
        w = torch.rand(3, 30)
        w = w / w.sum(-1, keepdim=True) * torch.rand(3, 1)
        assert 0.0 <= float(surface_loss(w, t, target)) <= 2.0
    with pytest.raises(ValueError, match="band_m"):
        surface_loss(w, t, target, band_m=0.0)
    with pytest.raises(ShapeError, match="target_t"):
        surface_loss(w, t, target[:2])


def test_surface_loss_gradient_moves_weight_from_free_space_to_the_surface() -> None:
    t = torch.linspace(0.2, 6.0, 30).unsqueeze(0)
    logits = torch.zeros(1, 30, requires_grad=True)
    w = torch.softmax(logits, -1)
    surface_loss(w, t, torch.tensor([3.0])).backward()
    assert logits.grad is not None
    near = (t[0] - 3.0).abs() <= 0.2
    in_front = t[0] < 3.0 - 0.2
    assert bool((logits.grad[0, near] < 0).all()) and bool((logits.grad[0, in_front] > 0).all())


def test_visibility_targets_visible_occluded_unknown() -> None:
    # View 0 sees a wall at z = 2; view 1 (at x = 0.5) has no depth anywhere.
    K = K1.expand(2, 4)
    poses = torch.stack([pose_at(0, 0, 0), pose_at(0.5, 0, 0)])
    wall = torch.full((H, W), 2.0, dtype=torch.float64)
    depth = torch.stack([wall, torch.zeros_like(wall)])
    points = torch.tensor(
        [[0.0, 0.0, 2.0],   # on the wall: visible from view 0
         [0.0, 0.0, 3.0],   # behind the wall: occluded in view 0
         [0.0, 0.0, 1.0],   # in front of the wall: view 0 would see the wall behind it: not visible
         [50.0, 0.0, 2.0],  # outside every image
         [0.0, 0.0, -1.0]], # behind the cameras
        dtype=torch.float64,
    )  # fmt: skip
    visible, known = visibility_targets(points, K, poses, depth, (W, H))
    assert visible[:, 0].tolist() == [True, False, False, False, False]
    assert known[:, 0].tolist() == [True, True, True, False, False]
    assert not bool(known[:, 1].any()) and not bool(visible[:, 1].any())


def test_visibility_targets_tolerance_scales_with_depth() -> None:
    depth = torch.full((1, H, W), 10.0, dtype=torch.float64)
    pts = torch.tensor([[0.0, 0.0, 10.4], [0.0, 0.0, 10.7]], dtype=torch.float64)
    pose = pose_at(0, 0, 0)[None]
    visible, _ = visibility_targets(pts, K1, pose, depth, (W, H), rel_tol=0.05, abs_tol_m=0.05)
    assert visible[:, 0].tolist() == [True, False]


def test_visibility_loss() -> None:
    visible = torch.tensor([[True, False, False], [True, True, False], [False, False, False]])
    known = torch.tensor([[True, True, False], [True, True, True], [True, True, True]])
    on_visible = torch.tensor([[1.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.3, 0.3, 0.4]])
    assert float(visibility_loss(on_visible, visible, known)) == pytest.approx(0.0, abs=1e-6)
    half = torch.tensor([[0.5, 0.5, 0.0], [0.25, 0.25, 0.5], [0.3, 0.3, 0.4]])
    # rows 0 and 1 count (a visible and an occluded view each); row 2 sees nothing
    assert float(visibility_loss(half, visible, known)) == pytest.approx(math.log(2.0), rel=1e-5)
    nothing_mixed = torch.tensor([[True, False, False]]), torch.tensor([[True, False, False]])
    assert float(visibility_loss(torch.tensor([[1.0, 0.0, 0.0]]), *nothing_mixed)) == 0.0
    logits = torch.zeros(2, 3, requires_grad=True)
    visibility_loss(torch.softmax(logits, -1), visible[:2], known[:2]).backward()
    assert logits.grad is not None and float(logits.grad[0, 0]) < 0 < float(logits.grad[0, 1])
