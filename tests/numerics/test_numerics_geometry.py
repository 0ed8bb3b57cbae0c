"""Stiff / extreme cases for projection and volume sampling.

Points behind or on a camera's plane; rays parallel to volume faces (trilinear sampling at and
outside the bounds); fp16 / bf16 vs float64; gradcheck in float64; no NaN/Inf forward or backward.
"""

from __future__ import annotations

import pytest
import torch

from mapper.model.ops.cost_volume import VolumeBounds, sample_volume
from mapper.model.ops.geometry import in_view, project_points, sample_bilinear

HALF_DTYPES = [torch.float16, torch.bfloat16]
ALL_DTYPES = [torch.float64, torch.float32, *HALF_DTYPES]
BOUNDS = VolumeBounds((-1.0, -0.5, 0.0), 0.5, (4, 3, 2))  # x in [-1, 1], y in [-0.5, 1], z in [0, 1]


def face_volume(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(2, X, Y, Z) volume: channel 0 a distinct value per voxel, channel 1 constant."""
    x, y, z = torch.meshgrid(torch.arange(4.0), torch.arange(3.0), torch.arange(2.0), indexing="ij")
    return torch.stack([1 + x + 10 * y + 100 * z, torch.full_like(x, 7.0)]).to(dtype)


@pytest.mark.parametrize("dtype", ALL_DTYPES)
def test_points_behind_on_and_near_the_camera_plane(dtype: torch.dtype) -> None:
    depths = [-10.0, -1e-3, 0.0, 1e-9, 1e-6, 1e-3, 1.0]
    pts = torch.tensor([[0.3, -0.2, d] for d in depths] + [[0.0, 0.0, 0.0]], dtype=dtype, requires_grad=True)
    K = torch.tensor([300.0, 300.0, 160.0, 120.0], dtype=dtype)
    uv, z = project_points(pts, K, torch.eye(4, dtype=dtype))
    assert torch.isfinite(uv).all() and torch.isfinite(z).all()
    visible = in_view(uv, z, 320, 240)
    assert not visible[:6].any() and not visible[-1]  # z <= eps or far outside the image
    values, _ = sample_bilinear(torch.rand(3, 24, 32, dtype=torch.float32).to(dtype), uv * 0.1)
    assert torch.isfinite(values).all()
    (uv.double().sum() + values.double().sum()).backward()
    assert pts.grad is not None and not torch.isnan(pts.grad).any()


def test_ray_parallel_to_volume_faces_samples_the_face() -> None:
    volume = face_volume()
    ys = torch.linspace(-0.5, 1.0, 31, dtype=torch.float64)  # along y, from face to face
    for x_face, z_face, i, k in [(-1.0, 0.25, 0, 0), (1.0, 0.75, 3, 1)]:
        pts = torch.stack([torch.full_like(ys, x_face), ys, torch.full_like(ys, z_face)], dim=-1)
        values, inside = sample_volume(volume, BOUNDS, pts)
        assert inside.all()
        # On the x face the trilinear sample equals the 1D interpolation of that face row along y.
        row = volume[0, i, :, k]  # (Y,)
        cont = ((ys + 0.5) / 0.5 - 0.5).clamp(0, 2)
        lo = cont.floor().long().clamp(max=1)
        frac = cont - lo
        expected = row[lo] * (1 - frac) + row[lo + 1] * frac
        torch.testing.assert_close(values[:, 0], expected)
        torch.testing.assert_close(values[:, 1], torch.full_like(ys, 7.0))


def test_volume_sampling_outside_and_on_edges_and_corners() -> None:
    volume = face_volume().requires_grad_()
    pts = torch.tensor(
        [
            [-1.0, -0.5, 0.0],  # min corner
            [1.0, 1.0, 1.0],  # max corner
            [1.0, 1.0, 0.5],  # edge
            [1.0 + 1e-9, 0.0, 0.5],  # just outside
            [-1e6, 0.0, 0.5],  # far outside
            [0.0, 0.0, 1e30],  # absurdly far
        ],
        dtype=torch.float64,
        requires_grad=True,
    )
    values, inside = sample_volume(volume, BOUNDS, pts)
    assert inside.tolist() == [True, True, True, False, False, False]
    assert values[0, 0].item() == 1.0 and values[1, 0].item() == 1 + 3 + 20 + 100
    assert torch.count_nonzero(values[3:]) == 0
    values.sum().backward()
    assert torch.isfinite(volume.grad).all() and torch.isfinite(pts.grad).all()
    assert pts.grad[3:].abs().sum() == 0  # outside points get no gradient


@pytest.mark.parametrize("dtype,atol", [(torch.float32, 1e-5), (torch.float16, 0.5), (torch.bfloat16, 4.0)])
def test_volume_sampling_low_precision_vs_float64(dtype: torch.dtype, atol: float) -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(64, 3, generator=g, dtype=torch.float64) * torch.tensor([2.4, 1.8, 1.2]) - torch.tensor(
        [1.2, 0.65, 0.1]
    )
    ref, ref_inside = sample_volume(face_volume(), BOUNDS, pts)
    out, inside = sample_volume(face_volume(dtype), BOUNDS, pts.to(dtype))
    assert out.dtype == dtype and torch.isfinite(out).all()
    agree = inside == ref_inside  # points within a rounding error of a face may flip
    assert agree.float().mean() > 0.9
    torch.testing.assert_close(out[agree].double(), ref[agree], atol=atol, rtol=0.02)


def test_gradcheck_volume_sampling_and_projection_float64() -> None:
    g = torch.Generator().manual_seed(1)
    volume = torch.rand(2, 4, 3, 2, generator=g, dtype=torch.float64, requires_grad=True)
    # Interior points away from voxel-centre planes (trilinear kinks) and from the faces.
    pts = torch.tensor([[-0.6, 0.1, 0.4], [0.3, 0.6, 0.6], [0.55, -0.1, 0.45]], dtype=torch.float64)
    pts.requires_grad_()
    assert torch.autograd.gradcheck(lambda v, p: sample_volume(v, BOUNDS, p)[0], (volume, pts))
    K = torch.tensor([300.0, 280.0, 160.0, 120.0], dtype=torch.float64, requires_grad=True)
    world = torch.tensor([[0.1, 0.2, 2.0], [-0.5, 0.3, 1e-3], [3.0, -2.0, 7.0]], dtype=torch.float64)
    world.requires_grad_()
    assert torch.autograd.gradcheck(
        lambda p, k: project_points(p, k, torch.eye(4, dtype=torch.float64))[0], (world, K)
    )
