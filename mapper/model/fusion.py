"""FusionNet: learned blending of source views, plus the density MLP and the Distill head.

For P points and N source views (a view that does not see a point is masked out):

    x^n   = [mean_n f, var_n f, v, rgb^n, f^n]        cross-view statistics + volume + own view
    x^n   = MLP_a(x^n) + DE(d^n) [+ RE(log r^n)]       d^n: unit direction source camera -> point,
                                                      r^n: its distance (``range_encoding``)
    x_att = CVA(x^n)                                  linear attention over views + extra token
    w_c^n = MLP_c(x_att^n + RDE(d_q, d^n))            colour weights, depend on the query ray
    w_s^n = MLP_s(x_att^n)                            OV weights, source-view agnostic
    c = sum softmax(w_c)^n rgb^n;  s = sum softmax(w_s)^n f_ov^n   (masked softmax over views)

RDE is the IBRNet relative direction ``[unit(d_q - d^n), d_q . d^n]``. A point no view sees gets
all-zero weights and ``valid = False`` (never NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapper.model.config import FusionConfig
from mapper.model.ops.fusion_kernel import RANGE_MIN_M, PointKernelWeights, kernel_applies, point_ov_weights
from mapper.model.ops.geometry import bilinear_corners

__all__ = [
    "CrossViewAttention",
    "DensityMLP",
    "DistillHead",
    "FusionNet",
    "FusionOutputs",
    "blend",
    "blend_from_maps",
    "cosines_from_maps",
    "masked_mean_var",
    "masked_softmax",
]


def _at_least_float32(x: Tensor) -> Tensor:
    return x.float() if x.dtype in (torch.float16, torch.bfloat16) else x


def masked_softmax(logits: Tensor, mask: Tensor, dim: int = -1) -> tuple[Tensor, Tensor]:
    """Softmax over the entries where ``mask`` is True.

    Args:
        logits: (..., N, ...); mask: bool, same shape.

    Returns:
        weights: float32 or float64 (same shape), 0 where masked; all 0 where every entry is
            masked.
        valid: bool (logits.shape without ``dim``), False where every entry is masked.
    """
    x = _at_least_float32(logits)
    very_negative = torch.finfo(x.dtype).min
    x = x.masked_fill(~mask, very_negative)
    peak = x.amax(dim=dim, keepdim=True).detach()
    e = torch.exp((x - peak).clamp(max=0.0)) * mask.to(x.dtype)
    total = e.sum(dim=dim, keepdim=True)
    weights = e / total.clamp_min(torch.finfo(x.dtype).tiny)
    return weights, mask.any(dim=dim)


def masked_mean_var(values: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Mean and population variance over views.

    Args:
        values: (P, N, C); mask: (P, N) bool.

    Returns:
        mean, var: (P, C) over the unmasked views (0 where none).
    """
    m = mask.to(values.dtype).unsqueeze(-1)
    count = m.sum(dim=1).clamp_min(1.0)
    mean = (values * m).sum(dim=1) / count
    var = (((values - mean.unsqueeze(1)) ** 2) * m).sum(dim=1) / count
    return mean, var


def blend(weights: Tensor, values: Tensor) -> Tensor:
    """(P, N) weights, (P, N, C) values -> (P, C) ``sum_n w^n values^n``.

    The fast path depends on the memory layout of ``values``:

    * P varies fastest (a view of ``grid_sample``'s (N, C, P) output, how ``GovNeSF.sample_views``
      hands the OV samples over): N fused multiply-adds over contiguous (C, P) slices, about 38x
      faster than ``einsum`` on that layout for 4096 x 8 x 384 on the CPU (2.1 vs 80 ms);
    * otherwise, and whenever autograd records (training), a batched matrix product (``einsum``;
      no (P, N, C) temporary). Training keeps this one path so that a training run is
      bit-for-bit what it was when the committed checkpoints were made (docs/how-to/train.md).
    """
    w = weights.to(values.dtype)
    recording = torch.is_grad_enabled() and (w.requires_grad or values.requires_grad)
    if (
        not recording
        and values.dim() == 3
        and values.shape[0] > 1
        and values.stride(0) == 1
        and values.shape[1] > 0
    ):
        per_view = values.permute(1, 2, 0)  # (N, C, P), each (C, P) slice contiguous
        w_t = w.T.unsqueeze(1)  # (N, 1, P)
        out = per_view[0] * w_t[0]
        for n in range(1, per_view.shape[0]):
            out = torch.addcmul(out, per_view[n], w_t[n])
        return out.T
    return torch.einsum("pn,pnc->pc", w, values)


def blend_from_maps(
    table: Tensor,  # (M * h * w, C) the views' maps, channel-last, view-major
    map_wh: tuple[int, int],  # (w, h) of every map
    view_idx: Tensor,  # (P, N) or (N,) long: the view (0..M-1) behind each slot
    uv: Tensor,  # (P, N, 2) pixel coordinates in the maps' resolution
    weights: Tensor,  # (P, N) blending weights (0 for masked slots)
) -> Tensor:  # (P, C)
    """``blend(weights, values)`` where ``values[p, n]`` is the bilinear sample of view
    ``view_idx[p, n]``'s map at ``uv[p, n]`` (``sample_bilinear``), without materialising the
    (P, N, C) samples: one ``embedding_bag`` over the taps of the slots with a non-zero weight.

    Inference only (no autograd through ``table``'s rows is needed, though it is supported).
    Equal to sampling then blending up to float rounding (tests/mapper/model/test_blend_from_maps.py).
    On the CPU in float32 without autograd it runs as one compiled kernel
    (:func:`mapper.kernels.average_kernel.blend_kernel`: the same taps, no (P, N, 4) arrays).
    """
    w, h = map_wh
    P, N = weights.shape
    check = table.shape[0] % (w * h) == 0 and uv.shape == (P, N, 2)
    if not check:
        raise ValueError(
            f"blend_from_maps: table {tuple(table.shape)} is not M x {h} x {w} rows, or uv "
            f"{tuple(uv.shape)} is not ({P}, {N}, 2)"
        )
    view_idx = view_idx.expand(P, N) if view_idx.dim() == 1 else view_idx
    if _blend_kernel_applies(table, uv, weights):
        from mapper.kernels.average_kernel import blend_kernel

        return torch.from_numpy(blend_kernel(table.numpy(), (w, h), view_idx.numpy(), uv.numpy(),
                                             weights.to(torch.float32).numpy(),
                                             threads=torch.get_num_threads()))
    index, tap = bilinear_corners(uv, w, h)  # (P, N, 4)
    index = index + (view_idx * (w * h)).unsqueeze(-1)
    tap_w = (weights.to(tap.dtype).unsqueeze(-1) * tap).reshape(P, N * 4)
    index = index.reshape(P, N * 4)
    keep = tap_w != 0
    counts = keep.sum(dim=1)
    offsets = torch.cumsum(counts, 0) - counts
    return F.embedding_bag(
        index[keep], table, offsets, mode="sum", per_sample_weights=tap_w[keep].to(table.dtype)
    )


def cosines_from_maps(
    table: Tensor,  # (M * h * w, C) the views' maps, channel-last, view-major
    map_wh: tuple[int, int],  # (w, h) of every map
    view_idx: Tensor,  # (P, N) or (N,) long
    uv: Tensor,  # (P, N, 2) pixel coordinates in the maps' resolution
    weights: Tensor,  # (P, N) blending weights
    texts: Tensor,  # (T, C)
) -> Tensor:  # (P, T)
    """``F.normalize(blend_from_maps(...), dim=-1) @ texts.T``: each text's cosine with each point's
    blend (0 where the blend is 0). On the CPU in float32 without autograd one compiled kernel
    (:func:`mapper.kernels.average_kernel.blend_kernel` with ``texts``) keeps each blend in a C-vector
    while its cosines are taken, so the (P, C) blends are never written; otherwise the two steps."""
    P, N = weights.shape
    if _blend_kernel_applies(table, uv, weights) and texts.device.type == "cpu" and not texts.requires_grad:
        from mapper.kernels.average_kernel import blend_kernel

        w, h = map_wh
        if table.shape[0] % (w * h) or uv.shape != (P, N, 2) or texts.shape[-1] != table.shape[1]:
            raise ValueError(
                f"cosines_from_maps: table {tuple(table.shape)} is not M x {h} x {w} rows of the texts' "
                f"{texts.shape[-1]} channels, or uv {tuple(uv.shape)} is not ({P}, {N}, 2)"
            )
        view_idx = view_idx.expand(P, N) if view_idx.dim() == 1 else view_idx
        n_maps = table.shape[0] // (w * h)
        if view_idx.numel() and not (0 <= int(view_idx.min()) and int(view_idx.max()) < n_maps):
            raise ValueError(f"cosines_from_maps: view_idx must index the {n_maps} maps")
        return torch.from_numpy(blend_kernel(
            table.numpy(), (w, h), view_idx.numpy(), uv.numpy(), weights.to(torch.float32).numpy(),
            threads=torch.get_num_threads(), texts=texts.to(torch.float32).numpy(),
        ))
    blended = blend_from_maps(table, map_wh, view_idx, uv, weights)
    return F.normalize(blended, dim=-1) @ texts.to(blended.dtype).T


def _blend_kernel_applies(table: Tensor, uv: Tensor, weights: Tensor) -> bool:
    """``blend_from_maps`` takes the compiled CPU kernel: every tensor on the CPU, float32 table and
    coordinates, and no gradient to record."""
    on_cpu = table.device.type == uv.device.type == weights.device.type == "cpu"
    grad = torch.is_grad_enabled() and (table.requires_grad or uv.requires_grad or weights.requires_grad)
    return on_cpu and not grad and table.dtype == uv.dtype == torch.float32 and weights.is_floating_point()


class CrossViewAttention(nn.Module):
    """One linear-attention layer across views with a learnable extra token.

    Linear attention (phi = elu + 1 > 0) with masked views removed from the keys; the extra
    token is always a key, so the normaliser is strictly positive even when every view is masked.
    """

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.extra_token = nn.Parameter(torch.zeros(dim))
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)
        self.norm1 = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(dim, 2 * dim), nn.ELU(), nn.Linear(2 * dim, dim))
        self.norm2 = nn.LayerNorm(dim)

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:
        """x: (P, N, D); mask: (P, N) bool -> (P, N, D)."""
        P, N, D = x.shape
        tokens = torch.cat([self.extra_token.to(x.dtype).expand(P, 1, D), x], dim=1)  # (P, N+1, D)
        key_mask = torch.cat([mask.new_ones(P, 1), mask], dim=1).to(x.dtype)  # (P, N+1)
        q, k, v = self.qkv(tokens).reshape(P, N + 1, 3, self.num_heads, D // self.num_heads).unbind(2)
        q = F.elu(q) + 1.0
        k = (F.elu(k) + 1.0) * key_mask[..., None, None]
        kv = torch.einsum("pnhd,pnhe->phde", k, v)
        normaliser = torch.einsum("pnhd,phd->pnh", q, k.sum(dim=1)).clamp_min(1e-6)
        att = torch.einsum("pnhd,phde->pnhe", q, kv) / normaliser.unsqueeze(-1)
        y = self.norm1(tokens + self.out(att.reshape(P, N + 1, D)))
        y = self.norm2(y + self.ffn(y))
        return y[:, 1:]


def _masked_mean_var_fast(values: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """``masked_mean_var`` (same formula) reduced over views in the (C, N, P) order, where the
    inputs of ``GovNeSF.sample_views_indexed`` are contiguous (P fastest): values (P, N, C),
    mask (P, N) -> mean, var (P, C) (views of (C, P) tensors). Other layouts: ``masked_mean_var``."""
    if values.stride(0) != 1 or values.shape[0] <= 1:
        return masked_mean_var(values, mask)
    per_view = values.permute(2, 1, 0)  # (C, N, P)
    m = mask.T.to(values.dtype)  # (N, P)
    count = m.sum(dim=0).clamp_min(1.0)  # (P,)
    mean = (per_view * m).sum(dim=1) / count  # (C, P)
    var = ((per_view - mean.unsqueeze(1)).square_() * m).sum(dim=1) / count
    return mean.T, var.T


def _layer_norm_(x: Tensor, norm: nn.LayerNorm) -> Tensor:
    """``norm(x)`` for (R, D) x (a new tensor) in separate vectorised steps, the same formula;
    faster on the CPU than the fused kernel for short rows (D = 16: 0.50 vs 0.78 ms, 32768 rows)."""
    centred = x - x.mean(dim=-1, keepdim=True)
    var = (centred * centred).mean(dim=-1, keepdim=True)
    return centred.mul_(torch.rsqrt(var.add_(norm.eps))).mul_(norm.weight).add_(norm.bias)


def _mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ELU(), nn.Linear(hidden, out_dim))


@dataclass
class FusionOutputs:
    """Per-point blending weights over N source views."""

    color_weights: Tensor | None
    """(P, N) softmax weights for colour (None in point mode, without a query direction)."""
    ov_weights: Tensor
    """(P, N) softmax weights for OV features (source-view agnostic)."""
    valid: Tensor
    """(P,) bool: at least one view sees the point."""
    x_att: Tensor
    """(P, N, A) per-view features after cross-view attention."""


class FusionNet(nn.Module):
    """Cross-view attention blending (see module docstring)."""

    def __init__(self, feature_dim: int, volume_feature_dim: int, cfg: FusionConfig) -> None:
        super().__init__()
        self.feature_dim = feature_dim
        self.volume_feature_dim = volume_feature_dim
        a = cfg.attention_dim
        in_dim = 3 * feature_dim + volume_feature_dim + 3
        self.mlp_a = nn.Sequential(
            nn.Linear(in_dim, cfg.hidden_dim), nn.ELU(), nn.Linear(cfg.hidden_dim, a), nn.ELU()
        )
        self.dir_encoding = nn.Linear(3, a)  # DE(d^n)
        self.range_encoding: nn.Linear | None = None
        if cfg.range_encoding:  # RE(log r^n), zero at first: the blend starts as without it
            self.range_encoding = nn.Linear(1, a)
            nn.init.zeros_(self.range_encoding.weight)
            nn.init.zeros_(self.range_encoding.bias)
        self.attention = CrossViewAttention(a, cfg.num_heads)
        self.rel_dir_encoding = nn.Linear(4, a)  # RDE(d_q, d^n)
        self.mlp_c = _mlp(a, a, 1)
        self.mlp_s = _mlp(a, a, 1)
        self.fast_inference = True
        """Use ``forward_fast`` when autograd does not record (no parameters, not saved)."""
        self.point_kernel = True
        """Let :meth:`point_weights` run the compiled CPU kernel where it applies (with
        ``fast_inference``; off: ``forward_fast``, for comparisons)."""
        self._kernel_weights: tuple[tuple[tuple[int, int], ...], PointKernelWeights] | None = None

    def forward(
        self,
        rgb: Tensor,
        features: Tensor,
        volume_features: Tensor,
        source_dirs: Tensor,
        mask: Tensor,
        query_dirs: Tensor | None,
        source_range: Tensor | None = None,
    ) -> FusionOutputs:
        """Blending weights.

        Args:
            rgb: (P, N, 3) colours sampled in each source view.
            features: (P, N, F) 2D features sampled in each source view.
            volume_features: (P, Dv) volume feature v at each point.
            source_dirs: (P, N, 3) unit directions from each source camera to the point.
            mask: (P, N) bool, the view sees the point (and passes depth masking).
            query_dirs: (P, 3) unit query-ray directions, or None (point mode: OV weights only).
            source_range: (P, N) distances (m) from each source camera to the point; needed (and
                only used) with ``range_encoding``.

        Without autograd recording (``torch.no_grad`` / ``inference_mode``, how rendering and
        ``segment_points`` call it), outside autocast and with ``fast_inference`` set, this runs
        ``forward_fast``: the same function of the same parameters, equal up to float round-off
        (tests/mapper/model/test_fusion_inference.py). Training (and autocast) runs ``forward_reference``.
        """
        autocast = torch.is_autocast_enabled(rgb.device.type)
        args = (rgb, features, volume_features, source_dirs, mask, query_dirs, source_range)
        if self.fast_inference and not torch.is_grad_enabled() and not autocast:
            return self.forward_fast(*args)
        return self.forward_reference(*args)

    def point_weights(
        self,
        rgb: Tensor,
        features: Tensor,
        volume_features: Tensor,
        source_dirs: Tensor,
        mask: Tensor,
        source_range: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Point mode, OV weights only: ``forward(..., query_dirs=None)``'s ``(ov_weights, valid)``
        (arguments as ``forward``; no ``x_att``).

        On the CPU in float32 without autograd (with ``fast_inference`` and ``point_kernel``) this
        runs the compiled kernel :func:`mapper.model.ops.fusion_kernel.point_ov_weights`: the same
        function, every intermediate in per-block buffers instead of (P*N, C) tensors (weights as
        close to a float64 reference as the torch float32 pass's;
        tests/mapper/model/ops/test_fusion_kernel.py).
        """
        tensors = (rgb, features, volume_features, source_dirs)
        if (
            self.fast_inference
            and self.point_kernel
            and kernel_applies(*tensors, mask)
            and all(t.dtype == torch.float32 for t in tensors)
            and not torch.is_autocast_enabled(rgb.device.type)
        ):
            return point_ov_weights(
                self.point_kernel_weights(), rgb, features, volume_features, source_dirs, mask, source_range,
                threads=torch.get_num_threads(),
            )
        fused = self.forward(rgb, features, volume_features, source_dirs, mask, None, source_range)
        return fused.ov_weights, fused.valid

    def point_kernel_weights(self) -> PointKernelWeights:
        """The parameters laid out for the compiled point kernel, in its argument order; taken again
        whenever one changed (in place: an optimiser step or ``load_state_dict``, seen by each
        tensor's version counter; or replaced)."""
        key = tuple((id(p), p._version) for p in self.parameters())
        if self._kernel_weights is None or self._kernel_weights[0] != key:
            self._kernel_weights = (key, self._kernel_params())
        return self._kernel_weights[1]

    def _kernel_params(self) -> PointKernelWeights:
        def arr(t: Tensor) -> np.ndarray:
            return np.ascontiguousarray(t.detach().to(torch.float32).cpu().numpy())

        lin1, lin2, att = self.mlp_a[0], self.mlp_a[2], self.attention
        f1, f2, s1, s2 = att.ffn[0], att.ffn[2], self.mlp_s[0], self.mlp_s[2]
        assert isinstance(lin1, nn.Linear) and isinstance(lin2, nn.Linear)
        assert isinstance(f1, nn.Linear) and isinstance(f2, nn.Linear)
        assert isinstance(s1, nn.Linear) and isinstance(s2, nn.Linear)
        A = lin2.weight.shape[0]
        split = 2 * self.feature_dim + self.volume_feature_dim
        re = self.range_encoding
        w, b = att.qkv.weight.detach(), att.qkv.bias.detach()
        with torch.no_grad():
            extra = att.qkv(att.extra_token.to(w.dtype))  # the extra token's q, k, v
        params = (
            arr(lin1.weight[:, :split]), arr(lin1.bias), arr(lin1.weight[:, split:]),
            arr(lin2.weight), arr(lin2.bias),
            arr(self.dir_encoding.weight), arr(self.dir_encoding.bias),
            arr(re.weight) if re is not None else np.zeros((A, 1), np.float32),
            arr(re.bias) if re is not None else np.zeros(A, np.float32),
            arr(w[:A]), arr(b[:A]), arr(w[A : 2 * A]), arr(b[A : 2 * A]), arr(w[2 * A :]), arr(b[2 * A :]),
            arr(F.elu(extra[A : 2 * A]) + 1.0), arr(extra[2 * A :]),
            np.arange(A, dtype=np.int64) // (A // att.num_heads),
            arr(att.out.weight), arr(att.out.bias),
            arr(att.norm1.weight), arr(att.norm1.bias), np.float32(att.norm1.eps),
            arr(att.norm2.weight), arr(att.norm2.bias), np.float32(att.norm2.eps),
            arr(f1.weight), arr(f1.bias), arr(f2.weight), arr(f2.bias),
            arr(s1.weight), arr(s1.bias), arr(s2.weight[0]), np.float32(s2.bias.item()),
        )
        return PointKernelWeights(params, self.feature_dim, self.volume_feature_dim, re is not None)

    def _range_input(self, source_range: Tensor | None, shape: tuple[int, int], dtype: torch.dtype) -> Tensor:
        """(P * N, 1) log distance, the input of RE (``range_encoding`` only)."""
        if source_range is None:
            raise ValueError("this FusionNet has range_encoding: pass source_range (P, N) distances (m)")
        if tuple(source_range.shape) != shape:
            raise ValueError(f"source_range shape {tuple(source_range.shape)}, expected {shape}")
        return source_range.to(dtype).clamp_min(RANGE_MIN_M).log().reshape(-1, 1)

    def forward_reference(
        self,
        rgb: Tensor,
        features: Tensor,
        volume_features: Tensor,
        source_dirs: Tensor,
        mask: Tensor,
        query_dirs: Tensor | None,
        source_range: Tensor | None = None,
    ) -> FusionOutputs:
        """The original forward pass (the definition; training uses it). Arguments as ``forward``."""
        P, N, _ = features.shape
        mean, var = masked_mean_var(features, mask)
        x = torch.cat(
            [
                mean.unsqueeze(1).expand(P, N, -1),
                var.unsqueeze(1).expand(P, N, -1),
                volume_features.unsqueeze(1).expand(P, N, -1),
                rgb,
                features,
            ],
            dim=-1,
        )
        x = self.mlp_a(x) + self.dir_encoding(source_dirs.to(x.dtype))
        if self.range_encoding is not None:
            x = x + self.range_encoding(self._range_input(source_range, (P, N), x.dtype)).view(P, N, -1)
        x_att = self.attention(x, mask)
        ov_weights, valid = masked_softmax(self.mlp_s(x_att).squeeze(-1), mask)
        color_weights = None
        if query_dirs is not None:
            dq = query_dirs.unsqueeze(1).expand_as(source_dirs)
            rel = torch.cat(
                [F.normalize(dq - source_dirs, dim=-1, eps=1e-6), (dq * source_dirs).sum(-1, keepdim=True)],
                dim=-1,
            )
            logits = self.mlp_c(x_att + self.rel_dir_encoding(rel.to(x_att.dtype))).squeeze(-1)
            color_weights, _ = masked_softmax(logits, mask)
        return FusionOutputs(color_weights, ov_weights, valid, x_att)

    def forward_fast(
        self,
        rgb: Tensor,
        features: Tensor,
        volume_features: Tensor,
        source_dirs: Tensor,
        mask: Tensor,
        query_dirs: Tensor | None,
        source_range: Tensor | None = None,
    ) -> FusionOutputs:
        """``forward_reference`` rearranged for inference (no autograd); arguments as ``forward``.

        Same parameters, same function, up to float round-off:

        * first layer of MLP_a split by input blocks, ``W [m, s, v, rgb^n, f^n] =
          W_p [m, s, v] + W_n [rgb^n, f^n]``: the per-point part once per point, not once per view;
        * the extra token's query, key and value are one vector for all points: its key and value
          enter the sums over views as constants and its own output (dropped by the reference) is
          never computed;
        * the per-head linear-attention products as one (D x D) batched matrix product per point,
          the off-head blocks zeroed;
        * MLP_s and MLP_c evaluated as one network of twice the width, with RDE folded into the
          first layer of MLP_c (``W_c (x + W_r r + b_r) = W_c x + (W_c W_r) r + W_c b_r``).
        """
        P, N, Fd = features.shape
        dtype = features.dtype
        lin1, lin2 = self.mlp_a[0], self.mlp_a[2]
        assert isinstance(lin1, nn.Linear) and isinstance(lin2, nn.Linear)
        split = 2 * Fd + volume_features.shape[-1]
        mean, var = _masked_mean_var_fast(features, mask)  # (P, F) each
        per_point = torch.addmm(
            lin1.bias, torch.cat([mean, var, volume_features.to(dtype)], dim=-1), lin1.weight[:, :split].T
        )  # (P, H)
        hid = lin1.weight.shape[0]
        own = torch.cat([rgb, features], dim=-1).reshape(P * N, 3 + Fd)  # (P*N, 3 + F)
        h = torch.mm(own, lin1.weight[:, split:].T).view(P, N, hid)
        h = F.elu(h.add_(per_point.unsqueeze(1)), inplace=True).view(P * N, hid)  # (P*N, H)
        x = F.elu(torch.addmm(lin2.bias, h, lin2.weight.T), inplace=True)  # (P*N, A)
        de = self.dir_encoding
        x = x.addmm_(source_dirs.to(dtype).reshape(P * N, 3), de.weight.T).add_(de.bias)
        if self.range_encoding is not None:
            re = self.range_encoding
            x = x.addmm_(self._range_input(source_range, (P, N), dtype), re.weight.T).add_(re.bias)
        A = x.shape[-1]
        x_att = self._attention_fast(x.view(P, N, A), mask)  # (P, N, A)
        flat = x_att.view(P * N, A)
        s1, s2 = self.mlp_s[0], self.mlp_s[2]
        assert isinstance(s1, nn.Linear) and isinstance(s2, nn.Linear)
        if query_dirs is None:
            hs = F.elu(torch.addmm(s1.bias, flat, s1.weight.T), inplace=True)
            ov_weights, valid = masked_softmax(torch.addmm(s2.bias, hs, s2.weight.T).view(P, N), mask)
            return FusionOutputs(None, ov_weights, valid, x_att)
        c1, c2 = self.mlp_c[0], self.mlp_c[2]
        assert isinstance(c1, nn.Linear) and isinstance(c2, nn.Linear)
        rde = self.rel_dir_encoding
        w1 = torch.cat([s1.weight, c1.weight])  # (2A, A)
        b1 = torch.cat([s1.bias, torch.addmv(c1.bias, c1.weight, rde.bias)])  # (2A,)
        hidden = torch.addmm(b1, flat, w1.T)  # (P*N, 2A): [MLP_s, MLP_c] first layers
        dirs = source_dirs.to(dtype)
        dq = query_dirs.to(dtype).unsqueeze(1)  # (P, 1, 3)
        rel = torch.cat(
            [F.normalize(dq - dirs, dim=-1, eps=1e-6), (dq * dirs).sum(-1, keepdim=True)], dim=-1
        ).view(P * N, 4)
        w_rel = torch.cat([rde.weight.new_zeros(A, 4), c1.weight @ rde.weight])  # (2A, 4), 0 for MLP_s
        hidden.addmm_(rel, w_rel.T)
        hidden = F.elu(hidden, inplace=True)
        w2 = hidden.new_zeros(2, 2 * A)  # block-diagonal second layers
        w2[0, :A] = s2.weight[0]
        w2[1, A:] = c2.weight[0]
        logits = torch.addmm(torch.cat([s2.bias, c2.bias]), hidden, w2.T).view(P, N, 2)
        weights, valid = masked_softmax(logits.permute(0, 2, 1), mask.unsqueeze(1).expand(P, 2, N))
        # contiguous (P, N) weights, as the reference returns them
        return FusionOutputs(weights[:, 1].contiguous(), weights[:, 0].contiguous(), valid[:, 0], x_att)

    def _attention_fast(self, x: Tensor, mask: Tensor) -> Tensor:
        """``CrossViewAttention.forward`` without autograd: x (P, N, D), mask (P, N) -> (P, N, D).

        Overwrites ``x`` (the residual is added in place). The extra token's key and value are
        constants added to the sums over views; the per-head sums are full (D x D) products per
        point with the blocks between different heads zeroed.
        """
        att = self.attention
        P, N, D = x.shape
        H = att.num_heads
        flat = x.view(P * N, D)
        w, b = att.qkv.weight, att.qkv.bias  # (3D, D), (3D,)
        qk = torch.addmm(b[: 2 * D], flat, w[: 2 * D].T)  # (P*N, 2D), contiguous for elu_
        qk = F.elu(qk, inplace=True).add_(1.0)
        v = torch.addmm(b[2 * D :], flat, w[2 * D :].T).view(P, N, D)
        q = qk[:, :D].view(P, N, D)
        k = qk[:, D:].view(P, N, D) * mask.to(x.dtype).unsqueeze(-1)  # (P, N, D), masked keys
        extra = att.qkv(att.extra_token.to(x.dtype))  # (3D,): the extra token's q, k, v
        k_extra = F.elu(extra[D : 2 * D]) + 1.0
        head = torch.arange(D, device=x.device) // (D // H)
        same_head = (head[:, None] == head[None, :]).to(x.dtype)  # (D, D) block-diagonal ones
        kv = torch.einsum("pnd,pne->pde", k, v)  # (P, D, D): sum_n k v^T, all head pairs
        kv.add_(torch.outer(k_extra, extra[2 * D :])).mul_(same_head)
        k_sum = k.sum(dim=1).add_(k_extra)  # (P, D)
        # q . k_sum within each head, repeated over the head's D / H columns: (P*N, D)
        normaliser = torch.mm((q * k_sum.unsqueeze(1)).view(P * N, D), same_head).clamp_min_(1e-6)
        att_out = torch.bmm(q, kv).view(P * N, D).div_(normaliser)
        y = flat.addmm_(att_out, att.out.weight.T).add_(att.out.bias)  # x + out(att)
        y = _layer_norm_(y, att.norm1)
        f1, f2 = att.ffn[0], att.ffn[2]
        assert isinstance(f1, nn.Linear) and isinstance(f2, nn.Linear)
        z = F.elu(torch.addmm(f1.bias, y, f1.weight.T), inplace=True)
        y = y.addmm_(z, f2.weight.T).add_(f2.bias)
        y = _layer_norm_(y, att.norm2)
        return y.view(P, N, D)


class DensityMLP(nn.Module):
    """sigma = act(MLP_sigma(v)): (..., Dv) -> (...,) density (1/m), >= 0.

    ``softplus`` (default): smooth, never a dead gradient, grows linearly (no overflow).
    ``trunc_exp``: exp of the logit shifted by -1 and clamped to [-15, 15] (the NeRF-style
    choice; steeper, kept for experiments).
    """

    def __init__(self, volume_feature_dim: int, cfg: FusionConfig) -> None:
        super().__init__()
        self.activation = cfg.density_activation
        self.mlp = _mlp(volume_feature_dim, 2 * volume_feature_dim, 1)
        last = self.mlp[-1]
        assert isinstance(last, nn.Linear)
        with torch.no_grad():
            last.bias.fill_(cfg.density_bias_init)

    def forward(self, v: Tensor) -> Tensor:
        logit = _at_least_float32(self.mlp(v).squeeze(-1))
        if self.activation == "softplus":
            return F.softplus(logit)
        return torch.exp((logit - 1.0).clamp(-15.0, 15.0))


class DistillHead(nn.Module):
    """Distill baseline: regress the OV feature directly from [mean_n x_att^n, v] (no blending)."""

    def __init__(self, volume_feature_dim: int, cfg: FusionConfig) -> None:
        super().__init__()
        width = cfg.distill_hidden_dim or 2 * cfg.hidden_dim
        layers: list[nn.Module] = []
        d_in = cfg.attention_dim + volume_feature_dim
        for _ in range(cfg.distill_layers):
            layers += [nn.Linear(d_in, width), nn.ELU()]
            d_in = width
        layers.append(nn.Linear(d_in, cfg.ov_dim))
        # (the default sizes give the same module indices, 0 / 2, as the first checkpoints' head)
        self.mlp = nn.Sequential(*layers)

    def forward(self, x_att: Tensor, mask: Tensor, volume_features: Tensor) -> Tensor:
        """x_att: (P, N, A); mask: (P, N); volume_features: (P, Dv) -> (P, ov_dim)."""
        pooled, _ = masked_mean_var(x_att, mask)
        return self.mlp(torch.cat([pooled, volume_features.to(pooled.dtype)], dim=-1))
