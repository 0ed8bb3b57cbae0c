"""The multi-view averaging of OV features as one compiled CPU kernel (numba).

:func:`mapper.model.baselines.average_features` and ``average_similarities`` (what the node's
``segment_points`` methods ``average`` and ``average_depth`` call) on a CPU device run here: each
point, in parallel over blocks of points, is projected into every view, tested (in front of the
camera, inside the image less the border, optionally the depth test and a view weight), and the
bilinear taps of its views are summed into one D-vector, from which the normalised feature or its
cosines with the texts are written. Nothing of size (pairs, ...) or (points, views) is
materialised; the torch / numpy path (``baselines._chunks``) made those arrays and spent most of
its time there (docs/results.md).

The D-dimensional sums are bound by loading the taps' rows (four rows of D floats per point and
view), so points are summed two at a time (:func:`accumulate_taps`): where both fall on the same
cell quad of a view, as neighbouring points mostly do (89% of the taps on ``govnesf bench``'s
stream points), its rows are read once for both. Each point's sum is the same expression in the
same order either way, so the answers do not depend on a point's neighbour. ``blend_kernel`` (the
learned model's blend over each point's chosen views) sums its points the same way.

The selection arithmetic is the reference's, in float32 and in the same order (projection
``R p + t`` without contraction, ``x / z * f + c``; the depth test's nearest pixel; the corners
and weights of ``grid_sample(bilinear, border, align_corners=False)``), so the views that count
are the same; only the D-dimensional sums are vectorised (``fastmath``, reassociated), which moves
the features by float rounding (about 1e-7).

The first call in a process compiles the kernel (a few seconds) or loads it from numba's cache
(``__pycache__`` beside this file, or numba's user cache where that is read-only); :func:`warm_up`
does that ahead of a first query.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import numba
import numpy as np

__all__ = [
    "LAUNCH_LOCK", "average_kernel", "blend_kernel", "blend_range", "check_prior", "in_view_matrix",
    "kernel_threads", "launch", "warm_up",
]

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F2 = np.float32(2.0)
LAUNCH_LOCK = threading.Lock()
"""Held around every parallel numba launch of the project (these kernels and
``mapper.map.query_kernels``): one launch at a time, since each uses every thread it is given and
the thread count is numba-global, and since numba's fallback threading layer (workqueue, where
neither OpenMP nor TBB is available) aborts on concurrent launches."""


@numba.njit(fastmath=True, boundscheck=False, cache=True)
def _add_taps(acc, table, r00, r01, r10, r11, w00, w01, w10, w11):  # pragma: no cover - compiled
    a, b, c, d = table[r00], table[r01], table[r10], table[r11]
    for k in range(acc.shape[0]):
        acc[k] += w00 * a[k] + w01 * b[k] + w10 * c[k] + w11 * d[k]


@numba.njit(fastmath=True, boundscheck=False, cache=True)
def _add_taps2(acc, acc2, table, r00, r01, r10, r11, w00, w01, w10, w11, u00, u01, u10,
               u11):  # pragma: no cover - compiled
    """:func:`_add_taps` for two points on the same four rows (weights w.. into ``acc``, u.. into
    ``acc2``): each row is read once for both."""
    a, b, c, d = table[r00], table[r01], table[r10], table[r11]
    for k in range(acc.shape[0]):
        ak, bk, ck, dk = a[k], b[k], c[k], d[k]
        acc[k] += w00 * ak + w01 * bk + w10 * ck + w11 * dk
        acc2[k] += u00 * ak + u01 * bk + u10 * ck + u11 * dk


_NO_KEY = np.int64(1) << np.int64(62)


@numba.njit(cache=True, boundscheck=False)
def accumulate_taps(acc, acc2, table, key, rows, wts, m, m2):  # pragma: no cover - compiled
    """Sum two points' bilinear taps into ``acc`` (point 0) and ``acc2`` (point 1; ``m2`` < 0:
    there is no second point). Point q's j-th entry (``j < m`` for q = 0, ``m2`` for q = 1) has a
    sort key ``key[q, j]`` (its view or slot, ascending along j), four table rows
    ``rows[q, 4j:4j+4]`` and their weights ``wts[q, 4j:4j+4]``; each point's entries are summed in
    their order. Where both points have an entry with the same key on the same rows (the same cell
    quad of the same map: neighbouring points mostly do), the rows are read once for both
    (:func:`_add_taps2`): the tap loads, not the arithmetic, bound this sum, and each sum is the
    same expression either way."""
    a, b = 0, 0
    while a < m or b < m2:
        ka = key[0, a] if a < m else _NO_KEY
        kb = key[1, b] if b < m2 else _NO_KEY
        ja, jb = 4 * a, 4 * b
        if ka == kb and rows[0, ja] == rows[1, jb]:  # the first row fixes the quad (rows are global)
            _add_taps2(acc, acc2, table, rows[0, ja], rows[0, ja + 1], rows[0, ja + 2], rows[0, ja + 3],
                       wts[0, ja], wts[0, ja + 1], wts[0, ja + 2], wts[0, ja + 3],
                       wts[1, jb], wts[1, jb + 1], wts[1, jb + 2], wts[1, jb + 3])
            a += 1
            b += 1
        elif ka <= kb:
            _add_taps(acc, table, rows[0, ja], rows[0, ja + 1], rows[0, ja + 2], rows[0, ja + 3],
                      wts[0, ja], wts[0, ja + 1], wts[0, ja + 2], wts[0, ja + 3])
            a += 1
        else:
            _add_taps(acc2, table, rows[1, jb], rows[1, jb + 1], rows[1, jb + 2], rows[1, jb + 3],
                      wts[1, jb], wts[1, jb + 1], wts[1, jb + 2], wts[1, jb + 3])
            b += 1


@numba.njit(fastmath=True, boundscheck=False, cache=True)
def dot(a, b):  # pragma: no cover - compiled
    s = _F0
    for k in range(a.shape[0]):
        s += a[k] * b[k]
    return s


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _kernel(
    pts,  # (N, 3) float32 world points
    cam_from_world,  # (V, 4, 4) float32
    K,  # (V, 4) float32 fx, fy, cx, cy
    right,  # (V,) float64: image width - border
    bottom,  # (V,) float64: image height - border
    border,  # float64
    eps,  # float32: smallest depth in front of the camera
    ov_off,  # (V,) int64: each view's first row in ``table``
    ov_w,  # (V,) int64 OV map sizes
    ov_h,  # (V,) int64
    ov_scale,  # (V, 2) float32: OV map size / image size
    table,  # (R, D) float32: the views' OV maps, row-major, one after another
    use_depth,  # bool
    has_depth,  # (V,) bool
    depth_flat,  # (S,) float32: the views' depth maps, flattened one after another
    d_off,  # (V,) int64
    d_w,  # (V,) int64
    d_h,  # (V,) int64
    d_scale,  # (V, 2) float32: depth map size / image size
    depth_tol,  # float32: relative tolerance of the depth test
    distance_power,  # float32: weight z ** -distance_power (0: none)
    view_weights,  # (V, N) float32, or (V, 0) for none
    prior,  # (P, D) float32: earlier views' mean features (e.g. of keyframes that left the window)
    prior_row,  # (N,) int64: each point's row of ``prior`` (-1: none), or (0,) for no prior at all
    prior_w,  # (N,) float32: the weight (views) behind each point's prior row
    raw,  # bool: with T = 0, write the weighted mean itself instead of its unit vector
    texts,  # (T, D) float32; T = 0: write features instead of cosines
    out,  # (N, T) cosines or (N, D) features, float32, zeroed by the caller
    count,  # (N,) int64 views that counted, zeroed by the caller
    block,  # int: points per parallel task
):  # pragma: no cover - compiled
    n_pts = pts.shape[0]
    n_views = cam_from_world.shape[0]
    dim = table.shape[1]
    n_blocks = (n_pts + block - 1) // block
    for blk in numba.prange(n_blocks):
        accs = np.empty((2, dim), np.float32)
        p_u = np.empty(n_views, np.float32)
        p_v = np.empty(n_views, np.float32)
        p_w = np.empty(n_views, np.float32)
        key = np.empty((2, n_views), np.int64)
        rows = np.empty((2, 4 * n_views), np.int64)
        wts = np.empty((2, 4 * n_views), np.float32)
        m_q = np.zeros(2, np.int64)
        active = np.zeros(2, np.bool_)
        hi = min(n_pts, (blk + 1) * block)
        for i0 in range(blk * block, hi, 2):  # points in pairs: neighbours share most taps
            n_q = min(2, hi - i0)
            for q in range(n_q):
                i = i0 + q
                m, wsum = _select(pts, i, cam_from_world, K, right, bottom, border, eps, use_depth,
                                  has_depth, depth_flat, d_off, d_w, d_h, d_scale, depth_tol, distance_power,
                                  view_weights, key[q], p_u, p_v, p_w)
                count[i] = m
                pw = _F0
                if prior_row.shape[0] > 0 and prior_row[i] >= 0:
                    pw = prior_w[i]
                m_q[q] = m
                active[q] = m > 0 or pw > 0
                if not active[q]:  # no taps, no prior: the output row stays 0
                    continue
                inv = _F1 / (wsum + pw)
                acc = accs[q]
                acc[:] = _F0
                if pw > 0:
                    pri = prior[prior_row[i]]
                    ps = pw * inv
                    for k in range(dim):
                        acc[k] = pri[k] * ps
                for k in range(m):
                    v = key[q, k]
                    r00, r01, r10, r11, tx, ty = corners(p_u[k] * ov_scale[v, 0], p_v[k] * ov_scale[v, 1],
                                                         ov_w[v], ov_h[v])
                    sc = p_w[k] * inv
                    j = 4 * k
                    rows[q, j], rows[q, j + 1] = ov_off[v] + r00, ov_off[v] + r01
                    rows[q, j + 2], rows[q, j + 3] = ov_off[v] + r10, ov_off[v] + r11
                    wts[q, j], wts[q, j + 1] = (_F1 - tx) * (_F1 - ty) * sc, tx * (_F1 - ty) * sc
                    wts[q, j + 2], wts[q, j + 3] = (_F1 - tx) * ty * sc, tx * ty * sc
            accumulate_taps(accs[0], accs[1], table, key, rows, wts, m_q[0], m_q[1] if n_q == 2 else 0)
            for q in range(n_q):
                if active[q]:
                    _write(accs[q], raw, texts, out, i0 + q)


@numba.njit(cache=True, boundscheck=False, inline="always")
def _select(pts, i, cam_from_world, K, right, bottom, border, eps, use_depth, has_depth, depth_flat, d_off,
            d_w, d_h, d_scale, depth_tol, distance_power, view_weights, p_view, p_u, p_v,
            p_w):  # pragma: no cover - compiled
    """The views that count for point i (in front, inside the image less the border, the weight
    and the depth test), in view order: their indices, pixels and weights into ``p_view`` ..
    ``p_w``; returns (how many, the sum of their weights)."""
    x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
    weighted = view_weights.shape[1] > 0
    m = 0
    wsum = _F0
    for v in range(cam_from_world.shape[0]):
        R = cam_from_world[v]
        cz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + R[2, 3]
        if not cz > eps:
            continue
        cx = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + R[0, 3]
        cy = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + R[1, 3]
        u = cx / cz * K[v, 0] + K[v, 2]
        vv = cy / cz * K[v, 1] + K[v, 3]
        if not (u >= border and u <= right[v] and vv >= border and vv <= bottom[v]):
            continue
        if weighted and not view_weights[v, i] > 0:
            continue
        if use_depth and has_depth[v]:
            col = min(max(np.floor(u * d_scale[v, 0]), _F0), np.float32(d_w[v] - 1))
            row = min(max(np.floor(vv * d_scale[v, 1]), _F0), np.float32(d_h[v] - 1))
            d = depth_flat[d_off[v] + np.int64(row) * d_w[v] + np.int64(col)]
            if not (d > 0 and abs(d - cz) <= depth_tol * d):
                continue
        w = _F1
        if distance_power != 0:
            w = max(cz, np.float32(1e-6)) ** (-distance_power)
        if weighted:
            w = w * view_weights[v, i]
        p_view[m], p_u[m], p_v[m], p_w[m] = v, u, vv, w
        wsum += w
        m += 1
    return m, wsum


@numba.njit(cache=True, boundscheck=False, inline="always")
def _write(acc, raw, texts, out, i):  # pragma: no cover - compiled
    """Point i's output from its weighted sum ``acc``: the cosines with ``texts`` (T > 0), else
    the unit feature, or with ``raw`` the sum itself."""
    norm = max(np.sqrt(dot(acc, acc)), np.float32(1e-12))
    if raw:
        norm = _F1
    if texts.shape[0] == 0:
        for k in range(acc.shape[0]):
            out[i, k] = acc[k] / norm
    else:
        for t in range(texts.shape[0]):
            out[i, t] = dot(acc, texts[t]) / norm


@numba.njit(cache=True, boundscheck=False, inline="always")
def corners(u, v, map_w, map_h):  # pragma: no cover - compiled
    """The four taps of a bilinear sample at pixel (u, v) of a map_w x map_h map, as
    ``bilinear_corners`` (``grid_sample``, bilinear, border, align_corners=False; non-finite
    coordinates read as 0): rows (r00, r01, r10, r11) within the map and the fractions (tx, ty)."""
    wf, hf = np.float32(map_w), np.float32(map_h)
    if not np.isfinite(u):
        u = _F0
    if not np.isfinite(v):
        v = _F0
    gx = min(max(_F2 * u / wf - _F1, -_F2), _F2)
    gy = min(max(_F2 * v / hf - _F1, -_F2), _F2)
    ix = min(max(((gx + _F1) * wf - _F1) / _F2, _F0), wf - _F1)
    iy = min(max(((gy + _F1) * hf - _F1) / _F2, _F0), hf - _F1)
    x0f, y0f = np.floor(ix), np.floor(iy)
    x0, y0 = np.int64(x0f), np.int64(y0f)
    x1, y1 = min(x0 + 1, map_w - 1), min(y0 + 1, map_h - 1)
    r0, r1 = y0 * map_w, y1 * map_w
    return r0 + x0, r0 + x1, r1 + x0, r1 + x1, ix - x0f, iy - y0f


@numba.njit(cache=True, boundscheck=False, inline="always")
def _blend_taps(table, map_w, map_h, view_idx, uv, weights, p, key, rows, wts):  # pragma: no cover - compiled
    """Point p's taps for :func:`accumulate_taps` (its slots of non-zero weight, in slot order,
    keyed by slot; :func:`corners` of each slot's map); returns how many."""
    m = 0
    for n in range(weights.shape[1]):
        w = weights[p, n]
        if w == 0:
            continue
        r00, r01, r10, r11, tx, ty = corners(uv[p, n, 0], uv[p, n, 1], map_w, map_h)
        base = view_idx[p, n] * map_w * map_h
        j = 4 * m
        key[m] = n
        rows[j], rows[j + 1], rows[j + 2], rows[j + 3] = base + r00, base + r01, base + r10, base + r11
        wts[j], wts[j + 1] = w * ((_F1 - tx) * (_F1 - ty)), w * (tx * (_F1 - ty))
        wts[j + 2], wts[j + 3] = w * ((_F1 - tx) * ty), w * (tx * ty)
        m += 1
    return m


@numba.njit(cache=True, boundscheck=False, inline="always")
def blend_range(table, map_w, map_h, view_idx, uv, weights, lo, hi, texts, out,
                shift):  # pragma: no cover - compiled
    """Points lo .. hi - 1 of (view_idx, uv, weights) (see :func:`_blend_kernel`) blended two at a
    time (neighbours share most taps, :func:`accumulate_taps`) into rows p + ``shift`` of ``out``:
    the blend itself (T = 0) or each text's cosine with the unit blend."""
    n_slots, n_texts = weights.shape[1], texts.shape[0]
    accs = np.empty((2, table.shape[1]), np.float32)
    key = np.empty((2, n_slots), np.int64)
    rows = np.empty((2, 4 * n_slots), np.int64)
    wts = np.empty((2, 4 * n_slots), np.float32)
    for p0 in range(lo, hi, 2):
        n_q = min(2, hi - p0)
        accs[:] = _F0
        m = _blend_taps(table, map_w, map_h, view_idx, uv, weights, p0, key[0], rows[0], wts[0])
        m2 = 0
        if n_q == 2:
            m2 = _blend_taps(table, map_w, map_h, view_idx, uv, weights, p0 + 1, key[1], rows[1], wts[1])
        accumulate_taps(accs[0], accs[1], table, key, rows, wts, m, m2)
        for q in range(n_q):
            acc = accs[q]
            row = p0 + q + shift
            if n_texts == 0:
                out[row, :] = acc
                continue
            inv = _F1 / max(np.sqrt(dot(acc, acc)), np.float32(1e-12))  # F.normalize's eps
            for t in range(n_texts):
                out[row, t] = dot(acc, texts[t]) * inv


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _blend_kernel(
    table,  # (R, C) float32: M maps of h x w rows, channel-last, view-major
    map_w,  # int
    map_h,  # int
    view_idx,  # (P, N) int64: the map behind each slot
    uv,  # (P, N, 2) float32 pixel coordinates in the maps' resolution
    weights,  # (P, N) float32
    texts,  # (T, C) float32; T = 0: write the blends themselves
    out,  # (P, C) blends or (P, T) each text's cosine with the unit blend
    block,  # int: points per parallel task
):  # pragma: no cover - compiled
    n_pts = weights.shape[0]
    n_blocks = (n_pts + block - 1) // block
    for blk in numba.prange(n_blocks):
        blend_range(table, map_w, map_h, view_idx, uv, weights, blk * block, min(n_pts, (blk + 1) * block),
                    texts, out, 0)


def _contiguous_uv(uv: np.ndarray) -> np.ndarray:  # (P, N, 2) -> the same, C-contiguous float32
    """``np.ascontiguousarray(uv, np.float32)``, several times faster for the usual case: a
    transposed view of slot-major (N, P, 2) pixel pairs (``sample_views_indexed``), copied as one
    8-byte element per pair (the same bits)."""
    if uv.dtype == np.float32 and uv.ndim == 3 and uv.shape[2] == 2 and uv.strides[2] == 4 \
            and not uv.flags.c_contiguous:
        return np.ascontiguousarray(uv.view(np.complex64)).view(np.float32)
    return np.ascontiguousarray(uv, np.float32)


def blend_kernel(
    table: np.ndarray,  # (M * h * w, C) float32
    map_wh: tuple[int, int],
    view_idx: np.ndarray,  # (P, N) int64
    uv: np.ndarray,  # (P, N, 2) float32
    weights: np.ndarray,  # (P, N) float32
    *,
    threads: int,
    texts: np.ndarray | None = None,  # (T, C) float32
    block: int = 64,
) -> np.ndarray:  # (P, C) float32, or (P, T) with texts
    """``fusion.blend_from_maps`` on the CPU: each point's weighted sum of the bilinear samples of
    its slots' maps (``bilinear_corners``' taps; slots of weight 0 are skipped). With ``texts``:
    ``F.normalize(blend) @ texts.T`` instead, each point's blend kept in a C-vector while its
    cosines are taken (the (P, C) blends are never written). Arguments checked by the caller."""
    n_out = table.shape[1] if texts is None else texts.shape[0]
    out = np.empty((weights.shape[0], n_out), np.float32)
    txt = np.zeros((0, table.shape[1]), np.float32) if texts is None else texts
    with launch(threads):
        _blend_kernel(np.ascontiguousarray(table, np.float32), int(map_wh[0]), int(map_wh[1]),
                      np.ascontiguousarray(view_idx, np.int64), _contiguous_uv(uv),
                      np.ascontiguousarray(weights, np.float32), np.ascontiguousarray(txt, np.float32), out,
                      int(block))
    return out


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _depth_test_kernel(pts, cam_from_world, K, width, height, eps, depth, ratio, out,
                       block):  # pragma: no cover - compiled
    # pts (P, 3) float32; cam_from_world (M, 4, 4) float32; K (M, 4) float32; depth (M, h, w) float32
    # (a (M, 1, 1) zero depth: in view only); out (P, M) bool
    n_pts, n_views = out.shape
    d_h, d_w = depth.shape[1], depth.shape[2]
    n_blocks = (n_pts + block - 1) // block
    for blk in numba.prange(n_blocks):
        for i in range(blk * block, min(n_pts, (blk + 1) * block)):
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            for v in range(n_views):
                R = cam_from_world[v]
                cz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + R[2, 3]
                if not cz > eps:
                    out[i, v] = False
                    continue
                cx = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + R[0, 3]
                cy = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + R[1, 3]
                u = cx / cz * K[v, 0] + K[v, 2]
                vv = cy / cz * K[v, 1] + K[v, 3]
                if not (u >= 0 and u <= width and vv >= 0 and vv <= height):
                    out[i, v] = False
                    continue
                col = min(max(int(np.floor(u)), 0), d_w - 1)
                row = min(max(int(np.floor(vv)), 0), d_h - 1)
                measured = depth[v, row, col]
                if measured > 0 and np.isfinite(measured):
                    out[i, v] = abs(cz - measured) <= ratio * measured
                else:
                    out[i, v] = True


def depth_test_launch(
    pts: np.ndarray, cam_from_world: np.ndarray, K: np.ndarray, image_wh: tuple[int, int], eps: float,
    depth_m: np.ndarray, ratio: float, threads: int, block: int,
) -> np.ndarray:  # (P, M) bool
    """One launch of the in-view and depth-test kernel (:func:`in_view_matrix`,
    :func:`mapper.model.ops.occlusion_kernel.depth_test_matrix`)."""
    out = np.empty((pts.shape[0], cam_from_world.shape[0]), np.bool_)
    with launch(threads):
        _depth_test_kernel(np.ascontiguousarray(pts, np.float32),
                           np.ascontiguousarray(cam_from_world, np.float32),
                           np.ascontiguousarray(K, np.float32), np.float32(image_wh[0]),
                           np.float32(image_wh[1]), np.float32(eps),
                           np.ascontiguousarray(depth_m, np.float32), np.float32(ratio), out, int(block))
    return out


def in_view_matrix(
    pts: np.ndarray,  # (P, 3) float32 world points
    cam_from_world: np.ndarray,  # (M, 4, 4) float32
    K: np.ndarray,  # (M, 4) float32
    image_wh: tuple[int, int],
    eps: float,
    *,
    threads: int,
    block: int = 256,
) -> np.ndarray:  # (P, M) bool
    """``in_view(*project_points(pts, K, cam_from_world), W, H)`` for every (point, view) at once
    (no border), as one compiled CPU kernel: the same float32 arithmetic, without the (M, P, 2)
    projections (the depth-test kernel with no depth)."""
    no_depth = np.zeros((cam_from_world.shape[0], 1, 1), np.float32)
    return depth_test_launch(pts, cam_from_world, K, image_wh, eps, no_depth, 0.0, threads, block)


@contextlib.contextmanager
def launch(threads: int) -> Iterator[None]:
    """Around one parallel numba launch: holds :data:`LAUNCH_LOCK` and sets numba's thread count
    to ``threads`` (within its pool; 0 = leave it), restoring it after."""
    with LAUNCH_LOCK:
        previous = numba.get_num_threads()
        numba.set_num_threads(kernel_threads(threads or previous))
        try:
            yield
        finally:
            numba.set_num_threads(previous)


def kernel_threads(threads: int) -> int:
    """The threads a launch may use: ``threads`` within numba's pool (1..NUMBA_NUM_THREADS)."""
    return max(1, min(int(threads), int(numba.config.NUMBA_NUM_THREADS)))  # type: ignore[attr-defined]


def average_kernel(
    pts: np.ndarray,  # (N, 3) float32
    cam_from_world: np.ndarray,  # (V, 4, 4) float32
    K: np.ndarray,  # (V, 4) float32
    right: np.ndarray,  # (V,) float64
    bottom: np.ndarray,  # (V,) float64
    border: float,
    eps: float,
    ov_off: np.ndarray,  # (V,) int64
    ov_w: np.ndarray,  # (V,) int64
    ov_h: np.ndarray,  # (V,) int64
    ov_scale: np.ndarray,  # (V, 2) float32
    table: np.ndarray,  # (R, D) float32
    *,
    use_depth: bool,
    has_depth: np.ndarray,  # (V,) bool
    depth_flat: np.ndarray,  # (S,) float32
    d_off: np.ndarray,  # (V,) int64
    d_w: np.ndarray,  # (V,) int64
    d_h: np.ndarray,  # (V,) int64
    d_scale: np.ndarray,  # (V, 2) float32
    depth_tol: float,
    distance_power: float,
    view_weights: np.ndarray | None,  # (V, N) float32
    texts: np.ndarray | None,  # (T, D) float32
    threads: int,
    block: int = 64,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,  # (P, D), (N,) int64, (N,) float32
    raw: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Run the kernel; returns (cosines (N, T) with ``texts``, else unit features (N, D), or with
    ``raw`` the weighted means themselves; zero rows where nothing counts) and the views that counted
    (N,) int64. ``prior`` = (mean features (P, D), each point's row (-1: none), the weight of its
    row): a point's mean then takes its prior row as ``weight`` more views (counts stay the views
    here). Arguments as the kernel's (checked by the caller, :mod:`mapper.model.baselines`)."""
    n_pts, dim = pts.shape[0], table.shape[1]
    n_views = cam_from_world.shape[0]
    txt = np.zeros((0, dim), np.float32) if texts is None else np.ascontiguousarray(texts, np.float32)
    out = np.zeros((n_pts, dim if texts is None else txt.shape[0]), np.float32)
    count = np.zeros(n_pts, np.int64)
    vw = np.zeros((n_views, 0), np.float32) if view_weights is None else np.ascontiguousarray(view_weights,
                                                                                               np.float32)
    if prior is None:
        p_tab, p_row, p_w = np.zeros((1, dim), np.float32), np.zeros(0, np.int64), np.zeros(0, np.float32)
    else:
        p_tab, p_row, p_w = check_prior(prior, dim, n_pts)
    with launch(threads):
        _kernel(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(cam_from_world, np.float32),
                np.ascontiguousarray(K, np.float32), np.ascontiguousarray(right, np.float64),
                np.ascontiguousarray(bottom, np.float64), float(border), np.float32(eps),
                ov_off.astype(np.int64), ov_w.astype(np.int64), ov_h.astype(np.int64),
                np.ascontiguousarray(ov_scale, np.float32), np.ascontiguousarray(table, np.float32),
                bool(use_depth), has_depth.astype(np.bool_), np.ascontiguousarray(depth_flat, np.float32),
                d_off.astype(np.int64), d_w.astype(np.int64), d_h.astype(np.int64),
                np.ascontiguousarray(d_scale, np.float32), np.float32(depth_tol),
                np.float32(distance_power), vw, p_tab, p_row, p_w, bool(raw), txt, out, count, int(block))
    return out, count


def check_prior(
    prior: tuple[np.ndarray, np.ndarray, np.ndarray], dim: int, n_pts: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # (P, D) float32, (N,) int64, (N,) float32
    """The averaging's ``prior`` (means, each point's row, its weight) as contiguous arrays of the
    kernel's dtypes; ``ValueError`` on a shape or a row out of ``[-1, P)``."""
    p_tab = np.ascontiguousarray(prior[0], np.float32)
    p_row = np.ascontiguousarray(prior[1], np.int64)
    p_w = np.ascontiguousarray(prior[2], np.float32)
    if p_tab.ndim != 2 or p_tab.shape[1] != dim or p_row.shape != (n_pts,) or p_w.shape != (n_pts,):
        raise ValueError(f"prior must be ((P, {dim}), ({n_pts},), ({n_pts},)), got {p_tab.shape}, "
                         f"{p_row.shape}, {p_w.shape}")
    if p_row.size and (p_row.max() >= p_tab.shape[0] or p_row.min() < -1):
        raise ValueError(f"prior rows must be in [-1, {p_tab.shape[0]})")
    return p_tab, p_row, p_w


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels now, on one-point problems."""
    in_view_matrix(np.zeros((1, 3), np.float32), np.eye(4, dtype=np.float32)[None],
                   np.ones((1, 4), np.float32), (1, 1), 1e-6, threads=1)
    blend_kernel(np.zeros((1, 2), np.float32), (1, 1), np.zeros((1, 1), np.int64),
                 np.zeros((1, 1, 2), np.float32), np.ones((1, 1), np.float32), threads=1)
    blend_kernel(np.zeros((1, 2), np.float32), (1, 1), np.zeros((1, 1), np.int64),
                 np.zeros((1, 1, 2), np.float32), np.ones((1, 1), np.float32), threads=1,
                 texts=np.ones((1, 2), np.float32))
    one = np.ones(1, np.int64)
    eye = np.eye(4, dtype=np.float32)[None]
    average_kernel(
        np.zeros((1, 3), np.float32), eye, np.ones((1, 4), np.float32), np.ones(1), np.ones(1), 0.0, 1e-6,
        np.zeros(1, np.int64), one, one, np.ones((1, 2), np.float32), np.zeros((1, 2), np.float32),
        use_depth=False, has_depth=np.zeros(1, bool), depth_flat=np.zeros(1, np.float32),
        d_off=np.zeros(1, np.int64), d_w=one, d_h=one, d_scale=np.ones((1, 2), np.float32), depth_tol=0.25,
        distance_power=0.0, view_weights=None, texts=np.zeros((1, 2), np.float32), threads=1)
