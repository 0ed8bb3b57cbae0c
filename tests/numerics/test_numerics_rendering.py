"""Stiff / extreme cases for volume rendering.

Densities 0, 1e-3, 1e6 (and overflowed, inf in fp16) and mixtures; spacings 1e-6 .. 1e3;
fp16 / bf16 / fp32 against float64; gradcheck in float64; no NaN/Inf forward or backward.
"""

from __future__ import annotations

import itertools

import pytest
import torch

from mapper.model.ops.rendering import accumulated_opacity, composite, expected_depth, render_weights

DENSITIES = [0.0, 1e-3, 1e6]
SPACINGS = [1e-6, 1e-3, 1.0, 1e3]
ALL_DTYPES = [torch.float64, torch.float32, torch.float16, torch.bfloat16]


def extreme_grid() -> tuple[torch.Tensor, torch.Tensor]:
    """Every (density, spacing) pair as a constant ray, plus mixed rays; (R, S) float64 each."""
    rows_sigma, rows_delta = [], []
    for sigma, delta in itertools.product(DENSITIES, SPACINGS):
        rows_sigma.append([sigma] * 6)
        rows_delta.append([delta] * 6)
    # Mixtures: alternating empty / opaque, tiny before huge, huge spacing then tiny.
    rows_sigma += [[0, 1e6, 0, 1e6, 0, 1e6], [1e-3, 1e-3, 1e6, 1e-3, 0, 0], [1e6, 0, 0, 0, 0, 1e-3]]
    rows_delta += [[1e-6, 1e3, 1e-3, 1.0, 1e3, 1e-6], [1e3, 1e3, 1e-6, 1e3, 1.0, 1.0], [1e-6] * 6]
    return torch.tensor(rows_sigma, dtype=torch.float64), torch.tensor(rows_delta, dtype=torch.float64)


def _forward_backward(dtype: torch.dtype) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    sigma64, delta64 = extreme_grid()
    sigma = sigma64.to(dtype).requires_grad_()  # 1e6 overflows to inf in fp16: must still work
    deltas = delta64.to(dtype).requires_grad_()
    colours = torch.rand(*sigma.shape, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    colours = colours.to(dtype).requires_grad_()
    t = torch.cumsum(delta64, dim=-1).to(dtype)
    weights, trans = render_weights(sigma, deltas)
    rgb = composite(weights, colours)
    depth = expected_depth(weights, t)
    (rgb.double().sum() + depth.double().sum() + trans.double().sum()).backward()
    grads = [leaf.grad for leaf in (sigma, deltas, colours)]
    assert all(g is not None for g in grads)
    return [weights, trans, rgb, depth], grads  # type: ignore[return-value]


@pytest.mark.parametrize("dtype", ALL_DTYPES)
def test_extremes_forward_and_backward_are_finite(dtype: torch.dtype) -> None:
    outputs, grads = _forward_backward(dtype)
    weights = outputs[0]
    for out in outputs:
        assert torch.isfinite(out).all(), dtype
    assert (weights >= 0).all()
    assert (accumulated_opacity(weights.float()) <= 1 + 1e-2).all()
    _, ref_grads = _forward_backward(torch.float64)
    limit = torch.finfo(dtype).max
    for grad, ref in zip(grads, ref_grads, strict=True):
        assert not torch.isnan(grad).any(), dtype
        # A gradient may only be infinite where the true (float64) gradient exceeds the dtype's
        # range (fp16: depth gradients of ~1e6 with 1 km spacings; grad scaling's job).
        overflow = torch.isinf(grad)
        assert (ref[overflow].abs() > limit / 2).all(), dtype
    if dtype in (torch.float64, torch.float32, torch.bfloat16):
        assert all(torch.isfinite(g).all() for g in grads)


def test_extremes_match_closed_forms_in_float64() -> None:
    sigma, deltas = extreme_grid()
    weights, trans = render_weights(sigma, deltas)
    for r in range(12):  # constant rays: opacity = 1 - exp(-sigma * total length)
        expected = -torch.expm1(-(sigma[r] * deltas[r]).sum().clamp_max(1e4))
        assert accumulated_opacity(weights[r : r + 1]).item() == pytest.approx(
            expected.item(), rel=1e-9, abs=1e-300
        )
    # Tiny optical depths keep their precision (expm1, not 1 - exp).
    w, _ = render_weights(
        torch.tensor([[1e-3]], dtype=torch.float64), torch.tensor([[1e-6]], dtype=torch.float64)
    )
    assert w.item() == pytest.approx(1e-9, rel=1e-6)
    w32, _ = render_weights(torch.tensor([[1e-3]]), torch.tensor([[1e-6]]))
    assert w32.item() == pytest.approx(1e-9, rel=1e-4)


@pytest.mark.parametrize(
    "dtype,atol",
    [(torch.float32, 1e-6), (torch.float16, 3e-3), (torch.bfloat16, 2e-2)],
)
def test_low_precision_vs_float64_on_extremes(dtype: torch.dtype, atol: float) -> None:
    sigma64, delta64 = extreme_grid()
    colours64 = torch.rand(*sigma64.shape, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    # Reference: float64 on the inputs as the low-precision dtype represents them.
    s, d, c = sigma64.to(dtype), delta64.to(dtype), colours64.to(dtype)
    ref = composite(render_weights(s.double(), d.double())[0], c.double())
    out = composite(render_weights(s, d)[0], c)
    torch.testing.assert_close(out.double(), ref, atol=atol, rtol=atol)


def test_gradcheck_float64_across_stiff_range() -> None:
    # Strictly positive densities (0 is a clamp kink where finite differences are one-sided).
    sigma = torch.tensor(
        [[1e-3, 1e-3, 1e-3, 1e-3], [5.0, 0.5, 50.0, 1e-3], [1e-3, 1e6, 1e-3, 2.0], [1e-2, 1e-2, 3.0, 1e-3]],
        dtype=torch.float64,
        requires_grad=True,
    )
    deltas = torch.tensor(
        [[1e-6, 1e-3, 1.0, 1e3], [1e-3, 1.0, 1e-3, 1.0], [0.5, 1e-6, 0.5, 0.5], [1e2, 1e-6, 1e-3, 1.0]],
        dtype=torch.float64,
        requires_grad=True,
    )
    colours = torch.rand(4, 4, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    colours.requires_grad_()

    def fn(s: torch.Tensor, d: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        w, trans = render_weights(s, d)
        return composite(w, c), trans

    assert torch.autograd.gradcheck(fn, (sigma, deltas, colours), eps=1e-9, atol=1e-6, rtol=1e-4)


def test_negative_and_nan_free_inputs_are_clamped_not_propagated() -> None:
    sigma = torch.tensor([[-5.0, 0.0, 2.0]], requires_grad=True)
    deltas = torch.tensor([[1.0, 0.0, 1.0]])
    weights, trans = render_weights(sigma, deltas)
    assert weights[0, 0] == 0 and weights[0, 1] == 0 and torch.isfinite(weights).all()
    weights.sum().backward()
    assert sigma.grad is not None and torch.isfinite(sigma.grad).all()
