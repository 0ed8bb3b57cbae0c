"""The compiled kernels of DGM against a request's own points (mapper.model.ops.occlusion_kernel)
against their numpy / torch references: z-buffers equal ``splat_points``' depths, the depth-test
matrix equals in-view x the DGM test of ``GovNeSF.sample_views``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from clients.harness import look_at
from mapper.geometry.splat import MAX_REACH_PX, occluder_depths, splat_points
from mapper.kernels.average_kernel import in_view_matrix
from mapper.model.ops.geometry import in_view, invert_pose, project_points
from mapper.model.ops.occlusion_kernel import depth_test_matrix, zbuffer_views
from mapper.runtime.views import depth_agrees

W, H = 40, 30


def _scene(seed: int, n: int = 3000, views: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-2, -2, 0], [2, 2, 2], (n, 3))
    poses = np.stack([look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3))
                      for a in rng.uniform(0, 2 * np.pi, views)])
    poses[0] = look_at(np.array([0.5, 0.2, 1.0]), np.array([3.0, 0.0, 1.0]))  # in the cloud: some behind
    K = np.tile([30.0, 30.0, W / 2, H / 2], (views, 1)) * rng.uniform(0.8, 1.2, (views, 1))
    return pts, K, poses


@pytest.mark.parametrize("footprint", [0.0, 0.05, 0.3])
@pytest.mark.parametrize("seed", [0, 1])
def test_zbuffers_equal_the_splats_depth(footprint: float, seed: int) -> None:
    pts, K, poses = _scene(seed)
    pts[:3] = np.nan  # non-finite rows are ignored, as splat_points ignores them
    z = zbuffer_views(pts, np.linalg.inv(poses), K, W, H, footprint, MAX_REACH_PX, threads=2)
    assert z.shape == (len(K), H, W) and z.dtype == np.float32
    for m in range(len(K)):
        _, ref = splat_points(pts, K[m], poses[m], W, H, footprint)
        np.testing.assert_allclose(z[m], ref, rtol=1e-6, atol=0)
    assert (z > 0).any() and (z == 0).any()


def test_compiled_occluder_depths_equal_the_reference_at_any_resolution() -> None:
    pts, K, poses = _scene(2, n=20000)
    K_hi = np.array([[525.0, 525.0, 320.0, 240.0]])  # splatted at a third of the size, then upsampled
    for Ks, wh in ((K, (W, H)), (K_hi, (640, 480))):
        p = poses[: len(Ks)]
        fast = occluder_depths(pts, Ks, p, *wh, 0.05, threads=2)
        ref = occluder_depths(pts, Ks, p, *wh, 0.05, compiled=False)
        np.testing.assert_allclose(fast, ref, rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match="footprint_m"):
        occluder_depths(pts, K, poses, W, H, float("nan"))


def _reference_test(pts: np.ndarray, K: np.ndarray, poses: np.ndarray, depth: np.ndarray,
                    ratio: float) -> np.ndarray:
    """In view and the DGM test, in torch float32 as ModelRuntime / GovNeSF.sample_views do it."""
    p = torch.from_numpy(pts).float()
    Kt, cam = torch.from_numpy(K).float(), invert_pose(torch.from_numpy(poses).float())
    uv, z = project_points(p.unsqueeze(0).expand(len(K), -1, -1), Kt, cam)  # (M, P, 2), (M, P)
    vis = in_view(uv, z, W, H)
    col = uv[..., 0].nan_to_num(0.0).floor().clamp(0, W - 1).long()
    row = uv[..., 1].nan_to_num(0.0).floor().clamp(0, H - 1).long()
    measured = torch.from_numpy(depth).reshape(len(K), -1).gather(1, row * W + col)
    has = torch.isfinite(measured) & (measured > 0)
    return (vis & (((z - measured).abs() <= ratio * measured) | ~has)).T.numpy()


def test_the_depth_test_matrix_is_in_view_times_the_dgm_test() -> None:
    pts, K, poses = _scene(3)
    pts = pts.astype(np.float32)
    cam = np.linalg.inv(poses).astype(np.float32)
    rng = np.random.default_rng(4)
    depth = rng.uniform(0.5, 5.0, (len(K), H, W)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0.0  # holes pass
    depth[0, :5] = 1e9  # a far surface masks what lies in front of it
    got = depth_test_matrix(pts, cam, K.astype(np.float32), (W, H), 1e-6, depth, 0.25, threads=2)
    want = _reference_test(pts, K.astype(np.float32), poses.astype(np.float32), depth, 0.25)
    assert got.shape == (len(pts), len(K)) and got.dtype == np.bool_
    assert (got != want).mean() < 1e-3  # float rounding at pixel edges only
    assert got.any() and (~got).any()
    no_depth = depth_test_matrix(pts, cam, K.astype(np.float32), (W, H), 1e-6, np.zeros_like(depth), 0.25,
                                 threads=2)
    np.testing.assert_array_equal(no_depth, in_view_matrix(pts, cam, K.astype(np.float32), (W, H), 1e-6,
                                                           threads=2))


def test_the_runtimes_torch_depth_test_equals_the_kernel() -> None:
    """``mapper.runtime.views.depth_agrees`` (the path off the CPU kernels, e.g. CUDA) and the kernel
    agree."""
    from mapper.model.field import GovNeSF
    from tests.mapper.runtime.test_model_runtime import TINY, make_runtime

    pts, K, poses = _scene(5)
    pts = pts.astype(np.float32)
    rng = np.random.default_rng(6)
    depth = rng.uniform(0.5, 5.0, (len(K), H, W)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0.0
    torch.manual_seed(0)
    runtime = make_runtime(GovNeSF(TINY).eval())
    ratio = runtime._loaded.require_model().cfg.render.depth_mask_ratio
    cam = invert_pose(torch.from_numpy(poses).float())
    Kt = torch.from_numpy(K).float()
    uv, z = project_points(torch.from_numpy(pts).unsqueeze(0).expand(len(K), -1, -1), Kt, cam)
    agrees = depth_agrees(runtime._loaded, uv, z, torch.from_numpy(depth)).T.numpy()
    vis = in_view_matrix(pts, cam.numpy(), K.astype(np.float32), (W, H), 1e-6, threads=2)
    got = depth_test_matrix(pts, cam.numpy(), K.astype(np.float32), (W, H), 1e-6, depth, ratio, threads=2)
    assert ((vis & agrees) != got).mean() < 1e-3
