"""The compiled point kernel (``FusionNet.point_weights``) equals the reference pass."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from mapper.model.config import FusionConfig, get_preset
from mapper.model.fusion import FusionNet
from mapper.model.ops import fusion_kernel
from tests.mapper.model.test_fusion_inference import _inputs, _net, _ranges

ROOT = Path(__file__).resolve().parents[4]
SMALL = get_preset("cpu-small")
HEAD = FusionConfig(hidden_dim=8, attention_dim=4, num_heads=1, ov_dim=384)  # the shipped point head's sizes


def _float(*tensors: torch.Tensor) -> list[torch.Tensor]:
    return [t.float() if t.is_floating_point() else t for t in tensors]


def _reference(net: FusionNet, *args: torch.Tensor, source_range: torch.Tensor | None = None):
    """float64 reference weights and validity of a float32 network's point mode."""
    ref_net = _copy(net).double()
    with torch.no_grad():
        fused = ref_net.forward_reference(*(a.double() if a.is_floating_point() else a for a in args), None,
                                          None if source_range is None else source_range.double())
    return fused.ov_weights, fused.valid


def _assert_as_accurate(net: FusionNet, weights: torch.Tensor, *args: torch.Tensor,
                        source_range: torch.Tensor | None = None) -> None:
    """The kernel's weights are as close to the float64 reference as the float32 torch pass's
    (which carries float32's own error where activations are large): within 2e-6 + 1.5x its error."""
    ref_w, _ = _reference(net, *args, source_range=source_range)
    with torch.no_grad():
        net.point_kernel = False
        torch_w, _ = net.point_weights(*args, source_range)
        net.point_kernel = True
    torch_err = (torch_w.double() - ref_w).abs().max().item()
    torch.testing.assert_close(weights.double(), ref_w, atol=2e-6 + 1.5 * torch_err, rtol=0.0)


def _copy(net: FusionNet) -> FusionNet:
    other = FusionNet(net.feature_dim, net.volume_feature_dim, _cfg_of(net))
    other.load_state_dict(net.state_dict())
    return other.eval()


def _cfg_of(net: FusionNet) -> FusionConfig:
    lin1 = net.mlp_a[0]
    assert isinstance(lin1, torch.nn.Linear)
    return FusionConfig(hidden_dim=lin1.out_features, attention_dim=net.rel_dir_encoding.out_features,
                        num_heads=net.attention.num_heads, range_encoding=net.range_encoding is not None)


@pytest.mark.parametrize("p_fastest", [True, False])
@pytest.mark.parametrize(
    ("cfg", "N", "P"),
    [(HEAD, 16, 1000), (HEAD, 1, 5), (SMALL.fusion, 8, 300), (replace(SMALL.fusion, num_heads=2), 5, 257),
     (get_preset("paper").fusion, 3, 70)],
    ids=["head16", "head1", "small8", "small-2heads", "paper3"],
)
def test_kernel_equals_float64_reference(cfg: FusionConfig, N: int, P: int, p_fastest: bool) -> None:
    net = _net(cfg, 16, 8, seed=N).float()
    rgb, feat, vol, dirs, mask, _ = _float(*_inputs(P, N, 16, 8, seed=20 + N, p_fastest=p_fastest))
    with torch.no_grad():
        weights, valid = net.point_weights(rgb, feat, vol, dirs, mask)
    _, ref_valid = _reference(net, rgb, feat, vol, dirs, mask)
    assert weights.dtype == torch.float32 and weights.shape == (P, N) and weights.is_contiguous()
    assert torch.equal(valid, ref_valid)
    _assert_as_accurate(net, weights, rgb, feat, vol, dirs, mask)
    assert torch.all(weights[~mask] == 0)  # masked views: exactly 0
    assert not valid[: max(1, P // 10)].any() and torch.all(weights[~valid] == 0)  # no view: all 0
    sums = weights.sum(-1)[valid].double()
    torch.testing.assert_close(sums, torch.ones_like(sums), atol=1e-6, rtol=0.0)


def test_kernel_range_encoding() -> None:
    net = _net(replace(SMALL.fusion, range_encoding=True), 16, 8, seed=30).float()
    rgb, feat, vol, dirs, mask, _ = _float(*_inputs(129, 6, 16, 8, seed=31, p_fastest=True))
    r = _ranges(129, 6, seed=32, p_fastest=True).float()  # some 0: clamped to RANGE_MIN_M
    with torch.no_grad():
        weights, _ = net.point_weights(rgb, feat, vol, dirs, mask, r)
        far, _ = net.point_weights(rgb, feat, vol, dirs, mask, r * 2.0)
        with pytest.raises(ValueError, match="range_encoding: pass source_range"):
            net.point_weights(rgb, feat, vol, dirs, mask)
        with pytest.raises(ValueError, match="range_encoding: pass source_range"):
            net.point_weights(rgb, feat, vol, dirs, mask, r[:, :3])
    _assert_as_accurate(net, weights, rgb, feat, vol, dirs, mask, source_range=r)
    assert not torch.allclose(far, weights)  # the distances reach the weights


def test_block_sizes_and_threads_agree() -> None:
    net = _net(HEAD, 16, 8, seed=40).float()
    args = _float(*_inputs(700, 9, 16, 8, seed=41, p_fastest=True))[:5]
    kw = net.point_kernel_weights()
    with torch.no_grad():
        first, valid = fusion_kernel.point_ov_weights(kw, *args, None, threads=1, block=32)
        for block, threads in [(1, 2), (33, 2), (256, 1), (1024, 2), (0, 2)]:
            w, v = fusion_kernel.point_ov_weights(kw, *args, None, threads=threads, block=block)
            assert torch.equal(v, valid)
            torch.testing.assert_close(w, first, atol=1e-7, rtol=0.0)  # blocks differ in reassociation only


def test_extreme_inputs_stay_finite() -> None:
    """Huge features and logits, every view masked, a single view: finite weights, no NaN."""
    net = _net(SMALL.fusion, 16, 8, seed=50).float()
    rgb, feat, vol, dirs, mask, _ = _float(*_inputs(64, 4, 16, 8, seed=51, p_fastest=True))
    with torch.no_grad():
        for scale in (1e-8, 1.0, 1e4):
            w, v = net.point_weights(rgb, feat * scale, vol * scale, dirs, mask)
            assert torch.isfinite(w).all() and torch.equal(v, mask.any(dim=1))
            _assert_as_accurate(net, w, rgb, feat * scale, vol * scale, dirs, mask)
        none = torch.zeros_like(mask)
        w, v = net.point_weights(rgb, feat, vol, dirs, none)
        assert not v.any() and torch.all(w == 0)
        empty_w, empty_v = net.point_weights(rgb[:0], feat[:0], vol[:0], dirs[:0], mask[:0])
        assert empty_w.shape == (0, 4) and empty_v.shape == (0,)


def test_exp_and_elu_against_float64() -> None:
    edges = [-87.0, -86.99, -1e-30, -0.0, 0.0, 1e-30]
    x = np.concatenate([np.linspace(-100.0, 5.0, 20001), edges]).astype(np.float32)
    buf = x[None].copy()
    fusion_kernel._elu_(buf, x.size, np.empty(x.size, np.int32), np.empty(x.size, np.float32))
    xd = x.astype(np.float64)
    ref = np.where(xd > 0, xd, np.expm1(np.maximum(xd, -87.0)))
    assert np.abs(buf[0] - ref).max() < 1e-7  # absolute: elu's output is in (-1, 0] below 0
    neg = x[x <= 0]
    got = np.array([fusion_kernel._exp_neg(np.float32(v), fusion_kernel._POW2) for v in neg])
    rel = np.abs(got - np.exp(np.maximum(neg.astype(np.float64), -87.0))) / np.exp(np.maximum(neg, -87.0))
    assert rel.max() < 1e-6


def test_dispatch_float64_gradients_and_switch() -> None:
    net = _net(SMALL.fusion, 16, 8, seed=60)  # float64: the torch pass, exactly forward's
    args = _inputs(50, 5, 16, 8, seed=61, p_fastest=False)[:5]
    with torch.no_grad():
        w, v = net.point_weights(*args)
        fused = net(*args, None)
    assert torch.equal(w, fused.ov_weights) and torch.equal(v, fused.valid)
    f32 = net.float()
    args32 = _float(*args)
    w32, _ = f32.point_weights(*args32)  # autograd records: the reference pass, with gradients
    assert w32.requires_grad
    (w32 * torch.arange(5.0)).sum().backward()
    for p in (f32.mlp_a[0].weight, f32.attention.qkv.weight, f32.mlp_s[2].weight):
        assert p.grad is not None and p.grad.abs().sum() > 0
    with torch.no_grad():
        kernel_w, _ = f32.point_weights(*args32)
        f32.point_kernel = False
        torch_w, _ = f32.point_weights(*args32)
    torch.testing.assert_close(kernel_w, torch_w, atol=1e-6, rtol=0.0)


def test_weights_follow_parameter_changes() -> None:
    """The kernel's copy of the parameters is taken again after an in-place change or a load."""
    net = _net(HEAD, 16, 8, seed=70).float()
    args = _float(*_inputs(40, 6, 16, 8, seed=71, p_fastest=True))[:5]
    with torch.no_grad():
        before, _ = net.point_weights(*args)
        net.mlp_s[2].weight.mul_(-3.0)
        after, _ = net.point_weights(*args)
        net.point_kernel = False
        expected, _ = net.point_weights(*args)
        net.point_kernel = True
        other = _net(HEAD, 16, 8, seed=72).float()
        net.load_state_dict(other.state_dict())
        loaded, _ = net.point_weights(*args)
        other_w, _ = other.point_weights(*args)
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, expected, atol=1e-6, rtol=0.0)
    torch.testing.assert_close(loaded, other_w, atol=0.0, rtol=0.0)


def test_kernel_refuses_other_sizes() -> None:
    net = _net(HEAD, 16, 8, seed=80).float()
    kw = net.point_kernel_weights()
    rgb, feat, vol, dirs, mask, _ = _float(*_inputs(10, 3, 12, 8, seed=81, p_fastest=True))
    with pytest.raises(ValueError, match="feature_dim 16"):
        fusion_kernel.point_ov_weights(kw, rgb, feat, vol, dirs, mask, None, threads=1)
    rgb, feat, vol, dirs, mask, _ = _float(*_inputs(10, 3, 16, 8, seed=82, p_fastest=True))
    with pytest.raises(ValueError, match="like the features"):
        fusion_kernel.point_ov_weights(kw, rgb[:, :2], feat, vol, dirs, mask, None, threads=1)
    with pytest.raises(ValueError, match="like the features"):
        fusion_kernel.point_ov_weights(kw, rgb, feat, vol, dirs, mask[:, :2], None, threads=1)


def test_shipped_point_head_matches_its_torch_pass() -> None:
    path = ROOT / "checkpoints" / "cpu-small-point-head"
    if not path.with_suffix(".safetensors").exists():
        pytest.skip("checkpoints/cpu-small-point-head not shipped in this tree")
    from mapper.model.point_head import load_point_head

    head, _ = load_point_head(path)
    args = _float(*_inputs(2048, 16, head.feature_dim, head.volume_feature_dim, seed=90, p_fastest=True))[:5]
    with torch.no_grad():
        kernel_w, valid = head.point_weights(*args)
    assert torch.equal(valid, _reference(head, *args)[1])
    _assert_as_accurate(head, kernel_w, *args)
