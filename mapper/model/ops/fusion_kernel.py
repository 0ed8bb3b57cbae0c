"""FusionNet's point mode (OV weights only) as one compiled CPU kernel (numba).

``FusionNet.forward_fast`` with ``query_dirs=None`` (how ``segment_points`` and the map's learned
features weigh a point's views) runs as a chain of small torch ops over (points x views) rows; for
a small network (the distilled point head, widths 8 / 4) those ops cost about the same whatever
the width: each one writes and reads its whole (P*N, C) result
(``benchmarks/speed/point_head_speed.py --kernel-ab`` compares the two). Here every point block's
intermediates stay in small per-block buffers, with the points of a block as the inner,
contiguous, vectorised axis (the samples' own layout, P fastest):

    per block of B points:  mean / var over views -> the per-point part of MLP_a's first layer
    per view:               MLP_a -> + DE [+ RE] -> q, k, v (linear attention, masked keys)
    per view again:         attention output -> LayerNorm -> FFN -> LayerNorm -> MLP_s -> logit
    masked softmax over the views

The same function of the same parameters as ``forward_reference`` (float32, sums reassociated;
``exp`` evaluated by range reduction and a polynomial, within a few ulp), so the weights are as
close to a float64 reference as the float32 torch pass's (tests/mapper/model/ops/test_fusion_kernel.py;
about 1e-7 for the shipped point head). The first call in a process compiles the kernel or loads
it from numba's cache (:func:`warm_up`). The samples and the network's parameters reach the kernel
as two tuples (``inputs``, ``params``), unpacked in :func:`_point_block`.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from mapper.kernels.average_kernel import launch

__all__ = [
    "RANGE_MIN_M", "PointKernelWeights", "default_block", "kernel_applies", "point_ov_weights", "warm_up",
]

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_EXP_MIN = np.float32(-87.0)
_POW2 = np.array([2.0**k for k in range(-127, 1)], np.float32)
"""2^k for k = -127..0 (index k + 127): the scale of ``_exp_neg``'s range reduction; 2^-127 is a
subnormal float32, exact."""
RANGE_MIN_M = 0.05
"""Distances below this (m) read as this in the range encoding (log of a positive number)."""


@numba.njit(fastmath=True, error_model="numpy", inline="always", cache=True)
def _exp_parts(x):  # pragma: no cover - compiled
    """exp(x) for x <= 0 (float32) as (p, k) with exp(x) = p * 2^k: x = k ln2 + r, |r| <= ln2 / 2,
    p = exp(r) by its Taylor series to r^7 (truncation below 3e-9 relative). x below -87 reads as
    -87."""
    x = max(x, _EXP_MIN)
    k = np.floor(x * _LOG2E + np.float32(0.5))
    r = (x - k * _LN2_HI) - k * _LN2_LO
    p = np.float32(1.0 / 5040.0)
    p = p * r + np.float32(1.0 / 720.0)
    p = p * r + np.float32(1.0 / 120.0)
    p = p * r + np.float32(1.0 / 24.0)
    p = p * r + np.float32(1.0 / 6.0)
    p = p * r + np.float32(0.5)
    p = p * r + _F1
    p = p * r + _F1
    return p, k


@numba.njit(fastmath=True, error_model="numpy", inline="always", cache=True)
def _exp_neg(x, pow2):  # pragma: no cover - compiled
    """exp(x) for x <= 0 (float32): :func:`_exp_parts`, 2^k from a table."""
    p, k = _exp_parts(x)
    return p * pow2[np.int64(k) + 127]


@numba.njit(fastmath=True, error_model="numpy", cache=True)
def _linear(W, b, x, out, nb):  # pragma: no cover - compiled
    """out[o, :nb] = b[o] + sum_i W[o, i] x[i, :nb]   (x: (I, B), out: (O, B))."""
    for o in range(W.shape[0]):
        bo = b[o]
        for j in range(nb):
            out[o, j] = bo
        for i in range(W.shape[1]):
            w = W[o, i]
            for j in range(nb):
                out[o, j] += w * x[i, j]


@numba.njit(fastmath=True, error_model="numpy", cache=True)
def _elu_(x, nb, ibuf, pbuf):  # pragma: no cover - compiled
    """x[:, :nb] = elu(x) in place: :func:`_exp_parts`, with 2^k built from its float32 bits
    (``ibuf`` int32, ``pbuf`` float32 scratch of >= nb), so that both loops vectorise."""
    fbuf = ibuf.view(np.float32)
    for o in range(x.shape[0]):
        for j in range(nb):
            p, k = _exp_parts(min(x[o, j], _F0))
            pbuf[j] = p
            ibuf[j] = (np.int32(k) + np.int32(127)) << 23
        for j in range(nb):
            v = x[o, j]
            x[o, j] = v if v > _F0 else pbuf[j] * fbuf[j] - _F1


@numba.njit(fastmath=True, error_model="numpy", cache=True)
def _layer_norm_(y, w, b, eps, nb, mu, var):  # pragma: no cover - compiled
    """y[:, :nb] = LayerNorm over y's rows (the feature axis) with weight w, bias b."""
    D = y.shape[0]
    inv = _F1 / np.float32(D)
    for j in range(nb):
        mu[j] = _F0
        var[j] = _F0
    for d in range(D):
        for j in range(nb):
            mu[j] += y[d, j]
    for j in range(nb):
        mu[j] *= inv
    for d in range(D):
        for j in range(nb):
            c = y[d, j] - mu[j]
            var[j] += c * c
    for j in range(nb):
        var[j] = _F1 / np.sqrt(var[j] * inv + eps)
    for d in range(D):
        wd, bd = w[d], b[d]
        for j in range(nb):
            y[d, j] = (y[d, j] - mu[j]) * var[j] * wd + bd


@numba.njit(fastmath=True, error_model="numpy", cache=True, boundscheck=False)
def _point_block(
    inputs,  # the samples (rgb, feat, vol, dirs, mask, log_range), unpacked below
    params,  # PointKernelWeights.params: the network, unpacked below
    pow2,  # _POW2
    out,  # (P, N) float32 weights
    valid,  # (P,) bool
    p0,  # int: the block's first point
    nb,  # int: its points
    block,  # int: the buffers' size (>= nb)
):  # pragma: no cover - compiled
    """One block of points (``_point_kernel``'s arguments; points p0 .. p0 + nb - 1).

    One long compiled kernel, exempt from the 120-line limit (tests/test_code_size.py): the whole
    network runs here on the block's small buffers (module docstring), its layers written out in
    one function rather than split into calls."""
    (
        rgb,  # (3, N, P) float32
        feat,  # (F, N, P) float32
        vol,  # (Dv, P) float32
        dirs,  # (3, N, P) float32
        mask,  # (N, P) bool
        log_range,  # (N, P) float32 log distances, or (N, 0) without range encoding
    ) = inputs
    (
        w1p, b1,  # (H, 2F + Dv), (H,): MLP_a's first layer, the per-point inputs [mean, var, v]
        w1n,  # (H, 3 + F): the same layer, the per-view inputs [rgb, f]
        w2, b2,  # (A, H), (A,)
        wde, bde,  # (A, 3), (A,)
        wre, bre,  # (A, 1), (A,) (unused without range encoding)
        wq, bq, wk, bk, wv, bv,  # (A, A), (A,) each
        k_extra, v_extra,  # (A,): the extra token's key (after elu + 1) and value
        head,  # (A,) int64: the attention head of each dimension
        wo, bo,  # (A, A), (A,)
        ln1w, ln1b, ln1_eps,  # (A,), (A,), float32: the first LayerNorm
        ln2w, ln2b, ln2_eps,  # the second
        wf1, bf1, wf2, bf2,  # (2A, A), (2A,), (A, 2A), (A,)
        ws1, bs1, ws2, bs2,  # (A, A), (A,), (A,), float32
    ) = params
    Fd, N, P = feat.shape
    Dv = vol.shape[0]
    H = w1n.shape[0]
    A = w2.shape[0]
    F2 = 2 * A
    n_heads = 0
    for d in range(A):
        n_heads = max(n_heads, head[d] + 1)
    use_range = log_range.shape[1] > 0
    cnt = np.zeros(block, np.float32)
    stats = np.zeros((2 * Fd + Dv, block), np.float32)  # [mean, var, v]
    pp = np.empty((H, block), np.float32)
    own = np.empty((3 + Fd, block), np.float32)
    h = np.empty((H, block), np.float32)
    x = np.empty((N, A, block), np.float32)
    q = np.empty((N, A, block), np.float32)
    kk = np.empty((A, block), np.float32)
    vv = np.empty((A, block), np.float32)
    kv = np.zeros((A, A, block), np.float32)
    ksum = np.zeros((A, block), np.float32)
    norm = np.empty((n_heads, block), np.float32)
    y = np.empty((A, block), np.float32)
    t = np.empty((A, block), np.float32)
    z = np.empty((F2, block), np.float32)
    hs = np.empty((A, block), np.float32)
    logit = np.empty((N, block), np.float32)
    mu = np.empty(block, np.float32)
    var = np.empty(block, np.float32)
    ibuf = np.empty(block, np.int32)
    pbuf = np.empty(block, np.float32)
    mf = np.empty((N, block), np.float32)  # the mask as 0 / 1
    # masked mean and population variance of the features over the views
    for n in range(N):
        for j in range(nb):
            mf[n, j] = _F1 if mask[n, p0 + j] else _F0
            cnt[j] += mf[n, j]
    for j in range(nb):
        cnt[j] = _F1 / max(cnt[j], _F1)
    for c in range(Fd):
        for n in range(N):
            for j in range(nb):
                stats[c, j] += feat[c, n, p0 + j] * mf[n, j]
        for j in range(nb):
            stats[c, j] *= cnt[j]
        for n in range(N):
            for j in range(nb):
                d = feat[c, n, p0 + j] - stats[c, j]
                stats[Fd + c, j] += d * d * mf[n, j]
        for j in range(nb):
            stats[Fd + c, j] *= cnt[j]
    for c in range(Dv):
        for j in range(nb):
            stats[2 * Fd + c, j] = vol[c, p0 + j]
    _linear(w1p, b1, stats, pp, nb)
    # per view: MLP_a + DE (+ RE), then the attention's sums over the views
    for n in range(N):
        for j in range(nb):
            own[0, j] = rgb[0, n, p0 + j]
            own[1, j] = rgb[1, n, p0 + j]
            own[2, j] = rgb[2, n, p0 + j]
        for c in range(Fd):
            for j in range(nb):
                own[3 + c, j] = feat[c, n, p0 + j]
        for o in range(H):
            for j in range(nb):
                h[o, j] = pp[o, j]
            for i in range(3 + Fd):
                w = w1n[o, i]
                for j in range(nb):
                    h[o, j] += w * own[i, j]
        _elu_(h, nb, ibuf, pbuf)
        xn = x[n]
        _linear(w2, b2, h, xn, nb)
        _elu_(xn, nb, ibuf, pbuf)
        for a in range(A):
            w0, w1, w2_, bb = wde[a, 0], wde[a, 1], wde[a, 2], bde[a]
            for j in range(nb):
                xn[a, j] += bb + w0 * dirs[0, n, p0 + j] + w1 * dirs[1, n, p0 + j] + w2_ * dirs[2, n, p0 + j]
            if use_range:
                wr, br = wre[a, 0], bre[a]
                for j in range(nb):
                    xn[a, j] += br + wr * log_range[n, p0 + j]
        qn = q[n]
        _linear(wq, bq, xn, qn, nb)
        _elu_(qn, nb, ibuf, pbuf)
        for a in range(A):
            for j in range(nb):
                qn[a, j] += _F1
        _linear(wk, bk, xn, kk, nb)
        _elu_(kk, nb, ibuf, pbuf)
        _linear(wv, bv, xn, vv, nb)
        for a in range(A):
            for j in range(nb):
                kk[a, j] = (kk[a, j] + _F1) * mf[n, j]
                ksum[a, j] += kk[a, j]
        for d in range(A):
            for e in range(A):
                if head[d] == head[e]:
                    for j in range(nb):
                        kv[d, e, j] += kk[d, j] * vv[e, j]
    # the extra token: a key and value added to every point's sums
    for d in range(A):
        for j in range(nb):
            ksum[d, j] += k_extra[d]
        for e in range(A):
            if head[d] == head[e]:
                c = k_extra[d] * v_extra[e]
                for j in range(nb):
                    kv[d, e, j] += c
    # per view: attention output, residual, LayerNorm, FFN, LayerNorm, MLP_s
    for n in range(N):
        qn = q[n]
        xn = x[n]
        for g in range(n_heads):
            for j in range(nb):
                norm[g, j] = _F0
        for d in range(A):
            g = head[d]
            for j in range(nb):
                norm[g, j] += qn[d, j] * ksum[d, j]
        for g in range(n_heads):
            for j in range(nb):
                norm[g, j] = _F1 / max(norm[g, j], np.float32(1e-6))
        for e in range(A):
            for j in range(nb):
                t[e, j] = _F0
            for d in range(A):
                if head[d] == head[e]:
                    for j in range(nb):
                        t[e, j] += qn[d, j] * kv[d, e, j]
            g = head[e]
            for j in range(nb):
                t[e, j] *= norm[g, j]
        _linear(wo, bo, t, y, nb)
        for a in range(A):
            for j in range(nb):
                y[a, j] += xn[a, j]
        _layer_norm_(y, ln1w, ln1b, ln1_eps, nb, mu, var)
        _linear(wf1, bf1, y, z, nb)
        _elu_(z, nb, ibuf, pbuf)
        for a in range(A):
            bb = bf2[a]
            for j in range(nb):
                y[a, j] += bb
            for i in range(F2):
                w = wf2[a, i]
                for j in range(nb):
                    y[a, j] += w * z[i, j]
        _layer_norm_(y, ln2w, ln2b, ln2_eps, nb, mu, var)
        _linear(ws1, bs1, y, hs, nb)
        _elu_(hs, nb, ibuf, pbuf)
        for j in range(nb):
            logit[n, j] = bs2
        for a in range(A):
            w = ws2[a]
            for j in range(nb):
                logit[n, j] += w * hs[a, j]
    # masked softmax over the views
    for j in range(nb):
        p = p0 + j
        peak = np.float32(-np.inf)
        any_view = False
        for n in range(N):
            if mask[n, p]:
                any_view = True
                peak = max(peak, logit[n, j])
        total = _F0
        for n in range(N):
            e = _exp_neg(logit[n, j] - peak, pow2) if mask[n, p] else _F0
            out[p, n] = e
            total += e
        valid[p] = any_view
        if any_view:
            inv = _F1 / total
            for n in range(N):
                out[p, n] *= inv




@numba.njit(parallel=True, fastmath=True, error_model="numpy", cache=True, boundscheck=False)
def _point_kernel(
    inputs,  # the samples (see _point_block)
    params,  # PointKernelWeights.params (see _point_block)
    pow2,  # _POW2
    out,  # (P, N) float32 weights
    valid,  # (P,) bool
    block,  # int: points per parallel task
):  # pragma: no cover - compiled
    P = out.shape[0]
    n_blocks = (P + block - 1) // block
    for blk in numba.prange(n_blocks):
        p0 = blk * block
        _point_block(inputs, params, pow2, out, valid, p0, min(P, p0 + block) - p0, block)


def default_block(n_views: int, attention_dim: int) -> int:
    """Points per parallel task: 256 (the fastest of 32-256 for the point head, 16 views, on two
    cores; ``benchmarks/speed/point_head_speed.py``), fewer where the per-view buffers ((N, A, block)
    floats, twice) would pass about 128 KiB."""
    block = 256
    while block > 32 and 2 * n_views * attention_dim * block * 4 > 128 * 1024:
        block //= 2
    return block


class PointKernelWeights:
    """A FusionNet's parameters laid out for :func:`_point_kernel` (float32 numpy): ``params`` in the
    order :func:`_point_block` unpacks them (``FusionNet.point_kernel_weights`` makes them from a
    network)."""

    def __init__(
        self, params: tuple[Any, ...], feature_dim: int, volume_feature_dim: int, range_encoding: bool
    ) -> None:
        self.params = params
        self.feature_dim = feature_dim
        self.volume_feature_dim = volume_feature_dim
        self.attention_dim = int(params[3].shape[0])  # MLP_a's second layer: (A, H)
        self.range_encoding = range_encoding

    @classmethod
    def zeros(
        cls, feature_dim: int, volume_feature_dim: int, hidden_dim: int, attention_dim: int
    ) -> PointKernelWeights:
        """A network of zeros of these sizes, one head (the kernel's argument types, for warm-up)."""
        H, A = hidden_dim, attention_dim

        def z(*shape: int) -> np.ndarray:
            return np.zeros(shape, np.float32)

        eps = np.float32(1e-5)
        params = (
            z(H, 2 * feature_dim + volume_feature_dim), z(H), z(H, 3 + feature_dim), z(A, H), z(A),
            z(A, 3), z(A),
            z(A, 1), z(A), z(A, A), z(A), z(A, A), z(A), z(A, A), z(A), z(A), z(A), np.zeros(A, np.int64),
            z(A, A), z(A), z(A), z(A), eps, z(A), z(A), eps, z(2 * A, A), z(2 * A), z(A, 2 * A), z(A),
            z(A, A), z(A), z(A), np.float32(0.0),
        )
        return cls(params, feature_dim, volume_feature_dim, False)


def kernel_applies(*tensors: Tensor) -> bool:
    """The compiled kernel serves this call: every tensor on the CPU and no gradient recorded."""
    return not torch.is_grad_enabled() and all(t.device.type == "cpu" for t in tensors)


def _cnp(t: Tensor) -> np.ndarray:
    """(P, N, C) samples -> (C, N, P) contiguous float32 numpy (no copy when they are already
    laid out P fastest, as ``sample_views_indexed`` returns them)."""
    return np.ascontiguousarray(t.permute(2, 1, 0).to(torch.float32).numpy())


def point_ov_weights(
    weights: PointKernelWeights,
    rgb: Tensor,  # (P, N, 3)
    features: Tensor,  # (P, N, F)
    volume_features: Tensor,  # (P, Dv)
    source_dirs: Tensor,  # (P, N, 3)
    mask: Tensor,  # (P, N) bool
    source_range: Tensor | None,  # (P, N) distances (m); needed with range encoding
    *,
    threads: int,
    block: int = 0,
) -> tuple[Tensor, Tensor]:  # (P, N) float32 weights, (P,) bool valid
    """FusionNet's OV weights (point mode) for P points over N views, as ``forward_fast`` with
    ``query_dirs=None`` computes them (see the module docstring). ``block``: points per parallel
    task (0: :func:`default_block`)."""
    P, N, Fd = features.shape
    if rgb.shape != (P, N, 3) or source_dirs.shape != (P, N, 3) or mask.shape != (P, N):
        raise ValueError(
            f"point kernel: rgb {tuple(rgb.shape)}, source_dirs {tuple(source_dirs.shape)} and mask "
            f"{tuple(mask.shape)} must be ({P}, {N}, 3), ({P}, {N}, 3) and ({P}, {N}) like the features"
        )
    if Fd != weights.feature_dim or volume_features.shape != (P, weights.volume_feature_dim):
        raise ValueError(
            f"point kernel: features {tuple(features.shape)} / volume features "
            f"{tuple(volume_features.shape)} do not fit a network of feature_dim {weights.feature_dim}, "
            f"volume_feature_dim {weights.volume_feature_dim}"
        )
    if weights.range_encoding:
        if source_range is None or tuple(source_range.shape) != (P, N):
            raise ValueError("this FusionNet has range_encoding: pass source_range (P, N) distances (m)")
        log_range = np.ascontiguousarray(
            source_range.to(torch.float32).clamp_min(RANGE_MIN_M).log().T.numpy()
        )
    else:
        log_range = np.zeros((N, 0), np.float32)
    out = np.empty((P, N), np.float32)
    valid = np.empty(P, np.bool_)
    block = block or default_block(N, weights.attention_dim)
    inputs = (
        _cnp(rgb), _cnp(features), np.ascontiguousarray(volume_features.T.to(torch.float32).numpy()),
        _cnp(source_dirs), np.ascontiguousarray(mask.T.numpy()), log_range,
    )
    if not _point_block.signatures:  # compile the block outside the launch lock (about 10 s, once)
        _point_block(inputs, weights.params, _POW2, out, valid, 0, 0, 1)
    if P:
        with launch(threads):
            _point_kernel(inputs, weights.params, _POW2, out, valid, int(block))
    return torch.from_numpy(out), torch.from_numpy(valid)


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now, on a one-point problem."""
    with torch.no_grad():
        point_ov_weights(PointKernelWeights.zeros(2, 1, 2, 2), torch.zeros(1, 1, 3), torch.zeros(1, 1, 2),
                         torch.zeros(1, 1), torch.zeros(1, 1, 3), torch.ones(1, 1, dtype=torch.bool), None,
                         threads=1)
