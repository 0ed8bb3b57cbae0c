"""Property tests for mapper.model.ops.rendering (volume rendering maths)."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mapper.model.ops.rendering import (
    Rays,
    RaySamples,
    accumulated_opacity,
    composite,
    expected_depth,
    intersect_aabb,
    render_weights,
    sample_along_rays,
)

# Densities and spacings spanning the stiff range the renderer must survive.
densities = st.one_of(st.sampled_from([0.0, 1e-3, 1e6]), st.floats(min_value=0.0, max_value=1e6))
spacings = st.one_of(st.sampled_from([1e-6, 1e-3, 1.0, 1e3]), st.floats(min_value=1e-6, max_value=1e3))


def ray_batch(draw_sigma: list[float], draw_delta: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
    n = min(len(draw_sigma), len(draw_delta))
    sigma = torch.tensor(draw_sigma[:n], dtype=torch.float64).unsqueeze(0)
    deltas = torch.tensor(draw_delta[:n], dtype=torch.float64).unsqueeze(0)
    return sigma, deltas


@settings(max_examples=80, deadline=None)
@given(st.lists(densities, min_size=1, max_size=12), st.lists(spacings, min_size=12, max_size=12))
def test_weights_are_a_sub_probability_and_transmittance_decreases(
    sig: list[float], dlt: list[float]
) -> None:
    sigma, deltas = ray_batch(sig, dlt)
    for dtype in (torch.float32, torch.float64):
        weights, trans = render_weights(sigma.to(dtype), deltas.to(dtype))
        assert torch.isfinite(weights).all() and torch.isfinite(trans).all()
        assert (weights >= 0).all()
        assert accumulated_opacity(weights).item() <= 1 + 1e-6
        assert (trans[:, 1:] <= trans[:, :-1]).all()
        assert trans[0, 0].item() == 1.0
        # Telescoping identity: w_i = T_i - T_{i+1}.
        t_next = torch.cat(
            [trans[:, 1:], (trans[:, -1:] * torch.exp(-(sigma * deltas)[:, -1:]).to(dtype))], 1
        )
        torch.testing.assert_close(weights, (trans - t_next).clamp_min(0), atol=1e-6, rtol=1e-5)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(densities, min_size=1, max_size=10),
    st.lists(spacings, min_size=10, max_size=10),
    st.floats(min_value=-2.0, max_value=2.0),
)
def test_constant_colour_renders_to_itself_times_opacity(
    sig: list[float], dlt: list[float], c: float
) -> None:
    sigma, deltas = ray_batch(sig, dlt)
    weights, _ = render_weights(sigma, deltas)
    values = torch.full((*weights.shape, 3), c, dtype=torch.float64)
    rendered = composite(weights, values)
    expected = accumulated_opacity(weights).unsqueeze(-1) * c
    torch.testing.assert_close(rendered, expected.expand(1, 3), atol=1e-12, rtol=1e-12)


def test_opaque_first_sample_takes_everything_and_empty_space_nothing() -> None:
    deltas = torch.full((2, 5), 0.1, dtype=torch.float64)
    sigma = torch.zeros(2, 5, dtype=torch.float64)
    sigma[0, 2] = 1e6
    weights, trans = render_weights(sigma, deltas)
    assert weights[0].tolist() == [0.0, 0.0, 1.0, 0.0, 0.0]
    assert weights[1].abs().sum().item() == 0.0
    assert trans[1].tolist() == [1.0] * 5
    t = torch.linspace(1, 5, 5, dtype=torch.float64).expand(2, 5)
    depth = expected_depth(weights, t)
    assert depth[0].item() == pytest.approx(3.0)
    assert depth[1].item() == 1.0  # no opacity: nearest sample, tell apart via opacity


def test_alpha_uses_the_sample_spacing() -> None:
    sigma = torch.tensor([[2.0]], dtype=torch.float64)
    for delta in (0.01, 0.5, 3.0):
        weights, _ = render_weights(sigma, torch.tensor([[delta]], dtype=torch.float64))
        assert weights.item() == pytest.approx(-math.expm1(-2.0 * delta), rel=1e-12)


def test_halving_the_spacing_with_twice_the_samples_keeps_the_opacity() -> None:
    # Discretisation invariance only holds because alpha includes delta.
    sigma = torch.full((1, 8), 0.7, dtype=torch.float64)
    w8, _ = render_weights(sigma, torch.full((1, 8), 0.25, dtype=torch.float64))
    w16, _ = render_weights(torch.full((1, 16), 0.7, dtype=torch.float64), torch.full((1, 16), 0.125))
    assert accumulated_opacity(w8).item() == pytest.approx(accumulated_opacity(w16).item(), rel=1e-12)


def test_sample_along_rays_uniform_and_stratified() -> None:
    origins = torch.zeros(3, 3)
    dirs = torch.nn.functional.normalize(
        torch.randn(3, 3, generator=torch.Generator().manual_seed(0)), dim=-1
    )
    t, deltas = sample_along_rays(origins, dirs, 0.2, 8.0, 64, stratified=False)
    assert t.shape == deltas.shape == (3, 64)
    torch.testing.assert_close(deltas.sum(-1), torch.full((3,), 7.8))
    assert t[0, 0].item() == pytest.approx(0.2 + 7.8 / 128)
    g = torch.Generator().manual_seed(1)
    near = torch.tensor([0.5, 1.0, 2.0])
    ts, ds = sample_along_rays(origins, dirs, near, near + 1.0, 10, stratified=True, generator=g)
    edges = near.unsqueeze(-1) + torch.linspace(0, 1, 11)
    assert ((ts >= edges[:, :-1] - 1e-6) & (ts <= edges[:, 1:] + 1e-6)).all()
    assert (ts[:, 1:] > ts[:, :-1]).all()
    ts2, _ = sample_along_rays(
        origins, dirs, near, near + 1.0, 10, stratified=True, generator=torch.Generator().manual_seed(1)
    )
    assert torch.equal(ts, ts2)  # reproducible with a seeded generator
    samples = RaySamples(Rays(origins, dirs), ts, ds)
    torch.testing.assert_close(samples.positions.norm(dim=-1), ts)


def test_sample_along_rays_rejects_bad_bounds() -> None:
    o = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="near < far"):
        sample_along_rays(o, o, 2.0, 1.0, 8, stratified=False)
    with pytest.raises(ValueError, match="n_samples 0"):
        sample_along_rays(o, o, 0.1, 1.0, 0, stratified=False)
    with pytest.raises(ValueError, match=r"\(2,\) tensor"):
        sample_along_rays(o, o, torch.zeros(3), 1.0, 8, stratified=False)


def test_gradcheck_render_chain_float64() -> None:
    g = torch.Generator().manual_seed(2)
    sigma = (torch.rand(3, 6, generator=g, dtype=torch.float64) * 3).requires_grad_()
    deltas = (torch.rand(3, 6, generator=g, dtype=torch.float64) * 0.5 + 0.01).requires_grad_()
    colours = torch.rand(3, 6, 2, generator=g, dtype=torch.float64).requires_grad_()
    t = torch.cumsum(deltas.detach(), dim=-1)

    def render(s: torch.Tensor, d: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, ...]:
        w, trans = render_weights(s, d)
        return composite(w, c), expected_depth(w, t), trans

    assert torch.autograd.gradcheck(render, (sigma, deltas, colours))


@pytest.mark.parametrize(
    "dtype,tol", [(torch.float16, 2e-3), (torch.bfloat16, 1.6e-2), (torch.float32, 1e-6)]
)
def test_low_precision_matches_float64_reference(dtype: torch.dtype, tol: float) -> None:
    g = torch.Generator().manual_seed(4)
    sigma = torch.rand(16, 32, generator=g, dtype=torch.float64) * 5
    sigma[:4] = 0.0
    sigma[4:8, 10] = 6e4  # near fp16 max: still a finite input
    deltas = torch.full((16, 32), 7.8 / 32, dtype=torch.float64)
    colours = torch.rand(16, 32, 3, generator=g, dtype=torch.float64)
    w64, _ = render_weights(sigma, deltas)
    ref = composite(w64, colours)
    # Inputs rounded to the low precision dtype; compare against float64 of the same rounded inputs.
    s_lo, d_lo, c_lo = sigma.to(dtype), deltas.to(dtype), colours.to(dtype)
    w_lo, trans_lo = render_weights(s_lo, d_lo)
    assert w_lo.dtype == dtype and trans_lo.dtype == dtype
    ref_rounded = composite(render_weights(s_lo.double(), d_lo.double())[0], c_lo.double())
    out = composite(w_lo, c_lo)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out.double(), ref_rounded, atol=tol, rtol=tol)
    # And the rounding of the inputs themselves costs at most a few dtype ulps of the colour.
    torch.testing.assert_close(out.double(), ref, atol=8 * tol, rtol=8 * tol)


def test_intersect_aabb_inside_outside_miss_and_parallel() -> None:
    box_min = torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)
    box_max = torch.tensor([2.0, 1.0, 1.0], dtype=torch.float64)
    origins = torch.tensor(
        [
            [1.0, 0.5, 0.5],
            [-1.0, 0.5, 0.5],
            [-1.0, 5.0, 0.5],
            [0.0, -1.0, 0.5],
            [3.0, -1.0, 0.5],
            [1.0, 0.5, 2.0],
        ],
        dtype=torch.float64,
    )
    dirs = torch.tensor(
        [
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        dtype=torch.float64,
    )
    t_near, t_far, hit = intersect_aabb(origins, dirs, box_min, box_max)
    # inside; from outside; parallel and off the box; in the x = 0 face plane; parallel outside; away.
    assert hit.tolist() == [True, True, False, True, False, False]
    assert t_near.tolist() == [0.0, 1.0, 0.0, 1.0, 0.0, 0.0]
    assert t_far.tolist() == [1.0, 3.0, 0.0, 2.0, 0.0, 0.0]
    for dtype in (torch.float32, torch.float16, torch.bfloat16):
        tn, tf, h = intersect_aabb(origins.to(dtype), dirs.to(dtype), box_min, box_max)
        assert h.tolist() == hit.tolist() and torch.isfinite(tn).all() and torch.isfinite(tf).all()
