"""Leaving out what the scene does not need: the march_rays levers against the dense march,
as pure functions in float64 with analytic fields.

* ``weight_groups``: runs of consecutive samples, about equal mass, every index in range;
* ``appearance_groups``: exact for an appearance that is affine along the ray (any K, with and
  without ``min_weight``), bounded by L x the weighted spread of the groups for an L-Lipschitz one,
  identical to the per-sample march for K >= S;
* ``stop_transmittance`` (early ray termination): opacity, colour and OV within the threshold of
  dense, identical on rays that stay above it, fewer density evaluations behind opaque surfaces;
* occupancy skipping: an all-occupied grid equals dense exactly, an all-empty grid renders the
  background (nothing) without a single network call;
* the node runtime: every lever switched off is the dense path, bit for bit.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from mapper.map.window import Keyframe, KeyframeWindow
from mapper.model.ops.cost_volume import VolumeBounds
from mapper.model.ops.rendering import Rays
from mapper.model.render import AppearanceFn, MarchOutputs, march_rays, occupancy_mask, weight_groups
from mapper.node.config import WindowConfig
from mapper.runtime.model_runtime import ModelRuntime, ModelRuntimeConfig
from mapper.runtime.views import view_groups
from tests.model_helpers import look_at, tiny_model_config

DT = torch.float64
BOUNDS = VolumeBounds(origin_m=(-2.0, -2.0, -2.0), voxel_size_m=0.25, dims=(16, 16, 16))
BOX = (torch.tensor(BOUNDS.origin_m, dtype=DT), torch.tensor(BOUNDS.max_corner_m, dtype=DT))


def make_rays(n: int, seed: int) -> Rays:
    """n rays from a sphere of radius 3 m towards points near the origin."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=DT), dim=-1) * 3.0
    targets = 0.5 * torch.randn(n, 3, generator=g, dtype=DT)
    return Rays(origins, torch.nn.functional.normalize(targets - origins, dim=-1))


class BlobDensity:
    """sigma = floor + peak * exp(-|x - c|^2 / r^2): a soft surface in a faint fog; features = x."""

    def __init__(self, floor: float, peak: float, radius: float = 0.6) -> None:
        self.floor, self.peak, self.radius = floor, peak, radius
        self.calls = 0

    def __call__(self, points: Tensor) -> tuple[Tensor, Tensor]:
        self.calls += int(points.shape[0])
        r2 = (points**2).sum(-1) / self.radius**2
        return self.floor + self.peak * torch.exp(-r2), points.clone()


def affine_appearance(points: Tensor, dirs: Tensor, feat: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """rgb and a 5-d OV that are affine in the position (and use the handed-over features)."""
    a = torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.15, 0.1], [-0.1, 0.05, 0.2]], dtype=points.dtype)
    rgb = 0.5 + points @ a.T
    ov = torch.cat([feat, points[:, :1] * 2.0 - 1.0, 1.0 + 0.0 * points[:, :1]], dim=-1)
    return rgb, ov, torch.ones(points.shape[0], dtype=torch.bool)


FREQUENCY = 2.0
WAVE_AXES = [[0.6, 0.8, 0.0], [0.0, 0.6, 0.8], [0.8, 0.0, 0.6]]  # unit vectors


def wavy_appearance(points: Tensor, dirs: Tensor, feat: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """rgb = 0.5 + 0.5 sin(FREQUENCY a_c . x) in [0, 1]: along a unit ray each channel is
    (0.5 FREQUENCY)-Lipschitz in t."""
    rgb = 0.5 + 0.5 * torch.sin(FREQUENCY * points @ torch.tensor(WAVE_AXES, dtype=points.dtype).T)
    return rgb, rgb[:, :2].clone(), torch.ones(points.shape[0], dtype=torch.bool)


def march(rays: Rays, density: BlobDensity, appearance: AppearanceFn | None, **kw: Any) -> MarchOutputs:
    return march_rays(rays, density, appearance, n_samples=32, near_m=0.2, far_m=8.0, box=BOX, **kw)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_groups=st.integers(1, 40),
    zero_rows=st.integers(0, 3),
)
def test_weight_groups_are_runs_in_range_with_bounded_mass(seed: int, n_groups: int, zero_rows: int) -> None:
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(8, 24, generator=g, dtype=DT) ** 3 * (torch.rand(8, 24, generator=g, dtype=DT) > 0.3)
    w[:zero_rows] = 0.0
    group = weight_groups(w, n_groups)
    assert group.shape == w.shape and group.dtype == torch.long
    assert bool(((group >= 0) & (group < n_groups)).all())
    assert bool((group[:, 1:] >= group[:, :-1]).all())  # never decreases: runs of consecutive samples
    assert bool((group[:zero_rows] == 0).all())
    mass = torch.zeros(8, n_groups, dtype=DT).scatter_add_(1, group, w)
    bound = w.sum(-1, keepdim=True) / n_groups + w.amax(-1, keepdim=True)
    assert bool((mass <= bound + 1e-12).all())
    torch.testing.assert_close(mass.sum(-1), w.sum(-1))


def test_weight_groups_rejects_a_bad_group_count() -> None:
    with pytest.raises(ValueError, match="n_groups"):
        weight_groups(torch.ones(2, 3), 0)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_groups=st.integers(1, 31),
    floor=st.sampled_from([0.0, 0.05, 0.5]),
    peak=st.sampled_from([0.5, 5.0, 200.0]),
    min_weight=st.sampled_from([0.0, 1e-3]),
)
def test_groups_are_exact_for_an_affine_appearance(
    seed: int, n_groups: int, floor: float, peak: float, min_weight: float
) -> None:
    rays = make_rays(64, seed)
    dense = march(rays, BlobDensity(floor, peak), affine_appearance, min_weight=min_weight)
    grouped = march(rays, BlobDensity(floor, peak), affine_appearance, min_weight=min_weight,
                    appearance_groups=n_groups)  # fmt: skip
    assert dense.rgb is not None and grouped.rgb is not None
    assert dense.ov is not None and grouped.ov is not None
    torch.testing.assert_close(grouped.weights, dense.weights)  # grouping touches the appearance only
    torch.testing.assert_close(grouped.rgb, dense.rgb, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(grouped.ov, dense.ov, atol=1e-10, rtol=1e-10)
    assert grouped.appearance_evals <= 64 * n_groups
    # covered opacity (weights of samples whose appearance ran and saw something) is the same
    kept = dense.weights >= min_weight if min_weight else torch.ones_like(dense.valid)
    torch.testing.assert_close((grouped.weights * grouped.valid).sum(-1), (dense.weights * kept).sum(-1))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), n_groups=st.integers(1, 12), floor=st.sampled_from([0.02, 0.3]))
def test_group_error_is_bounded_by_lipschitz_times_weighted_spread(
    seed: int, n_groups: int, floor: float
) -> None:
    rays = make_rays(64, seed)
    dense = march(rays, BlobDensity(floor, 8.0), wavy_appearance)
    grouped = march(rays, BlobDensity(floor, 8.0), wavy_appearance, appearance_groups=n_groups)
    assert dense.rgb is not None and grouped.rgb is not None
    w, t = dense.weights, dense.t
    group = weight_groups(w, n_groups)
    mass = torch.zeros(64, n_groups, dtype=DT).scatter_add_(1, group, w)
    t_mean = torch.zeros(64, n_groups, dtype=DT).scatter_add_(1, group, w * t) / mass.clamp_min(1e-300)
    spread = (w * (t - t_mean.gather(1, group)).abs()).sum(-1)  # sum_i w_i |t_i - t_mean(group(i))|
    lipschitz = 0.5 * FREQUENCY  # |d/dt 0.5 sin(f a . (o + t d))| <= 0.5 f |a| |d| = 0.5 f
    err = (grouped.rgb - dense.rgb).abs().amax(-1)
    assert bool((err <= lipschitz * spread + 1e-9).all())


def test_groups_at_least_the_samples_are_the_per_sample_march() -> None:
    rays = make_rays(32, 1)
    dense = march(rays, BlobDensity(0.1, 5.0), wavy_appearance)
    same = march(rays, BlobDensity(0.1, 5.0), wavy_appearance, appearance_groups=32)
    assert dense.rgb is not None and same.rgb is not None
    assert same.appearance_evals == dense.appearance_evals
    assert torch.equal(same.rgb, dense.rgb) and torch.equal(same.depth_m, dense.depth_m)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    threshold=st.sampled_from([1e-6, 1e-3, 1e-2, 0.2]),
    block=st.integers(1, 12),
    peak=st.sampled_from([2.0, 50.0, 1e4]),
)
def test_early_termination_error_is_bounded_by_the_threshold(
    seed: int, threshold: float, block: int, peak: float
) -> None:
    rays = make_rays(64, seed)
    d_dense, d_stop = BlobDensity(0.05, peak), BlobDensity(0.05, peak)
    dense = march(rays, d_dense, wavy_appearance)
    stop = march(rays, d_stop, wavy_appearance, stop_transmittance=threshold, termination_block=block)
    assert dense.rgb is not None and stop.rgb is not None and dense.ov is not None and stop.ov is not None
    # colours and OV in [0, 1]: the samples left out carry at most the transmittance at the stop
    assert bool(((dense.opacity - stop.opacity) <= threshold + 1e-12).all())
    assert bool((stop.opacity <= dense.opacity + 1e-12).all())
    assert bool(((dense.rgb - stop.rgb).abs() <= threshold + 1e-12).all())
    assert bool(((dense.ov - stop.ov).abs() <= threshold + 1e-12).all())
    # rays whose transmittance never fell below the threshold are untouched
    transmittance_end = 1.0 - dense.weights.cumsum(-1)[:, :-1]
    untouched = (transmittance_end >= threshold).all(-1)
    torch.testing.assert_close(stop.rgb[untouched], dense.rgb[untouched], atol=1e-12, rtol=0)
    assert stop.density_evals == d_stop.calls <= dense.density_evals == d_dense.calls
    if peak >= 50.0 and threshold >= 1e-3 and block <= 8:  # opaque blob: rays stop inside it
        assert stop.density_evals < dense.density_evals


def test_early_termination_rejects_bad_settings() -> None:
    rays = make_rays(4, 0)
    with pytest.raises(ValueError, match="stop_transmittance"):
        march(rays, BlobDensity(0.1, 1.0), None, stop_transmittance=1.0)
    with pytest.raises(ValueError, match="termination_block"):
        march(rays, BlobDensity(0.1, 1.0), None, stop_transmittance=0.1, termination_block=0)
    with pytest.raises(ValueError, match="appearance_groups"):
        march(rays, BlobDensity(0.1, 1.0), None, appearance_groups=-1)


def test_an_all_occupied_grid_equals_dense_and_an_all_empty_grid_renders_the_background() -> None:
    rays = make_rays(64, 7)
    full = occupancy_mask(torch.ones(BOUNDS.dims, dtype=torch.bool), BOUNDS)
    empty = occupancy_mask(torch.zeros(BOUNDS.dims, dtype=torch.bool), BOUNDS)
    dense = march(rays, BlobDensity(0.1, 5.0), wavy_appearance)
    occupied = march(rays, BlobDensity(0.1, 5.0), wavy_appearance, sample_mask=full)
    assert dense.rgb is not None and occupied.rgb is not None
    assert dense.ov is not None and occupied.ov is not None
    for a, b in ((occupied.rgb, dense.rgb), (occupied.ov, dense.ov), (occupied.depth_m, dense.depth_m),
                 (occupied.opacity, dense.opacity)):  # fmt: skip
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    density = BlobDensity(0.1, 5.0)
    for groups, stop in ((0, 0.0), (4, 1e-3)):
        nothing = march(rays, density, wavy_appearance, sample_mask=empty, appearance_groups=groups,
                        stop_transmittance=stop)  # fmt: skip
        assert nothing.rgb is not None and nothing.ov is not None
        assert nothing.density_evals == 0 and nothing.appearance_evals == 0 and density.calls == 0
        assert not nothing.opacity.any() and not nothing.rgb.any() and not nothing.ov.any()
        assert not nothing.valid.any()


def test_levers_combined_stay_within_their_bounds_on_a_faint_fog() -> None:
    """A fog everywhere (the trained cpu-small model's case): groups + termination + pruning."""
    rays = make_rays(128, 3)
    dense = march(rays, BlobDensity(0.09, 6.0), affine_appearance)
    fast = march(rays, BlobDensity(0.09, 6.0), affine_appearance, appearance_groups=3,
                 stop_transmittance=1e-3, min_weight=1e-4)  # fmt: skip
    assert dense.rgb is not None and fast.rgb is not None
    assert fast.appearance_evals <= 3 * 128 < dense.appearance_evals
    # affine appearance: grouping is exact, termination and pruning lose at most 1e-3 + S * 1e-4 of weight
    scale = float(affine_appearance(BOX[1][None], BOX[1][None], BOX[1][None])[0].abs().max())
    assert float((fast.rgb - dense.rgb).abs().max()) <= (1e-3 + 32 * 1e-4) * max(1.0, scale) + 1e-9


# ---- the node runtime: every lever off is the dense path --------------------------------------

D = 6
TINY = tiny_model_config(ov_dim=D, max_voxels=2048, n_samples=16)


class FakeEncoder:
    space = "test-space"
    dim = D

    def encode(self, texts: list[str]) -> np.ndarray:
        return np.eye(len(texts), D, dtype=np.float32)


@pytest.fixture(scope="module")
def runtime() -> ModelRuntime:
    from mapper.model.field import GovNeSF

    torch.manual_seed(0)
    cfg = ModelRuntimeConfig(device="cpu", chunk_rays=128, chunk_points=1000, source_views=8)
    rt = ModelRuntime(cfg, model=GovNeSF(TINY).eval(), text_encoder=lambda space: FakeEncoder())  # type: ignore[arg-type,return-value]
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    rt.attach(window)
    for i in range(4):
        rng = np.random.default_rng(i)
        a = 0.7 * i
        window.consider(Keyframe(
            seq=i, stamp_ns=i, camera="cam0", K=np.array([32.0, 32.0, 20.0, 15.0]),
            world_from_cam=look_at((2.0 * np.cos(a), 2.0 * np.sin(a), 1.2), (0.0, 0.0, 0.5)),
            rgb=rng.integers(0, 256, (30, 40, 3), dtype=np.uint8), depth_m=np.full((30, 40), 2.0, np.float32),
            ov=rng.standard_normal((5, 6, D)).astype(np.float16), ov_space="test-space",
        ))  # fmt: skip
    rt.sync()
    return rt


@torch.no_grad()
def test_runtime_with_every_lever_off_is_the_dense_path(runtime: ModelRuntime) -> None:
    K, pose = [20.0, 20.0, 10.0, 7.5], look_at((2.0, 0.5, 1.1), (0.0, 0.0, 0.5))
    outputs, texts = ["rgb", "depth", "label", "score"], ["a", "b"]
    dense = runtime.render(K, pose, 20, 15, outputs, texts, empty_space_skipping=False)
    saved = runtime.config
    runtime.config = dataclasses.replace(
        saved, occupancy_threshold=0.0, min_weight=0.0, stop_transmittance=0.0, appearance_groups=0,
        batched_view_groups=False,
    )
    try:
        off = runtime.render(K, pose, 20, 15, outputs, texts, empty_space_skipping=True)
        runtime.config = dataclasses.replace(
            saved, occupancy_threshold=0.0, appearance_groups=3, stop_transmittance=1e-3, refine_margin=0.0
        )
        fast = runtime.render(K, pose, 20, 15, outputs, texts, empty_space_skipping=True)
    finally:
        runtime.config = saved
    for name in ("rgb", "depth_m", "label", "score", "opacity"):
        np.testing.assert_array_equal(getattr(off, name), getattr(dense, name), err_msg=name)
    assert off.stats["appearance_evals"] == dense.stats["appearance_evals"] == dense.stats["samples"]
    # the fast path: at most 3 appearance evaluations a ray, fewer density evaluations, and the
    # opacity within the termination threshold (+ nothing skipped at this tiny threshold)
    assert fast.stats["appearance_evals"] <= 3 * 20 * 15 < dense.stats["appearance_evals"]
    assert fast.opacity is not None and dense.opacity is not None
    assert float(np.abs(fast.opacity - dense.opacity).max()) <= 1e-3 + 1e-6
    assert fast.stats["density_evals"] <= dense.stats["density_evals"] + fast.stats["appearance_evals"]


# ---- one network pass over every view group (batched_view_groups) ------------------------------


@pytest.fixture(scope="module")
def few_views_runtime(runtime: ModelRuntime) -> ModelRuntime:
    """The same window with 2 source views a point: several view groups, some of one view."""
    assert runtime.model is not None
    cfg = dataclasses.replace(runtime.config, source_views=2, view_cell_m=0.3)
    rt = ModelRuntime(cfg, model=runtime.model, text_encoder=lambda space: FakeEncoder())  # type: ignore[arg-type,return-value]
    window = KeyframeWindow(WindowConfig(max_keyframes=8, min_translation_m=0.05, min_rotation_deg=5))
    rt.attach(window)
    for kf in runtime._attached[0].keyframes:
        window.consider(kf)
    rt.sync()
    return rt


@torch.no_grad()
@pytest.mark.parametrize("use_depth", [False, True])
def test_batched_view_groups_segment_equals_one_pass_per_group(
    few_views_runtime: ModelRuntime, use_depth: bool
) -> None:
    rt = few_views_runtime
    rng = np.random.default_rng(5)
    points = rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 1.2], (400, 3)).astype(np.float32)
    saved = rt.config
    try:
        rt.config = dataclasses.replace(saved, batched_view_groups=False)
        ref_label, ref_score, _ = rt.segment(points, ["a", "b", "c"], use_depth=use_depth)
        prep = rt._volume.prepare()
        groups = view_groups(rt._loaded, prep, torch.from_numpy(points), prep.has_ov)
        rt.config = dataclasses.replace(saved, batched_view_groups=True)
        label, score, _ = rt.segment(points, ["a", "b", "c"], use_depth=use_depth)
    finally:
        rt.config = saved
    assert len(groups) > 2 and min(int(v.numel()) for _, v in groups) >= 1
    assert (ref_label >= 0).mean() > 0.5
    np.testing.assert_array_equal(label, ref_label)
    np.testing.assert_allclose(score, ref_score, atol=1e-5)


@torch.no_grad()
def test_batched_view_groups_render_equals_one_pass_per_group(few_views_runtime: ModelRuntime) -> None:
    rt = few_views_runtime
    K, pose = [20.0, 20.0, 10.0, 7.5], look_at((2.0, 0.5, 1.1), (0.0, 0.0, 0.5))
    saved = rt.config
    off = dict(occupancy_threshold=0.0, min_weight=0.0, stop_transmittance=0.0, appearance_groups=0)
    try:
        rt.config = dataclasses.replace(saved, batched_view_groups=True, **off)  # type: ignore[arg-type]
        batched = rt.render(K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"])
        rt.config = dataclasses.replace(saved, batched_view_groups=False, **off)  # type: ignore[arg-type]
        per_group = rt.render(K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"])
    finally:
        rt.config = saved
    dense = rt.render(K, pose, 20, 15, ["rgb", "depth", "score"], ["a", "b"], empty_space_skipping=False)
    assert batched.stats["view_groups"] == per_group.stats["view_groups"] > 1
    for frame in (per_group, batched):
        assert frame.rgb is not None and dense.rgb is not None
        assert frame.score is not None and dense.score is not None
        assert int(np.abs(frame.rgb.astype(int) - dense.rgb.astype(int)).max()) <= 1  # uint8 rounding
        np.testing.assert_allclose(frame.score, dense.score, atol=1e-5)
        np.testing.assert_array_equal(frame.depth_m, dense.depth_m)
    np.testing.assert_array_equal(per_group.rgb, dense.rgb)


@torch.no_grad()
def test_refining_every_pixel_is_the_per_sample_appearance_and_a_zero_margin_refines_nothing(
    runtime: ModelRuntime,
) -> None:
    K, pose = [20.0, 20.0, 10.0, 7.5], look_at((2.0, 0.5, 1.1), (0.0, 0.0, 0.5))
    outputs, texts = ["rgb", "depth", "label", "score"], ["a", "b", "c"]
    saved = runtime.config
    common = dict(occupancy_threshold=0.0, stop_transmittance=1e-3)
    try:
        runtime.config = dataclasses.replace(saved, appearance_groups=0, **common)  # type: ignore[arg-type]
        per_sample = runtime.render(K, pose, 20, 15, outputs, texts)
        runtime.config = dataclasses.replace(saved, appearance_groups=2, refine_margin=2.0, **common)  # type: ignore[arg-type]
        everything = runtime.render(K, pose, 20, 15, outputs, texts)
        runtime.config = dataclasses.replace(saved, appearance_groups=2, refine_margin=0.0, **common)  # type: ignore[arg-type]
        coarse = runtime.render(K, pose, 20, 15, outputs, texts)
        runtime.config = dataclasses.replace(saved, appearance_groups=2, refine_margin=0.05, **common)  # type: ignore[arg-type]
        some = runtime.render(K, pose, 20, 15, outputs, texts)
    finally:
        runtime.config = saved
    assert everything.stats["refined_rays"] == 20 * 15 and "refined_rays" not in coarse.stats
    for name in ("rgb", "depth_m", "label", "score", "opacity"):
        np.testing.assert_array_equal(getattr(everything, name), getattr(per_sample, name), err_msg=name)
    assert coarse.stats["appearance_evals"] <= 2 * 20 * 15
    # refined pixels take the per-sample answer; the others keep the coarse one
    assert some.score is not None and coarse.score is not None and per_sample.score is not None
    top2 = np.sort(coarse.score, axis=-1)[..., -2:]
    drawn = coarse.label >= 0  # type: ignore[operator]
    redo = (top2[..., 1] - top2[..., 0] < 0.05) & drawn
    assert 0 < int(redo.sum()) <= some.stats["refined_rays"] < 20 * 15
    np.testing.assert_array_equal(some.label[redo], per_sample.label[redo])  # type: ignore[index]
    np.testing.assert_array_equal(some.label[~redo & drawn], coarse.label[~redo & drawn])  # type: ignore[index]


@torch.no_grad()
def test_rays_below_min_opacity_are_not_refined_and_their_labels_match_the_per_sample_render(
    runtime: ModelRuntime,
) -> None:
    """A view half off the volume: the refinement re-renders only rays that can be labelled
    (opacity >= min_opacity; ``covered`` never exceeds the opacity, which depends on the density
    only), and every label still equals the per-sample render's."""
    K, pose = [20.0, 20.0, 10.0, 7.5], look_at((2.0, 0.5, 1.1), (0.0, 0.0, 2.4))
    outputs, texts = ["rgb", "depth", "label", "score"], ["a", "b", "c"]
    saved = runtime.config
    common = dict(occupancy_threshold=0.0, stop_transmittance=1e-3, min_opacity=0.3)
    try:
        runtime.config = dataclasses.replace(saved, appearance_groups=0, **common)  # type: ignore[arg-type]
        per_sample = runtime.render(K, pose, 20, 15, outputs, texts)
        runtime.config = dataclasses.replace(saved, appearance_groups=2, refine_margin=2.0, **common)  # type: ignore[arg-type]
        refined = runtime.render(K, pose, 20, 15, outputs, texts)
    finally:
        runtime.config = saved
    labelled = refined.opacity >= 0.3
    assert 0 < int(labelled.sum()) < 20 * 15  # the view is partly off the volume
    assert refined.stats["refined_rays"] == int(labelled.sum())
    np.testing.assert_array_equal(refined.label, per_sample.label)
    np.testing.assert_array_equal(refined.opacity, per_sample.opacity)
    assert (refined.label[~labelled] == -1).all()  # type: ignore[index]
    np.testing.assert_array_equal(refined.rgb[labelled], per_sample.rgb[labelled])  # type: ignore[index]
