"""One ray marcher: the node's renders are the field's renders.

``ModelRuntime`` renders with the model's rendering core (``mapper.model.render.march_rays``),
as ``field.render_rays`` and ``render_depth_maps`` do. These tests render the same rays with the
same source views and volume both ways and compare them with ``assert_close``, as gsplat tests its
fast path against its torch reference:

* dense (no empty-space skipping): node == ``render_rays(clip_to_volume=True)`` on every ray,
  also on rays that miss the volume (both render nothing there);
* depth only: node == the field's depth and opacity == ``render_depth_maps``;
* skipping: node == field on every ray none of whose samples lies in an empty voxel; on the
  others the difference is bounded by the optical depth the skip left out, tau_s (opacity within
  ``1 - exp(-tau_s)``, colour within ``2 tau_s``, see ``_skip_bound``);
* ``min_weight`` pruning: node == ``render_rays(weight_threshold=min_weight)`` on every ray.

All keyframes are source views (``source_views`` >= their number), so the node's per-point view
groups are one group holding every view, the views ``render_rays`` gets. Tiny random-init model.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import Tensor

from mapper.map.window import Keyframe, KeyframeWindow
from mapper.model.field import GovNeSF, RenderOutputs, SourceViews, render_depth_maps, render_rays
from mapper.model.ops.geometry import pixel_rays
from mapper.model.ops.rendering import Rays, clip_to_box
from mapper.model.render import occupancy_mask
from mapper.node.config import WindowConfig
from mapper.runtime.density import occupancy_grid
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from mapper.runtime.prepared import Prepared
from tests.model_helpers import look_at, tiny_model_config

D = 6
TINY = tiny_model_config(ov_dim=D, max_voxels=2048, n_samples=16)
N_KEYFRAMES = 4
CAMERAS = {
    # (K for 20 x 15, world_from_cam): one looking at the scene, one far away whose rays mostly miss
    "inside": ([20.0, 20.0, 10.0, 7.5], look_at((2.0, 0.5, 1.1), (0.0, 0.0, 0.5))),
    "far": ([8.0, 8.0, 10.0, 7.5], look_at((5.0, 3.0, 2.5), (0.0, 0.0, 0.5))),
}
WH = (20, 15)


def keyframe(i: int) -> Keyframe:
    rng = np.random.default_rng(i)
    a = 0.7 * i
    return Keyframe(
        seq=i,
        stamp_ns=i,
        camera="cam0",
        K=np.array([32.0, 32.0, 20.0, 15.0]),
        world_from_cam=look_at((2.0 * np.cos(a), 2.0 * np.sin(a), 1.2), (0.0, 0.0, 0.5)),
        rgb=rng.integers(0, 256, (30, 40, 3), dtype=np.uint8),
        depth_m=np.full((30, 40), 2.0, np.float32),
        ov=rng.standard_normal((5, 6, D)).astype(np.float16),
        ov_space="test-space",
    )


@pytest.fixture(scope="module")
def runtime() -> ModelRuntime:
    torch.manual_seed(0)
    model = GovNeSF(TINY).eval()
    cfg = ModelRuntimeConfig(device="cpu", chunk_rays=128, chunk_points=1000, source_views=8)
    rt = ModelRuntime(cfg, model=model, text_encoder=lambda space: None)  # type: ignore[arg-type,return-value]
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    rt.attach(window)
    for i in range(N_KEYFRAMES):
        window.consider(keyframe(i))
    rt.sync()
    assert len(rt) == N_KEYFRAMES <= rt.source_views
    return rt


def camera_rays(K: list[float], pose: np.ndarray) -> Rays:
    """The node's pixel rays (float64 pixel_rays, then float32, as ``ModelRuntime.render``)."""
    origins, dirs = pixel_rays(torch.tensor(K, dtype=torch.float64), torch.tensor(pose), *WH)
    return Rays(origins.reshape(-1, 3).float(), dirs.reshape(-1, 3).float())


def all_views(prep: Prepared) -> SourceViews:
    assert prep.ov is not None
    return SourceViews(prep.rgb, prep.features, prep.ov, prep.K, prep.world_from_cam)


def field_render(
    rt: ModelRuntime, prep: Prepared, rays: Rays, weight_threshold: float = 0.0
) -> RenderOutputs:
    """``render_rays`` with the node's sampling: its bins, near / far, clipped to the volume."""
    assert rt.model is not None
    return render_rays(
        rt.model, all_views(prep), prep.volume, prep.bounds, rays, n_samples=rt.samples_per_ray,
        near_m=rt.config.near_m, far_m=rt.config.far_m, clip_to_volume=True,
        weight_threshold=weight_threshold,
    )  # fmt: skip


def node_render(
    rt: ModelRuntime, prep: Prepared, rays: Rays, occupancy: Tensor | None = None, appearance: bool = True
) -> tuple[tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor], dict[str, int]]:
    """The node's float outputs for the rays: rgb, ray distance, opacity, ov, covered; and its counts."""
    assert rt.model is not None
    stats = {"samples": 0, "density_evals": 0, "appearance_evals": 0, "view_groups": 0}
    out = rt._renderer.render_rays(
        rt.model, prep, rays.origins, rays.directions, occupancy, True, prep.has_ov, stats, appearance
    )
    return out, stats


@pytest.mark.parametrize("camera", list(CAMERAS))
@torch.no_grad()
def test_dense_node_render_equals_field_render_rays(runtime: ModelRuntime, camera: str) -> None:
    K, pose = CAMERAS[camera]
    prep = runtime._volume.prepare()
    rays = camera_rays(K, pose)
    (rgb, ray_depth, opacity, ov, covered), stats = node_render(runtime, prep, rays)
    ref = field_render(runtime, prep, rays)
    assert ov is not None and stats["view_groups"] == 1  # every keyframe is a source view
    torch.testing.assert_close(rgb, ref.rgb)
    torch.testing.assert_close(ov, ref.ov)
    torch.testing.assert_close(ray_depth, ref.depth_m)
    torch.testing.assert_close(opacity, ref.opacity)
    assert bool((covered <= opacity + 1e-6).all())
    box = (torch.tensor(prep.bounds.origin_m).float(), torch.tensor(prep.bounds.max_corner_m).float())
    _, _, crosses = clip_to_box(
        rays.origins, rays.directions, runtime.config.near_m, runtime.config.far_m, *box
    )
    missed = ~crosses
    if camera == "far":  # rays that miss the volume: the node does not evaluate them, both render 0
        assert int(missed.sum()) > len(rays) // 2 and stats["density_evals"] < stats["samples"]
        assert bool((opacity[missed] == 0).all() & (rgb[missed] == 0).all())
    else:
        assert not missed.any() and stats["density_evals"] == stats["samples"] == len(rays) * 16
    # The public render: its opacity and z-depth are those of the same march.
    frame = runtime.render(K, pose, *WH, ["rgb", "depth"], empty_space_skipping=False)
    assert frame.opacity is not None and frame.depth_m is not None
    torch.testing.assert_close(torch.from_numpy(frame.opacity).reshape(-1), ref.opacity)
    axis = torch.tensor(pose[:3, 2], dtype=torch.float32)
    z = ref.depth_m * (rays.directions @ axis)
    z = torch.where(ref.opacity >= runtime.config.min_opacity, z, torch.zeros_like(z))
    torch.testing.assert_close(torch.from_numpy(frame.depth_m).reshape(-1), z)


@torch.no_grad()
def test_depth_only_node_render_equals_field_depth_and_render_depth_maps(runtime: ModelRuntime) -> None:
    assert runtime.model is not None
    prep = runtime._volume.prepare()
    for K, pose in CAMERAS.values():
        rays = camera_rays(K, pose)
        (rgb, ray_depth, opacity, _, covered), stats = node_render(runtime, prep, rays, appearance=False)
        ref = field_render(runtime, prep, rays)
        assert stats["appearance_evals"] == 0 and not rgb.any() and not covered.any()
        torch.testing.assert_close(ray_depth, ref.depth_m)
        torch.testing.assert_close(opacity, ref.opacity)
        frame = runtime.render(K, pose, *WH, ["depth"], empty_space_skipping=False)
        assert frame.depth_m is not None and frame.opacity is not None
        pose_t = torch.tensor(pose, dtype=torch.float32)[None]
        depth, op = render_depth_maps(
            runtime.model, prep.volume, prep.bounds, torch.tensor([K]), pose_t, *WH,
            n_samples=runtime.samples_per_ray, min_opacity=runtime.config.min_opacity,
        )  # fmt: skip
        torch.testing.assert_close(op[0], torch.from_numpy(frame.opacity))
        torch.testing.assert_close(depth[0], torch.from_numpy(frame.depth_m))


def _skip_bound(
    rt: ModelRuntime, prep: Prepared, rays: Rays, ref: RenderOutputs, occupancy: Tensor
) -> Tensor:
    """(R,) tau_s: optical depth of the samples the skip leaves out (density in empty voxels).

    Skipping sets alpha_i = 0 for those samples, so (colours in [0, 1]) the opacity changes by at
    most ``1 - exp(-tau_s)`` and the weights by at most ``tau_s + 1 - exp(-tau_s) <= 2 tau_s`` in sum.
    """
    assert rt.model is not None
    points = (rays.origins[:, None] + ref.t[..., None] * rays.directions[:, None]).reshape(-1, 3)
    sigma, _ = rt.model.density_at(prep.volume, prep.bounds, points)
    empty = ~occupancy_mask(occupancy, prep.bounds)(points)
    deltas = ref.t[:, 1:2] - ref.t[:, 0:1]  # uniform bins
    return (sigma * empty).reshape(ref.t.shape).sum(dim=-1) * deltas[:, 0]


@torch.no_grad()
def test_skipping_equals_field_on_the_rays_it_does_not_skip_and_is_bounded_elsewhere(
    runtime: ModelRuntime,
) -> None:
    prep = runtime._volume.prepare()
    occupancy_grid(runtime._loaded, prep)
    assert prep.max_density is not None
    threshold = float(torch.quantile(prep.max_density.flatten(), 0.3))  # ~30 % of voxels empty
    saved = runtime.config
    runtime.config = dataclasses.replace(saved, occupancy_threshold=threshold, min_weight=0.0)
    try:
        occupancy = occupancy_grid(runtime._loaded, prep)
        assert 0.1 < 1.0 - occupancy.float().mean().item() < 0.5
        for K, pose in CAMERAS.values():
            rays = camera_rays(K, pose)
            (rgb, ray_depth, opacity, ov, _), stats = node_render(runtime, prep, rays, occupancy)
            ref = field_render(runtime, prep, rays)
            assert ov is not None and stats["density_evals"] < stats["samples"]
            tau_s = _skip_bound(runtime, prep, rays, ref, occupancy)
            exact = tau_s == 0  # no sample of the ray lies in an empty voxel (or misses the volume)
            assert exact.any() and (~exact).any()
            torch.testing.assert_close(rgb[exact], ref.rgb[exact])
            torch.testing.assert_close(ov[exact], ref.ov[exact])
            torch.testing.assert_close(ray_depth[exact], ref.depth_m[exact])
            torch.testing.assert_close(opacity[exact], ref.opacity[exact])
            assert bool(((opacity - ref.opacity).abs() <= 1.0 - torch.exp(-tau_s) + 1e-6).all())
            assert bool(((rgb - ref.rgb).abs().amax(dim=-1) <= 2.0 * tau_s + 1e-6).all())
            assert bool((opacity <= ref.opacity + 1e-6).all())  # skipping only removes density
    finally:
        runtime.config = saved


@torch.no_grad()
def test_min_weight_pruning_equals_field_weight_threshold(runtime: ModelRuntime) -> None:
    prep = runtime._volume.prepare()
    saved = runtime.config
    runtime.config = dataclasses.replace(saved, occupancy_threshold=0.0, min_weight=0.03)
    try:
        occupancy = occupancy_grid(runtime._loaded, prep)
        assert bool(occupancy.all())  # densities are >= 0: nothing is skipped, only pruned
        K, pose = CAMERAS["inside"]
        rays = camera_rays(K, pose)
        (rgb, ray_depth, opacity, ov, _), stats = node_render(runtime, prep, rays, occupancy)
        ref = field_render(runtime, prep, rays, weight_threshold=0.03)
        assert ov is not None and 0 < stats["appearance_evals"] < stats["density_evals"] == stats["samples"]
        torch.testing.assert_close(rgb, ref.rgb)
        torch.testing.assert_close(ov, ref.ov)
        torch.testing.assert_close(ray_depth, ref.depth_m)
        torch.testing.assert_close(opacity, ref.opacity)
    finally:
        runtime.config = saved
