"""Tests for mapper.model.ops.cost_volume: incremental vs batch, visibility counting, bounds, sampling."""

from __future__ import annotations

import math

import pytest
import torch

from mapper.model.ops.cost_volume import (
    CostVolume,
    VolumeBounds,
    bounds_from_points,
    build_cost_volume,
    cost_volume_features,
    sample_volume,
    voxel_view_samples,
)

BOUNDS = VolumeBounds((-2.0, -2.0, -0.5), 0.25, (16, 16, 4))
IMAGE_WH = (16, 12)
K = torch.tensor([12.0, 12.0, 8.0, 6.0])


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """world_from_cam (4, 4) for an OpenCV camera at eye looking at target (world +z up)."""
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0])), dim=0)
    down = torch.linalg.cross(forward, right)
    pose = torch.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def random_views(n: int, seed: int, channels: int = 3) -> list[tuple[torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(seed)
    views = []
    for _ in range(n):
        angle = float(torch.rand(1, generator=g)) * 2 * math.pi
        eye = torch.tensor([2.5 * math.cos(angle), 2.5 * math.sin(angle), float(torch.rand(1, generator=g))])
        target = torch.randn(3, generator=g) * 0.3
        features = torch.randn(channels, 3, 4, generator=g)  # stride-4 map of a 16x12 image
        views.append((features, look_at(eye, target)))
    return views


def test_incremental_matches_batch_after_1000_random_add_remove_steps() -> None:
    views = random_views(12, seed=0)
    volume = CostVolume(BOUNDS, feature_dim=3)
    present: list[int] = []
    g = torch.Generator().manual_seed(1)
    for _ in range(1000):
        absent = [i for i in range(len(views)) if i not in present]
        add = absent and (not present or float(torch.rand(1, generator=g)) < 0.5)
        if add:
            i = absent[int(torch.randint(len(absent), (1,), generator=g))]
            volume.add_view(i, views[i][0], K, views[i][1], IMAGE_WH)
            present.append(i)
        else:
            i = present.pop(int(torch.randint(len(present), (1,), generator=g)))
            volume.remove_view(i)
    assert sorted(volume.view_ids) == sorted(present) and len(present) > 1
    feats = torch.stack([views[i][0] for i in present])
    poses = torch.stack([views[i][1] for i in present])
    mean, var, count = build_cost_volume(BOUNDS, feats, K.expand(len(present), 4), poses, IMAGE_WH)
    inc_mean, inc_var, inc_count = volume.statistics()
    assert torch.equal(inc_count, count)
    assert count.max() > 1 and (count == 0).any()  # the test exercises overlap and unseen voxels
    torch.testing.assert_close(inc_mean, mean, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(inc_var, var, rtol=1e-5, atol=1e-5)


def test_views_that_do_not_see_a_voxel_do_not_count() -> None:
    volume = CostVolume(BOUNDS, feature_dim=1)
    front = look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3))
    away = look_at(torch.tensor([0.0, -3.0, 0.0]), torch.tensor([0.0, -6.0, 0.0]))  # looks away
    volume.add_view("front", torch.full((1, 3, 4), 2.0), K, front, IMAGE_WH)
    touched = volume.add_view("away", torch.full((1, 3, 4), -5.0), K, away, IMAGE_WH)
    assert touched == 0
    mean, var, count = volume.statistics()
    seen = count > 0
    assert seen.any() and count.max() == 1
    torch.testing.assert_close(mean[0][seen], torch.full_like(mean[0][seen], 2.0))
    assert torch.all(var[0][seen].abs() < 1e-6)


def test_two_views_variance_is_population_variance() -> None:
    volume = CostVolume(BOUNDS, feature_dim=1)
    pose = look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3))
    volume.add_view(1, torch.full((1, 3, 4), 1.0), K, pose, IMAGE_WH)
    volume.add_view(2, torch.full((1, 3, 4), 3.0), K, pose, IMAGE_WH)
    mean, var, count = volume.statistics()
    seen = count > 0
    assert torch.all(count[seen] == 2)
    torch.testing.assert_close(mean[0][seen], torch.full_like(mean[0][seen], 2.0))
    torch.testing.assert_close(var[0][seen], torch.full_like(var[0][seen], 1.0))
    stacked = volume.as_tensor()
    assert stacked.shape == (3, *BOUNDS.dims)
    net = volume.network_input()
    assert net.shape == (3, *BOUNDS.dims)
    assert torch.all(net[1][~seen] == 0) and torch.allclose(net[1][seen], torch.exp(torch.tensor(-1.0)))
    assert torch.all(net[2][~seen] == 0) and torch.allclose(net[2][seen], torch.tensor(2 / 3))


def test_remove_everything_returns_to_exact_zero_and_rebuild_moves_bounds() -> None:
    views = random_views(4, seed=3)
    volume = CostVolume(BOUNDS, feature_dim=3)
    for i, (f, p) in enumerate(views):
        volume.add_view(i, f, K, p, IMAGE_WH)
    before = volume.as_tensor()
    new_bounds = VolumeBounds((-1.5, -1.5, -0.5), 0.5, (4, 4, 4))
    volume.rebuild(new_bounds)
    assert volume.as_tensor().shape == (7, 4, 4, 4) and volume.as_tensor()[-1].max() > 0
    volume.rebuild(BOUNDS)
    torch.testing.assert_close(volume.as_tensor(), before)
    for i in range(4):
        volume.remove_view(i)
    assert torch.count_nonzero(volume.as_tensor()) == 0


def test_bad_input_is_rejected_and_changes_nothing() -> None:
    volume = CostVolume(BOUNDS, feature_dim=2)
    pose = look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3))
    volume.add_view("a", torch.ones(2, 3, 4), K, pose, IMAGE_WH)
    snapshot = volume.as_tensor().clone()
    with pytest.raises(ValueError, match="already in the cost volume"):
        volume.add_view("a", torch.ones(2, 3, 4), K, pose, IMAGE_WH)
    with pytest.raises(ValueError, match=r"features must have shape \(2, h, w\)"):
        volume.add_view("b", torch.ones(3, 3, 4), K, pose, IMAGE_WH)
    with pytest.raises(ValueError, match="image_wh"):
        volume.add_view("b", torch.ones(2, 3, 4), K, pose, (0, 12))
    with pytest.raises(KeyError, match="not in the cost volume"):
        volume.remove_view("zzz")
    assert torch.equal(volume.as_tensor(), snapshot) and volume.view_ids == ["a"]
    with pytest.raises(ValueError, match="voxel_size_m"):
        VolumeBounds((0.0, 0.0, 0.0), 0.0, (2, 2, 2))


def test_batch_build_is_differentiable_wrt_features() -> None:
    views = random_views(3, seed=5, channels=2)
    feats = torch.stack([v[0] for v in views]).double().requires_grad_()
    poses = torch.stack([v[1] for v in views]).double()
    mean, var, count = build_cost_volume(BOUNDS, feats, K.double().expand(3, 4), poses, IMAGE_WH)
    net = cost_volume_features(mean, var, count)
    net.sum().backward()
    assert feats.grad is not None and torch.isfinite(feats.grad).all() and feats.grad.abs().sum() > 0


def test_voxel_view_samples_only_visible_voxels() -> None:
    pose = look_at(torch.tensor([0.0, -3.0, 0.0]), torch.zeros(3))
    narrow = torch.tensor([40.0, 40.0, 8.0, 6.0])
    indices, values = voxel_view_samples(BOUNDS, torch.ones(2, 3, 4), narrow, pose, IMAGE_WH)
    assert values.shape == (indices.numel(), 2) and 0 < indices.numel() < BOUNDS.num_voxels


def test_bounds_from_points_covers_points_and_respects_budget() -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(5000, 3, generator=g) * torch.tensor([6.0, 4.0, 2.5]) + torch.tensor([10.0, -3.0, 0.0])
    pts = torch.cat([pts, torch.tensor([[1e4, 0.0, 0.0], [float("nan"), 0.0, 0.0]])])  # strays
    bounds = bounds_from_points(pts, max_voxels=40 * 40 * 16)
    assert bounds.num_voxels <= 40 * 40 * 16
    assert all(d % 4 == 0 for d in bounds.dims)
    lo, hi = torch.tensor(bounds.origin_m), torch.tensor(bounds.max_corner_m)
    inner = torch.quantile(pts[:5000], torch.tensor([0.01, 0.99]), dim=0)
    assert torch.all(lo <= inner[0]) and torch.all(hi >= inner[1])
    assert hi[0] < 100  # the stray point did not blow the box up
    # The origin is snapped to the voxel grid, so slightly more points keep the same grid.
    more = bounds_from_points(torch.cat([pts, pts[:10] + 0.01]), max_voxels=40 * 40 * 16)
    assert more.voxel_size_m == bounds.voxel_size_m
    fixed = bounds_from_points(pts, voxel_size_m=0.16)
    assert fixed.voxel_size_m == 0.16
    with pytest.raises(ValueError, match="at least one finite point"):
        bounds_from_points(torch.full((3, 3), float("nan")))


def test_sample_volume_at_centres_faces_and_outside() -> None:
    bounds = VolumeBounds((0.0, 0.0, 0.0), 1.0, (2, 3, 4))
    x, y, z = torch.meshgrid(torch.arange(2.0), torch.arange(3.0), torch.arange(4.0), indexing="ij")
    volume = torch.stack([x + 10 * y + 100 * z, torch.ones_like(x)]).double()  # (2, X, Y, Z)
    centres = bounds.voxel_centers(torch.float64)
    values, inside = sample_volume(volume, bounds, centres)
    torch.testing.assert_close(values, volume.reshape(2, -1).T)  # axes not swapped
    assert inside.all()
    # Points on the faces and corners are inside and replicate the face value.
    face_pts = torch.tensor([[0.0, 0.5, 0.5], [2.0, 3.0, 4.0], [1.0, 1.5, 0.0]], dtype=torch.float64)
    vals, inside = sample_volume(volume, bounds, face_pts)
    assert inside.all()
    assert vals[:, 0].tolist() == [0.0, 1 + 20 + 300, 0.5 + 10]
    # Outside: zero and flagged.
    vals, inside = sample_volume(volume, bounds, torch.tensor([[-0.01, 1.0, 1.0], [5.0, 5.0, 50.0]]).double())
    assert not inside.any() and torch.count_nonzero(vals) == 0
