"""The learned ``segment_points`` answer (sample, weigh, blend, compare) as one compiled CPU pass.

``segment_points`` with the learned model runs three compiled kernels in turn over every (point,
view) pair: the sampling of colour and 2D features (:mod:`mapper.model.ops.sample_kernel`), the
FusionNet's OV weights (:mod:`mapper.model.ops.fusion_kernel`) and the blend of the OV maps with
each text's cosine (:func:`mapper.kernels.average_kernel.blend_kernel`). Between them the pairs'
samples (23 floats a pair: 1.6M pairs, about 150 MB, for 100k points over 16 views) are written
to memory and read back, chunk by chunk. Here each block of points goes through all three steps
while its samples sit in per-block buffers, using the same compiled functions
(:func:`~mapper.model.ops.sample_kernel.sample_pair`, ``_point_block``,
:func:`~mapper.kernels.average_kernel.blend_range`) in the same order, so the answers are the
same numbers as the three kernels' (tests/mapper/model/ops/test_answer_kernel.py). A block also skips the
trailing padding slots none of its points uses (padding is masked: it changes no answer). Without
texts the pass writes each point's blended feature instead (the learned features the node writes
into the global map).
"""

from __future__ import annotations

import numba
import numpy as np

from mapper.kernels.average_kernel import blend_range, launch
from mapper.model.ops.fusion_kernel import _POW2, RANGE_MIN_M, PointKernelWeights, _point_block, default_block
from mapper.model.ops.sample_kernel import PairArgs, pair_args, sample_pair

__all__ = ["answer_points", "warm_up"]


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _answer_kernel(
    pts,  # (P, 3) float32 world points
    view_idx,  # (N, P) int64: slot-major, the view behind each pair
    slot_mask,  # (N, P) bool: False for padding slots
    cameras,  # (cam_from_world (M, 4, 4), K (M, 4), centres (M, 3), width, height, eps): sample_pair's
    rgb,  # (table (M * h * w, 3), w, h, sx, sy): the colour maps and their scale from image pixels
    feat,  # (table (M * h * w, F), w, h, sx, sy): the 2D feature maps
    depth,  # (use_depth, (M * dh * dw,) float32 or (0,), dw, dh, sx, sy, ratio): the DGM test
    vol,  # (Dv, P) float32 volume features
    use_range,  # bool: the network has range encoding (log distances)
    params,  # PointKernelWeights.params
    pow2,  # fusion_kernel._POW2
    ov,  # (table (M * h * w, C), w, h, sx, sy): the OV maps
    texts,  # (T, C) float32 unit text embeddings; T = 0: write the blends themselves
    out,  # out (P, T) float32: each text's cosine with the point's unit blend (0 where none), or
    # (P, C) the blends
    valid,  # out (P,) bool: some view sees the point
    num_views,  # out (P,) int64: the views that see it
    block,  # int: points per parallel task
):  # pragma: no cover - compiled
    n_slots, n_pts = view_idx.shape
    ov_t, ov_w, ov_h, ov_sx, ov_sy = ov
    n_feat, n_vol = feat[0].shape[1], vol.shape[0]
    n_blocks = (n_pts + block - 1) // block
    for blk in numba.prange(n_blocks):
        p0 = blk * block
        nb = min(n_pts, p0 + block) - p0
        nk = 1  # the slots the block's points use (trailing padding dropped)
        for j in range(nb):
            for n in range(n_slots - 1, nk - 1, -1):
                if slot_mask[n, p0 + j]:
                    nk = n + 1
                    break
        # 1. every pair's samples, pair n * block + j (the sample kernel's layout, P = block)
        s_rgb = np.zeros((3, nk * block), np.float32)
        s_feat = np.zeros((n_feat, nk * block), np.float32)
        s_mask = np.zeros(nk * block, np.bool_)
        s_dirs = np.zeros((3, nk * block), np.float32)
        s_dist = np.ones(nk * block, np.float32)
        s_uv = np.zeros((nk * block, 2), np.float32)
        for n in range(nk):
            for j in range(nb):
                p = p0 + j
                sample_pair(pts[p, 0], pts[p, 1], pts[p, 2], view_idx[n, p], slot_mask[n, p], cameras,
                            rgb, s_rgb, feat, s_feat, depth, s_mask, s_dirs, s_dist, s_uv, n * block + j)
        # 2. the network's OV weights of the block's views
        b_vol = np.empty((n_vol, block), np.float32)
        for c in range(n_vol):
            for j in range(nb):
                b_vol[c, j] = vol[c, p0 + j]
        log_range = np.zeros((nk, block if use_range else 0), np.float32)
        if use_range:
            for i in range(nk * block):
                log_range[i // block, i % block] = np.log(max(s_dist[i], np.float32(RANGE_MIN_M)))
        weights = np.zeros((block, nk), np.float32)
        b_valid = np.zeros(block, np.bool_)
        inputs = (s_rgb.reshape(3, nk, block), s_feat.reshape(n_feat, nk, block), b_vol,
                  s_dirs.reshape(3, nk, block), s_mask.reshape(nk, block), log_range)
        _point_block(inputs, params, pow2, weights, b_valid, 0, nb, block)
        # 3. the OV blend with those weights, two points at a time (neighbours share most taps)
        b_view = np.empty((block, nk), np.int64)
        b_uv = np.empty((block, nk, 2), np.float32)
        for n in range(nk):
            for j in range(nb):
                b_view[j, n] = view_idx[n, p0 + j]
                b_uv[j, n, 0] = s_uv[n * block + j, 0] * ov_sx
                b_uv[j, n, 1] = s_uv[n * block + j, 1] * ov_sy
        blend_range(ov_t, ov_w, ov_h, b_view, b_uv, weights, 0, nb, texts, out, p0)
        for j in range(nb):
            valid[p0 + j] = b_valid[j]
            seen = 0
            for n in range(nk):
                seen += s_mask[n * block + j]
            num_views[p0 + j] = seen


def answer_points(
    weights: PointKernelWeights,
    pts: np.ndarray,  # (P, 3) float32 world points
    view_idx: np.ndarray,  # (N, P) int64, slot-major
    slot_mask: np.ndarray,  # (N, P) bool
    pairs: PairArgs,  # the cameras and maps the pairs are sampled from (sample_kernel.pair_args)
    volume_features: np.ndarray,  # (P, Dv) float32
    ov: tuple[np.ndarray, tuple[int, int]],  # (M * h * w, C) OV maps, channel-last, their (w, h)
    texts: np.ndarray | None,  # (T, C) float32 unit text embeddings; None: the blends themselves
    *,
    threads: int,
    block: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # (P, T) or (P, C) float32, (P,) bool, (P,) int64
    """Each text's cosine with each point's learned OV feature, as ``GovNeSF.point_cosines`` over
    ``sample_views_indexed`` samples computes it with the compiled kernels (see the module
    docstring): cosines (P, T) (0 where no view sees the point), valid (P,), num_views (P,). With
    ``texts=None`` the features themselves, (P, C), as ``GovNeSF.point_outputs(...).ov`` (0 rows
    where no view sees the point). ``block``: points per parallel task (0: the point kernel's
    :func:`default_block`)."""
    n_ov = ov[0].shape[1]
    raw = texts is None
    if texts is not None and texts.shape[0] == 0:
        raise ValueError("answer_points: texts holds no embedding (texts=None asks for the features)")
    texts = np.zeros((0, n_ov), np.float32) if texts is None else texts
    N, P = view_idx.shape
    n_feat = pairs.feat[0].shape[1]
    if (slot_mask.shape != (N, P) or pts.shape != (P, 3)
            or volume_features.shape != (P, weights.volume_feature_dim)):
        raise ValueError(f"answer_points: points {pts.shape}, slot_mask {slot_mask.shape} and volume "
                         f"features {volume_features.shape} do not fit view_idx {view_idx.shape}")
    if n_feat != weights.feature_dim or texts.ndim != 2 or texts.shape[1] != ov[0].shape[1]:
        raise ValueError(f"answer_points: {n_feat} feature channels / texts {texts.shape} do not fit the "
                         f"network (feature_dim {weights.feature_dim}) or the {ov[0].shape[1]}-channel OV "
                         "maps")
    ov_table, (ov_w, ov_h) = ov
    width, height = float(pairs.cameras[3]), float(pairs.cameras[4])
    ov_maps = (np.ascontiguousarray(ov_table, np.float32), int(ov_w), int(ov_h),
               np.float32(ov_w / width), np.float32(ov_h / height))  # scale_uv's factors
    out = np.zeros((P, n_ov if raw else texts.shape[0]), np.float32)
    valid = np.zeros(P, np.bool_)
    num_views = np.zeros(P, np.int64)
    if P == 0:
        return out, valid, num_views
    with launch(threads):
        _answer_kernel(
            np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(view_idx, np.int64),
            np.ascontiguousarray(slot_mask, np.bool_), pairs.cameras, pairs.rgb, pairs.feat, pairs.depth,
            np.ascontiguousarray(volume_features.T, np.float32), bool(weights.range_encoding), weights.params,
            _POW2, ov_maps, np.ascontiguousarray(texts, np.float32), out, valid, num_views,
            int(block or default_block(N, weights.attention_dim)),
        )
    return out, valid, num_views


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now, on a one-point problem."""
    one = np.zeros((1, 1), np.int64)
    pairs = pair_args(np.eye(4, dtype=np.float32)[None], np.ones((1, 4), np.float32),
                      np.zeros((1, 3), np.float32), (1, 1), 1e-6, (np.zeros((1, 3), np.float32), (1, 1)),
                      (np.zeros((1, 2), np.float32), (1, 1)), (np.ones((1, 1, 1), np.float32), (1, 1)), 0.1)
    answer_points(PointKernelWeights.zeros(2, 1, 2, 2), np.zeros((1, 3), np.float32), one,
                  np.ones((1, 1), np.bool_), pairs, np.zeros((1, 1), np.float32),
                  (np.zeros((1, 4), np.float32), (1, 1)), np.zeros((1, 4), np.float32), threads=1)
