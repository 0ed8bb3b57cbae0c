"""Property tests for mapper.model.ops.geometry: poses, projection, pixel convention, sampling."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mapper.model.ops.geometry import (
    camera_centers,
    in_view,
    invert_pose,
    pixel_rays,
    project_points,
    sample_bilinear,
    sample_nearest,
    scale_uv,
    transform_points,
    unproject_points,
)


def random_pose(
    generator: torch.Generator, dtype: torch.dtype = torch.float64, batch: tuple = ()
) -> torch.Tensor:
    """A random rigid transform (..., 4, 4) from a QR-orthogonalised matrix."""
    a = torch.randn(*batch, 3, 3, generator=generator, dtype=torch.float64)
    q, r = torch.linalg.qr(a)
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    det = torch.det(q)
    q[..., :, 0] = q[..., :, 0] * det.unsqueeze(-1)  # make it a proper rotation
    pose = torch.zeros(*batch, 4, 4, dtype=torch.float64)
    pose[..., :3, :3] = q
    pose[..., :3, 3] = torch.randn(*batch, 3, generator=generator, dtype=torch.float64) * 3
    pose[..., 3, 3] = 1
    return pose.to(dtype)


seeds = st.integers(min_value=0, max_value=2**31 - 1)


@settings(max_examples=25, deadline=None)
@given(seeds)
def test_invert_pose_is_inverse(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    world_from_cam = random_pose(g, batch=(3,))
    eye = torch.eye(4, dtype=torch.float64).expand(3, 4, 4)
    torch.testing.assert_close(world_from_cam @ invert_pose(world_from_cam), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(invert_pose(invert_pose(world_from_cam)), world_from_cam, atol=1e-12, rtol=0)


@settings(max_examples=25, deadline=None)
@given(seeds)
def test_transform_points_matches_homogeneous_product(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    pose = random_pose(g)
    pts = torch.randn(7, 3, generator=g, dtype=torch.float64)
    homog = torch.cat([pts, torch.ones(7, 1, dtype=torch.float64)], dim=1)
    expected = (pose @ homog.T).T[:, :3]
    torch.testing.assert_close(transform_points(pose, pts), expected, atol=1e-12, rtol=0)


@settings(max_examples=25, deadline=None)
@given(seeds)
def test_project_unproject_round_trip(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    world_from_cam = random_pose(g, batch=(2,))
    K = torch.tensor([[120.0, 110.0, 80.0, 60.0], [90.0, 95.0, 40.5, 30.25]], dtype=torch.float64)
    uv = torch.rand(2, 9, 2, generator=g, dtype=torch.float64) * 160
    z = torch.rand(2, 9, generator=g, dtype=torch.float64) * 8 + 0.1
    pts = unproject_points(uv, z, K, world_from_cam)
    uv2, z2 = project_points(pts, K, invert_pose(world_from_cam))
    torch.testing.assert_close(uv2, uv, atol=1e-9, rtol=0)
    torch.testing.assert_close(z2, z, atol=1e-12, rtol=0)


@pytest.mark.parametrize("width,height", [(1, 1), (4, 3), (16, 9)])
def test_ray_through_pixel_centre_projects_to_centre(width: int, height: int) -> None:
    g = torch.Generator().manual_seed(width * 100 + height)
    world_from_cam = random_pose(g)
    K = torch.tensor([20.0, 22.0, width / 2 + 0.3, height / 2 - 0.2], dtype=torch.float64)
    origins, dirs = pixel_rays(K, world_from_cam, width, height)
    assert origins.shape == dirs.shape == (height, width, 3)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(height, width, dtype=torch.float64))
    torch.testing.assert_close(origins[0, 0], camera_centers(world_from_cam))
    points = (origins + 2.5 * dirs).reshape(-1, 3)
    uv, z = project_points(points, K, invert_pose(world_from_cam))
    cols, rows = torch.meshgrid(torch.arange(width), torch.arange(height), indexing="xy")
    expected = torch.stack([cols, rows], dim=-1).reshape(-1, 2).to(torch.float64) + 0.5
    torch.testing.assert_close(uv, expected, atol=1e-9, rtol=0)
    assert bool((z > 0).all())


def test_pixel_rays_batched_matches_single() -> None:
    g = torch.Generator().manual_seed(3)
    poses = random_pose(g, batch=(2,))
    K = torch.tensor([[20.0, 20.0, 3.0, 2.0], [30.0, 25.0, 2.5, 1.5]], dtype=torch.float64)
    origins, dirs = pixel_rays(K, poses, 6, 4)
    assert dirs.shape == (2, 4, 6, 3)
    for i in range(2):
        o1, d1 = pixel_rays(K[i], poses[i], 6, 4)
        torch.testing.assert_close(dirs[i], d1)
        torch.testing.assert_close(origins[i], o1)


def test_points_behind_and_on_camera_plane_are_finite_and_invisible() -> None:
    K = torch.tensor([100.0, 100.0, 32.0, 24.0], dtype=torch.float32)
    cam_from_world = torch.eye(4)
    pts = torch.tensor(
        [[0.1, 0.2, 0.0], [1.0, -1.0, -2.0], [1e-3, 0.0, 1e-9], [5.0, 5.0, -1e-7], [0.0, 0.0, 1.0]],
        requires_grad=True,
    )
    uv, z = project_points(pts, K, cam_from_world)
    assert torch.isfinite(uv).all() and torch.isfinite(z).all()
    visible = in_view(uv, z, 64, 48)
    assert visible.tolist() == [False, False, False, False, True]
    (uv.sum() + z.sum()).backward()
    assert pts.grad is not None and torch.isfinite(pts.grad).all()


def test_in_view_border_and_edges() -> None:
    uv = torch.tensor([[0.0, 0.0], [64.0, 48.0], [5.0, 5.0], [64.01, 10.0], [-0.01, 3.0]])
    z = torch.ones(5)
    assert in_view(uv, z, 64, 48).tolist() == [True, True, True, False, False]
    assert in_view(uv, z, 64, 48, border_px=10).tolist() == [False, False, False, False, False]
    assert in_view(uv, -z, 64, 48).tolist() == [False] * 5


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_projection_float32_matches_float64(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(11)
    world_from_cam = random_pose(g)
    pts = torch.randn(50, 3, generator=g, dtype=torch.float64) + camera_centers(world_from_cam)
    pts = pts + 4 * world_from_cam[:3, 2]  # in front of the camera
    K = torch.tensor([300.0, 300.0, 160.0, 120.0], dtype=torch.float64)
    uv64, z64 = project_points(pts, K, invert_pose(world_from_cam))
    uv, z = project_points(pts.to(dtype), K.to(dtype), invert_pose(world_from_cam.to(dtype)))
    assert uv.dtype == dtype
    tol = 1e-3 if dtype == torch.float32 else 1e-10
    mask = z64 > 0.5
    torch.testing.assert_close(uv[mask].double(), uv64[mask], atol=tol, rtol=0)


def test_sample_bilinear_pixel_centres_and_edges() -> None:
    image = torch.arange(12, dtype=torch.float64).reshape(1, 3, 4)  # C=1, H=3, W=4
    centres = torch.tensor([[0.5, 0.5], [3.5, 2.5], [1.5, 1.5]], dtype=torch.float64)
    values, inside = sample_bilinear(image, centres)
    assert values.shape == (3, 1)
    assert values[:, 0].tolist() == [0.0, 11.0, 5.0]
    assert inside.all()
    # Halfway between two horizontally adjacent centres.
    mid, _ = sample_bilinear(image, torch.tensor([[1.0, 0.5]], dtype=torch.float64))
    assert mid.item() == pytest.approx(0.5)
    # Between the outer centre and the edge the edge value is replicated; beyond, flagged outside.
    edge, inside = sample_bilinear(image, torch.tensor([[0.0, 0.0], [4.5, 1.0]], dtype=torch.float64))
    assert edge[0].item() == 0.0
    assert inside.tolist() == [True, False]
    assert torch.isfinite(edge).all()


def test_sample_bilinear_is_resolution_independent() -> None:
    # A linear ramp in u sampled at the same physical point at two resolutions gives the same value.
    def ramp(width: int, height: int) -> torch.Tensor:
        u = (torch.arange(width, dtype=torch.float64) + 0.5) / width
        return u.expand(height, width).unsqueeze(0)

    uv_full = torch.tensor([[37.3, 20.0], [100.0, 70.2]], dtype=torch.float64)
    full, _ = sample_bilinear(ramp(160, 120), uv_full)
    quarter, _ = sample_bilinear(ramp(40, 30), scale_uv(uv_full, (160, 120), (40, 30)))
    torch.testing.assert_close(full, uv_full[:, :1] / 160)
    torch.testing.assert_close(quarter, uv_full[:, :1] / 160)


def test_sample_bilinear_batched_broadcast_and_gradients() -> None:
    g = torch.Generator().manual_seed(5)
    image = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)  # (N, C, H, W)
    uv = (torch.rand(2, 7, 2, generator=g, dtype=torch.float64) * torch.tensor([6.0, 5.0])).requires_grad_()
    values, inside = sample_bilinear(image, uv)
    assert values.shape == (2, 7, 3) and inside.shape == (2, 7)
    for n in range(2):
        single, _ = sample_bilinear(image[n], uv[n])
        torch.testing.assert_close(values[n], single)
    # Gradient w.r.t. uv (interior points away from pixel-centre kinks).
    uv_in = torch.tensor([[[1.2, 1.3], [2.7, 3.1]]], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda p: sample_bilinear(image[:1], p)[0], (uv_in,))


def test_sample_nearest_picks_containing_pixel() -> None:
    depth = torch.tensor([[[1.0, 2.0], [3.0, 4.0]]])  # C=1, H=2, W=2
    uv = torch.tensor([[0.1, 0.1], [1.9, 0.2], [0.5, 1.5], [1.99, 1.99], [2.0, 2.0], [-5.0, 0.0]])
    values, inside = sample_nearest(depth, uv)
    assert values[:, 0].tolist() == [1.0, 2.0, 3.0, 4.0, 4.0, 1.0]
    assert inside.tolist() == [True, True, True, True, True, False]


def test_bad_shapes_raise_clear_errors() -> None:
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 4\)"):
        invert_pose(torch.eye(3))
    with pytest.raises(ValueError, match="K must have shape"):
        project_points(torch.zeros(2, 3), torch.zeros(3), torch.eye(4))
    with pytest.raises(ValueError, match="out of range"):
        pixel_rays(torch.ones(4), torch.eye(4), 0, 3)
    with pytest.raises(ValueError, match="uv must have shape"):
        sample_bilinear(torch.zeros(1, 2, 2), torch.zeros(3))


def test_extreme_projection_stays_finite_in_half_precision() -> None:
    for dtype in (torch.float16, torch.bfloat16):
        pts = torch.tensor([[100.0, 0.0, 1e-3], [0.0, 0.0, 0.0], [0.1, 0.1, 2.0]], dtype=dtype)
        K = torch.tensor([300.0, 300.0, 160.0, 120.0], dtype=dtype)
        uv, z = project_points(pts, K, torch.eye(4, dtype=dtype))
        assert torch.isfinite(uv).all(), dtype
        assert in_view(uv, z, 320, 240).tolist() == [False, False, True]
        assert math.isclose(uv[2, 0].item(), 175.0, rel_tol=1e-2)
