"""FusionNet's inference pass (``forward_fast``) equals the reference pass."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from mapper.model.config import FusionConfig, get_preset
from mapper.model.fusion import FusionNet, FusionOutputs

ROOT = Path(__file__).resolve().parents[3]


def _net(cfg: FusionConfig, feature_dim: int, volume_dim: int, seed: int) -> FusionNet:
    """A FusionNet with every parameter random (the extra token and biases non-zero too)."""
    torch.manual_seed(seed)
    net = FusionNet(feature_dim, volume_dim, cfg)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 0.4)
    return net.double().eval()


def _inputs(
    P: int, N: int, feature_dim: int, volume_dim: int, seed: int, *, p_fastest: bool, see: float = 0.6
) -> tuple[torch.Tensor, ...]:
    """(rgb, features, volume, source_dirs, mask, query_dirs), float64; with ``p_fastest`` the
    per-view tensors are (P, N, C) views of (C, N, P) storage (``sample_views_indexed``)."""
    g = torch.Generator().manual_seed(seed)

    def per_view(c: int) -> torch.Tensor:
        if p_fastest:
            return torch.randn(c, N, P, generator=g, dtype=torch.float64).permute(2, 1, 0)
        return torch.randn(P, N, c, generator=g, dtype=torch.float64)

    rgb = per_view(3).sigmoid()
    features = per_view(feature_dim) * 2.0
    volume = torch.randn(P, volume_dim, generator=g, dtype=torch.float64)
    dirs = F.normalize(per_view(3), dim=-1)
    mask = torch.rand(P, N, generator=g) < see
    mask[: max(1, P // 10)] = False  # points no view sees
    if P > 2:
        mask[-1] = True  # a point every view sees
    query = F.normalize(torch.randn(P, 3, generator=g, dtype=torch.float64), dim=-1)
    query[0] = -dirs[0, 0]  # query opposite a source direction (RDE at its degenerate end)
    return rgb, features, volume, dirs, mask, query


def _assert_same(a: FusionOutputs, b: FusionOutputs, atol: float) -> None:
    assert torch.equal(a.valid, b.valid)
    assert b.ov_weights.is_contiguous() and b.x_att.is_contiguous()  # as the reference's
    torch.testing.assert_close(b.ov_weights, a.ov_weights, atol=atol, rtol=0.0)
    torch.testing.assert_close(b.x_att, a.x_att, atol=atol, rtol=0.0)
    if a.color_weights is None:
        assert b.color_weights is None
    else:
        assert b.color_weights is not None
        torch.testing.assert_close(b.color_weights, a.color_weights, atol=atol, rtol=0.0)


SMALL = get_preset("cpu-small")
PAPER = get_preset("paper")


@pytest.mark.parametrize("p_fastest", [False, True])
@pytest.mark.parametrize("with_query", [False, True])
@pytest.mark.parametrize(
    ("preset", "N"),
    [(SMALL, 8), (SMALL, 1), (SMALL, 3), (PAPER, 5)],
    ids=["small8", "small1", "small3", "paper5"],
)
def test_fast_equals_reference_float64(preset, N: int, with_query: bool, p_fastest: bool) -> None:
    fd, dv = preset.encoder.feature_dim, preset.volume.volume_feature_dim
    net = _net(preset.fusion, fd, dv, seed=N)
    rgb, feat, vol, dirs, mask, query = _inputs(257, N, fd, dv, seed=10 + N, p_fastest=p_fastest)
    q = query if with_query else None
    with torch.no_grad():
        ref = net.forward_reference(rgb, feat, vol, dirs, mask, q)
        fast = net.forward_fast(rgb, feat, vol, dirs, mask, q)
    _assert_same(ref, fast, atol=1e-10)
    # masked entries are exactly 0 and each seen point's weights sum to 1 (as the reference)
    assert torch.all(fast.ov_weights[~mask] == 0)
    assert not fast.valid[: 257 // 10].any()
    sums = fast.ov_weights.sum(-1)
    torch.testing.assert_close(sums[fast.valid], torch.ones_like(sums[fast.valid]))
    assert torch.all(sums[~fast.valid] == 0)


def test_all_views_masked_and_single_point() -> None:
    net = _net(SMALL.fusion, 16, 8, seed=3)
    rgb, feat, vol, dirs, mask, query = _inputs(7, 4, 16, 8, seed=4, p_fastest=False)
    mask[:] = False
    with torch.no_grad():
        fast = net.forward_fast(rgb, feat, vol, dirs, mask, query)
        ref = net.forward_reference(rgb, feat, vol, dirs, mask, query)
        _assert_same(ref, fast, atol=1e-10)
        assert not fast.valid.any() and torch.isfinite(fast.x_att).all()
        assert fast.color_weights is not None and torch.all(fast.color_weights == 0)
        one = net.forward_fast(rgb[:1], feat[:1], vol[:1], dirs[:1], mask[:1] | True, query[:1])
        ref_one = net.forward_reference(rgb[:1], feat[:1], vol[:1], dirs[:1], mask[:1] | True, query[:1])
        _assert_same(ref_one, one, atol=1e-10)
        empty = net.forward_fast(rgb[:0], feat[:0], vol[:0], dirs[:0], mask[:0], query[:0])
        assert empty.ov_weights.shape == (0, 4) and empty.x_att.shape == (0, 4, SMALL.fusion.attention_dim)


def test_forward_dispatch_and_inputs_untouched() -> None:
    net = _net(SMALL.fusion, 16, 8, seed=5)
    args = _inputs(64, 8, 16, 8, seed=6, p_fastest=True)
    copies = [a.clone() for a in args]
    with torch.no_grad():
        ref = net.forward_reference(*args)
        fast = net(*args)  # no autograd: the fast pass
        _assert_same(ref, fast, atol=1e-10)
    with torch.inference_mode():
        _assert_same(ref, net(*args), atol=1e-10)
    for a, c in zip(args, copies, strict=True):
        assert torch.equal(a, c)  # the in-place steps touch only the pass's own tensors
    net.fast_inference = False
    with torch.no_grad():
        assert torch.equal(net(*args).x_att, ref.x_att)  # flag off: the reference, bit for bit


def test_training_mode_keeps_reference_and_gradients() -> None:
    net = _net(SMALL.fusion, 16, 8, seed=7).train()
    args = _inputs(32, 8, 16, 8, seed=8, p_fastest=False)
    out = net(*args)
    with torch.no_grad():
        ref = net.forward_reference(*args)
    assert torch.equal(out.x_att, ref.x_att)
    assert out.color_weights is not None
    (out.color_weights.sum() + (out.ov_weights * torch.arange(8.0, dtype=torch.float64)).sum()).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_shipped_checkpoint_float32() -> None:
    path = ROOT / "checkpoints" / "cpu-small"
    if not path.with_suffix(".safetensors").exists():
        pytest.skip("checkpoints/cpu-small not shipped in this tree")
    from mapper.model.checkpoint import load_model

    model, _ = load_model(path)
    net = model.fusion.eval()
    cfg = model.cfg
    fd, dv, N = cfg.encoder.feature_dim, cfg.volume.volume_feature_dim, cfg.num_source_views
    inputs = _inputs(2048, N, fd, dv, seed=9, p_fastest=True)
    rgb, feat, vol, dirs, mask, query = (a.float() if a.is_floating_point() else a for a in inputs)
    with torch.no_grad():
        for q in (query, None):
            ref = net.forward_reference(rgb, feat, vol, dirs, mask, q)
            _assert_same(ref, net(rgb, feat, vol, dirs, mask, q), atol=1e-5)


# ---- the range encoding (each view's camera-to-point distance as a blend input) ------------------
RANGED = replace(SMALL.fusion, range_encoding=True)


def _ranges(P: int, N: int, seed: int, *, p_fastest: bool) -> torch.Tensor:
    """(P, N) distances in [0, 8) m, some at 0 (clamped to RANGE_MIN_M inside)."""
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(N, P, generator=g, dtype=torch.float64) * 8.0
    r[0, :3] = 0.0
    return r.T if p_fastest else r.T.contiguous()


@pytest.mark.parametrize("p_fastest", [False, True])
@pytest.mark.parametrize("with_query", [False, True])
def test_range_encoding_fast_equals_reference(with_query: bool, p_fastest: bool) -> None:
    net = _net(RANGED, 16, 8, seed=11)  # RE random and non-zero here
    rgb, feat, vol, dirs, mask, query = _inputs(129, 6, 16, 8, seed=12, p_fastest=p_fastest)
    r = _ranges(129, 6, seed=13, p_fastest=p_fastest)
    q = query if with_query else None
    with torch.no_grad():
        ref = net.forward_reference(rgb, feat, vol, dirs, mask, q, r)
        _assert_same(ref, net.forward_fast(rgb, feat, vol, dirs, mask, q, r), atol=1e-10)
        # the distances change the weights (a different input), and only through RE
        other = net.forward_reference(rgb, feat, vol, dirs, mask, q, r * 2.0)
    assert not torch.allclose(other.ov_weights, ref.ov_weights)


def test_range_encoding_starts_as_the_blend_without_it() -> None:
    """A fresh RE is zero: the same weights as a net without it that shares every other parameter."""
    plain = _net(SMALL.fusion, 16, 8, seed=14)
    torch.manual_seed(0)
    ranged = FusionNet(16, 8, RANGED).double().eval()
    assert ranged.range_encoding is not None
    assert torch.all(ranged.range_encoding.weight == 0) and torch.all(ranged.range_encoding.bias == 0)
    missing, unexpected = ranged.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == ["range_encoding.bias", "range_encoding.weight"] and not unexpected
    args = _inputs(64, 5, 16, 8, seed=15, p_fastest=False)
    r = _ranges(64, 5, seed=16, p_fastest=False)
    with torch.no_grad():
        _assert_same(plain(*args), ranged(*args, r), atol=1e-12)


def test_range_encoding_needs_ranges() -> None:
    net = _net(RANGED, 16, 8, seed=17)
    args = _inputs(10, 3, 16, 8, seed=18, p_fastest=False)
    for fwd in (net.forward_reference, net.forward_fast):
        with torch.no_grad(), pytest.raises(ValueError, match="range_encoding: pass source_range"):
            fwd(*args)
        with torch.no_grad(), pytest.raises(ValueError, match="source_range shape"):
            fwd(*args, torch.ones(10, 4, dtype=torch.float64))
    # a net without it ignores them
    plain = _net(SMALL.fusion, 16, 8, seed=19)
    with torch.no_grad():
        _assert_same(plain(*args), plain(*args, torch.ones(10, 3, dtype=torch.float64)), atol=0.0)
