"""OpenScene-2D style baselines: plain multi-view averaging of OV features at 3D points.

For every point, the OV features of the views it projects into (10 px border cut) are sampled
bilinearly and averaged; with ``use_depth`` only views whose measured depth at that pixel agrees
with the point's depth (|depth - z| <= 0.25 * depth, nearest-pixel lookup) count. The mapper's
``average`` and ``average_depth`` segmentation methods call ``average_features``.

Chunked over points. Per chunk the points are projected into every view at once (torch, as
before); the samples of all views are then gathered as one weighted sum per point with
``embedding_bag`` over the views' flattened (h * w, D) maps (bilinear corners and weights
computed exactly as ``grid_sample`` with border padding does), so the (m, D) samples are never
materialised per view; the selection, depth test and corners run once over all (view, point)
pairs of a chunk, taken point-major so that each point's taps are contiguous for the bag.
``average_features_reference`` is the previous per-view implementation.

On a CPU device both run as one compiled kernel instead
(:mod:`mapper.kernels.average_kernel`: the same views and taps per point, no per-pair arrays);
``impl="torch"`` keeps the torch / numpy path above (what other devices use).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.checks import check_shape
from mapper.kernels import average as _average
from mapper.kernels.average import OVView
from mapper.model.ops.geometry import (
    DEFAULT_EPS,
    in_view,
    invert_pose,
    project_points,
    sample_bilinear,
    sample_nearest,
    scale_uv,
)

__all__ = ["OVView", "average_features", "average_features_reference", "average_similarities"]


def _as_tensor(x: np.ndarray | Tensor, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(x, Tensor):
        return x.to(device=device, dtype=dtype)
    # read-only arrays (e.g. the protocol's decoded frames) are copied: torch needs writable memory
    return torch.from_numpy(np.require(x, requirements=["C", "W"])).to(device=device, dtype=dtype)



def _parse_inputs(
    points: np.ndarray | Tensor,
    views: Sequence[OVView | tuple],
    *,
    use_depth: bool,
    border_px: float,
    depth_rel_tol: float,
    chunk: int,
    view_weights: np.ndarray | Tensor | None,
    device: torch.device,
) -> tuple[Tensor, list[OVView], Tensor | None, int]:
    """Validate the averaging inputs (raising ``ValueError`` at once) for both implementations.
    Returns (points (N, 3) float32, the views that count (with depth where ``use_depth``), their
    (V', N) weights or None, the feature dimension D (0 without views))."""
    if depth_rel_tol < 0:
        raise ValueError(f"depth_rel_tol {depth_rel_tol} must be >= 0")
    if chunk < 1:
        raise ValueError(f"chunk {chunk} must be >= 1")
    if border_px < 0:
        raise ValueError(f"border_px {border_px} must be >= 0")
    pts = _as_tensor(points, torch.float32, device)
    check_shape(pts, "N 3", "points must have shape (N points, xyz)")
    parsed = [OVView(*v) for v in views]
    for i, v in enumerate(parsed):
        check_shape(v.ov, "h w D", f"view {i}: ov")
        if len(v.image_wh) != 2 or min(v.image_wh) < 1:
            raise ValueError(f"view {i}: image_wh must be (W, H) >= 1, got {v.image_wh}")
    dims = {int(v.ov.shape[-1]) for v in parsed}
    if len(dims) > 1:
        raise ValueError(f"views have OV features of different dimensions {sorted(dims)}")
    dim = dims.pop() if dims else 0
    n_pts = pts.shape[0]
    view_ids = [i for i, v in enumerate(parsed) if not use_depth or v.depth_m is not None]
    vw = None
    if view_weights is not None:
        vw = _as_tensor(view_weights, torch.float32, device)
        check_shape(vw, "V N", "view_weights must have shape (V views, N points)",
                    {"V": len(parsed), "N": n_pts})
        if not bool((vw >= 0).all()):
            raise ValueError("view_weights must be >= 0")
        vw = vw[view_ids]
    parsed = [parsed[i] for i in view_ids]
    return pts, parsed, vw, dim


def _view_arrays(
    parsed: list[OVView], *, use_depth: bool, device: torch.device
) -> tuple[Tensor, Tensor, _average.ViewArrays]:
    """The kernel driver's per-view constants (:func:`mapper.kernels.average.view_arrays`), and
    its ``cam_from_world`` (V, 4, 4) and ``K`` (V, 4) as float32 tensors on ``device`` (the torch
    path)."""
    va = _average.view_arrays(parsed, use_depth=use_depth)
    return torch.from_numpy(va.cam_from_world).to(device), torch.from_numpy(va.K).to(device), va


def _kernel_average(
    pts: Tensor,  # (N, 3) float32
    parsed: list[OVView],
    *,
    use_depth: bool,
    border_px: float,
    depth_rel_tol: float,
    distance_power: float,
    vw: Tensor | None,  # (V, N) float32
    dim: int,
    texts: Tensor | None,  # (T, D) float32
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,  # (P, D), (N,) int64, (N,) float32
    raw: bool = False,
    cache_table: bool = True,
) -> tuple[Tensor, Tensor]:
    """The CPU path of :func:`average_features` (``texts`` None: (N, D) unit features, or with
    ``raw`` the means themselves) and :func:`average_similarities` ((N, T) cosines): one compiled
    kernel, and the views counted (N,). ``prior``: see :func:`average_similarities`.
    ``cache_table`` False builds the views' OV table without replacing the cached one (the
    window's, which the next query reuses)."""
    out, count = _average.kernel_average(
        pts.cpu().numpy(), parsed, use_depth=use_depth, border_px=border_px, depth_rel_tol=depth_rel_tol,
        distance_power=distance_power, vw=None if vw is None else vw.cpu().numpy(), dim=dim,
        texts=None if texts is None else texts.cpu().numpy(), threads=torch.get_num_threads(), prior=prior,
        raw=raw, cache_table=cache_table)
    return torch.from_numpy(out), torch.from_numpy(count)


def view_samples(
    points: np.ndarray,  # (N, 3) float32 world metres
    view: OVView | tuple,
    *,
    use_depth: bool,
    border_px: float = 10.0,
    depth_rel_tol: float = 0.25,
) -> tuple[np.ndarray, np.ndarray]:
    """One view's contribution to :func:`average_features` at each point, with the same selection
    (in front, inside the image less ``border_px``, the depth test with ``use_depth``): (features
    (N, D) float32, the bilinear OV sample where the view counts and 0 elsewhere; counted (N,) bool).
    A view without depth counts nowhere with ``use_depth``. The compiled kernel (CPU); the cached
    OV table of the window's queries is left alone."""
    pts, parsed, _, dim = _parse_inputs(points, [view], use_depth=use_depth, border_px=border_px,
                                        depth_rel_tol=depth_rel_tol, chunk=1, view_weights=None,
                                        device=torch.device("cpu"))
    if not parsed or pts.shape[0] == 0:
        d = int(OVView(*view).ov.shape[-1])
        return np.zeros((pts.shape[0], d), np.float32), np.zeros(pts.shape[0], bool)
    feats, count = _kernel_average(pts, parsed, use_depth=use_depth, border_px=border_px,
                                   depth_rel_tol=depth_rel_tol, distance_power=0.0, vw=None, dim=dim,
                                   texts=None, raw=True, cache_table=False)
    return feats.numpy(), count.numpy() > 0


def average_features_reference(
    points: np.ndarray | Tensor,
    views: Sequence[OVView | tuple],
    *,
    use_depth: bool,
    border_px: float = 10.0,
    depth_rel_tol: float = 0.25,
    chunk: int = 16384,
    distance_power: float = 0.0,
    view_weights: np.ndarray | Tensor | None = None,
    device: str | torch.device = "cpu",
) -> tuple[Tensor, Tensor]:
    """The previous implementation of :func:`average_features` (per view and chunk: ``grid_sample``
    of the whole (D, h, w) map and ``index_add_`` of (m, D) rows), kept as the reference the
    tests and ``benchmarks/speed/bench_averaging.py`` compare the fast path with. Same arguments and
    results (up to float rounding).

    Args:
        points: (N, 3) world points (m).
        views: V views, each ``OVView`` or a tuple ``(ov (h, w, D), K (4,), world_from_cam
            (4, 4), (W, H), depth_m (H', W') | None)``; all ``ov`` share D.
        use_depth: keep a view only where |depth - z| <= depth_rel_tol * depth at the point's
            pixel (nearest pixel; depth 0 = unknown fails the test). Views without depth are
            then skipped entirely.
        border_px: points projecting closer than this (full-image pixels) to the edge are out.
        depth_rel_tol: relative depth tolerance of the depth test (0.25 in OpenScene/GOV-NeSF).
        chunk: points per chunk (bounds memory: about chunk x D x 8 bytes per view sample).
        distance_power: weight each view by z ** -distance_power (0 = plain mean); the
            "visible views weighted by distance" oracle of the reference numbers uses > 0.
        view_weights: optional (V, N) float >= 0 (or bool): multiplies view v's weight for point
            n; 0 / False excludes it on top of the other tests (e.g. a ray-cast visibility
            oracle, or an oracle weighting by known view quality). Rows follow ``views``.
        device: torch device for the computation.

    Returns:
        features: (N, D) float32, L2-normalised weighted mean (zero rows where no view counts).
        n_views: (N,) int64, number of views that counted for each point.
    """
    device = torch.device(device)
    pts, parsed, vw, dim = _parse_inputs(points, views, use_depth=use_depth, border_px=border_px,
                                         depth_rel_tol=depth_rel_tol, chunk=chunk,
                                         view_weights=view_weights, device=device)
    n_pts = pts.shape[0]
    feats = torch.zeros(n_pts, dim, dtype=torch.float32, device=device)
    n_views = torch.zeros(n_pts, dtype=torch.int64, device=device)
    if not parsed or n_pts == 0:
        return feats, n_views

    # Per-view constants once (small): poses, intrinsics; maps are converted per chunk.
    cam_from_world = invert_pose(torch.stack([_as_tensor(v.world_from_cam, torch.float32, device)
                                              for v in parsed]))  # (V, 4, 4)
    Ks = torch.stack([_as_tensor(v.K, torch.float32, device) for v in parsed])  # (V, 4)

    for start in range(0, n_pts, chunk):
        p = pts[start:start + chunk]  # (n, 3)
        acc = torch.zeros(p.shape[0], dim, dtype=torch.float32, device=device)
        wsum = torch.zeros(p.shape[0], dtype=torch.float32, device=device)
        count = torch.zeros(p.shape[0], dtype=torch.int64, device=device)
        uv_all, z_all = project_points(p, Ks, cam_from_world)  # (V, n, 2), (V, n)
        for i, v in enumerate(parsed):
            width, height = int(v.image_wh[0]), int(v.image_wh[1])
            uv, z = uv_all[i], z_all[i]
            ok = in_view(uv, z, width, height, border_px=border_px)  # (n,)
            if vw is not None:
                ok &= vw[i, start:start + chunk] > 0
            if not bool(ok.any()):
                continue
            idx = ok.nonzero().squeeze(1)
            uv_ok, z_ok = uv[idx], z[idx]
            if use_depth:
                assert v.depth_m is not None  # checked when the views were parsed
                depth = _as_tensor(v.depth_m, torch.float32, device)  # (H', W')
                duv = scale_uv(uv_ok, (width, height), (depth.shape[1], depth.shape[0]))
                d, _ = sample_nearest(depth[None], duv)  # (m, 1)
                d = d[:, 0]
                keep = (d > 0) & ((d - z_ok).abs() <= depth_rel_tol * d)
                idx, uv_ok, z_ok = idx[keep], uv_ok[keep], z_ok[keep]
                if idx.numel() == 0:
                    continue
            ov = _as_tensor(v.ov, torch.float32, device).permute(2, 0, 1)  # (D, h, w)
            fuv = scale_uv(uv_ok, (width, height), (ov.shape[2], ov.shape[1]))
            vals, _ = sample_bilinear(ov, fuv)  # (m, D)
            w = z_ok.clamp_min(1e-6) ** (-distance_power) if distance_power else torch.ones_like(z_ok)
            if vw is not None:
                w = w * vw[i, start:start + chunk][idx]
            acc.index_add_(0, idx, vals * w[:, None])
            wsum.index_add_(0, idx, w)
            count.index_add_(0, idx, torch.ones_like(idx))
        seen = count > 0
        acc[seen] /= wsum[seen, None]
        feats[start:start + chunk] = F.normalize(acc, dim=1) * seen[:, None]
        n_views[start:start + chunk] = count
    return feats, n_views


def average_features(
    points: np.ndarray | Tensor,
    views: Sequence[OVView | tuple],
    *,
    use_depth: bool,
    border_px: float = 10.0,
    depth_rel_tol: float = 0.25,
    chunk: int = 16384,
    distance_power: float = 0.0,
    view_weights: np.ndarray | Tensor | None = None,
    device: str | torch.device = "cpu",
    max_table_bytes: int = 256 << 20,
    impl: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Multi-view average of OV features at 3D points (OpenScene-2D baseline).

    Args:
        points: (N, 3) world points (m).
        views: V views, each ``OVView`` or a tuple ``(ov (h, w, D), K (4,), world_from_cam
            (4, 4), (W, H), depth_m (H', W') | None)``; all ``ov`` share D.
        use_depth: keep a view only where |depth - z| <= depth_rel_tol * depth at the point's
            pixel (nearest pixel; depth 0 = unknown fails the test). Views without depth are
            then skipped entirely.
        border_px: points projecting closer than this (full-image pixels) to the edge are out.
        depth_rel_tol: relative depth tolerance of the depth test (0.25 in OpenScene/GOV-NeSF).
        chunk: points per chunk (bounds memory: the projections of a chunk into every view).
        distance_power: weight each view by z ** -distance_power (0 = plain mean); the
            "visible views weighted by distance" oracle of the reference numbers uses > 0.
        view_weights: optional (V, N) float >= 0 (or bool): multiplies view v's weight for point
            n; 0 / False excludes it on top of the other tests (e.g. a ray-cast visibility
            oracle, or an oracle weighting by known view quality). Rows follow ``views``.
        device: torch device for the computation.
        max_table_bytes: the views' float32 (h * w, D) maps are gathered from tables of at most
            about this size (views are taken in groups; one view larger than this is one group);
            the torch path only.
        impl: ``"auto"`` (the compiled kernel on a CPU device, the torch path elsewhere),
            ``"kernel"`` or ``"torch"``.

    Returns:
        features: (N, D) float32, L2-normalised weighted mean (zero rows where no view counts).
        n_views: (N,) int64, number of views that counted for each point.
    """
    if _use_kernel(impl, device, max_table_bytes):
        pts, parsed, vw, dim = _parse_inputs(points, views, use_depth=use_depth, border_px=border_px,
                                             depth_rel_tol=depth_rel_tol, chunk=chunk,
                                             view_weights=view_weights, device=torch.device("cpu"))
        if not parsed or pts.shape[0] == 0:
            return (torch.zeros(pts.shape[0], dim, dtype=torch.float32),
                    torch.zeros(pts.shape[0], dtype=torch.int64))
        return _kernel_average(pts, parsed, use_depth=use_depth, border_px=border_px,
                               depth_rel_tol=depth_rel_tol, distance_power=distance_power, vw=vw, dim=dim,
                               texts=None)
    n_pts, dim, chunks = _average_chunks(
        points, views, use_depth=use_depth, border_px=border_px, depth_rel_tol=depth_rel_tol, chunk=chunk,
        distance_power=distance_power, view_weights=view_weights, device=device,
        max_table_bytes=max_table_bytes)
    device = torch.device(device)
    feats = torch.empty(n_pts, dim, dtype=torch.float32, device=device)
    n_views = torch.zeros(n_pts, dtype=torch.int64, device=device)
    for start, acc, count in chunks:
        out = feats[start:start + count.shape[0]]
        if acc is None:
            out.zero_()
        else:  # F.normalize (eps 1e-12), in place into the result
            norm = torch.linalg.vector_norm(acc, dim=1, keepdim=True).clamp_min_(1e-12)
            torch.div(acc, norm, out=out)
        n_views[start:start + count.shape[0]] = count
    return feats, n_views


def average_similarities(
    points: np.ndarray | Tensor,
    views: Sequence[OVView | tuple],
    text_emb: np.ndarray | Tensor,
    *,
    use_depth: bool,
    border_px: float = 10.0,
    depth_rel_tol: float = 0.25,
    chunk: int = 16384,
    device: str | torch.device = "cpu",
    max_table_bytes: int = 256 << 20,
    impl: str = "auto",
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[Tensor, Tensor]:
    """Cosines between :func:`average_features` and texts, without keeping the (N, D) features.

    Args:
        points, views, use_depth, border_px, depth_rel_tol, chunk, device, max_table_bytes, impl: as
            in :func:`average_features`.
        text_emb: (T, D) float32 text embeddings (unit rows for cosines).
        prior: optional ``(means (P, D) float32, row (N,) int64 (-1: none), weight (N,) float32)``:
            point n's average also takes ``means[row[n]]`` as the mean of ``weight[n]`` more views
            (views no longer given, e.g. keyframes that left the node's window; with uniform view
            weights the result is the average over both sets). The compiled CPU path only
            (``ValueError`` elsewhere). ``n_views`` still counts the given views only.

    Returns:
        similarities: (N, T) float32, ``average_features(...)[0] @ text_emb.T`` (zero rows where no
            view counts).
        n_views: (N,) int64, number of views that counted for each point.
    """
    device = torch.device(device)
    texts = _as_tensor(text_emb, torch.float32, device)
    check_shape(texts, "T D", "text_emb must have shape (T texts, D)")
    if _use_kernel(impl, device, max_table_bytes):
        pts, parsed, _, dim = _parse_inputs(points, views, use_depth=use_depth, border_px=border_px,
                                            depth_rel_tol=depth_rel_tol, chunk=chunk, view_weights=None,
                                            device=torch.device("cpu"))
        if dim and texts.shape[1] != dim:
            raise ValueError(f"text_emb has dimension {texts.shape[1]}, the views' features {dim}")
        if not parsed and prior is not None and pts.shape[0] > 0:
            # no view here: the prior alone (a placeholder view that counts nowhere)
            return _prior_only_similarities(pts, prior, texts)
        if not parsed or pts.shape[0] == 0:
            return (torch.zeros(pts.shape[0], texts.shape[0], dtype=torch.float32),
                    torch.zeros(pts.shape[0], dtype=torch.int64))
        return _kernel_average(pts, parsed, use_depth=use_depth, border_px=border_px,
                               depth_rel_tol=depth_rel_tol, distance_power=0.0, vw=None, dim=dim, texts=texts,
                               prior=prior)
    if prior is not None:
        raise ValueError("prior is supported by the compiled CPU path only (impl 'auto' on a CPU device)")
    n_pts, dim, chunks = _average_chunks(
        points, views, use_depth=use_depth, border_px=border_px, depth_rel_tol=depth_rel_tol, chunk=chunk,
        distance_power=0.0, view_weights=None, device=device, max_table_bytes=max_table_bytes)
    if dim and texts.shape[1] != dim:
        raise ValueError(f"text_emb has dimension {texts.shape[1]}, the views' features {dim}")
    sims = torch.zeros(n_pts, texts.shape[0], dtype=torch.float32, device=device)
    n_views = torch.zeros(n_pts, dtype=torch.int64, device=device)
    for start, acc, count in chunks:
        stop = start + count.shape[0]
        if acc is not None:
            norm = torch.linalg.vector_norm(acc, dim=1, keepdim=True).clamp_min_(1e-12)
            sims[start:stop] = (acc @ texts.T) / norm
        n_views[start:stop] = count
    return sims, n_views


def _prior_only_similarities(
    pts: Tensor,  # (N, 3)
    prior: tuple[np.ndarray, np.ndarray, np.ndarray],
    texts: Tensor,  # (T, D)
) -> tuple[Tensor, Tensor]:
    """:func:`average_similarities` with a prior and no view: the prior rows' cosines."""
    sims, count = _average.prior_only_similarities(int(pts.shape[0]), prior, texts.numpy())
    return torch.from_numpy(sims), torch.from_numpy(count)


def _use_kernel(impl: str, device: str | torch.device, max_table_bytes: int) -> bool:
    """Whether the compiled CPU kernel answers (``impl`` "auto" on a CPU device, or "kernel");
    checks the arguments both paths share."""
    if max_table_bytes < 1:
        raise ValueError(f"max_table_bytes {max_table_bytes} must be >= 1")
    if impl not in ("auto", "kernel", "torch"):
        raise ValueError(f"impl {impl!r} must be one of auto, kernel, torch")
    if impl == "kernel" and torch.device(device).type != "cpu":
        raise ValueError(f"impl 'kernel' runs on the CPU, not on device {device}")
    return impl == "kernel" or (impl == "auto" and torch.device(device).type == "cpu")


def _average_chunks(
    points: np.ndarray | Tensor,
    views: Sequence[OVView | tuple],
    *,
    use_depth: bool,
    border_px: float,
    depth_rel_tol: float,
    chunk: int,
    distance_power: float,
    view_weights: np.ndarray | Tensor | None,
    device: str | torch.device,
    max_table_bytes: int,
) -> tuple[int, int, Iterator[tuple[int, Tensor | None, Tensor]]]:
    """Validates the inputs (raising at once) and returns (N, D, chunks); each chunk is
    ``(start, acc (n, D) weighted mean or None when no view counts, count (n,) int64)``."""
    if max_table_bytes < 1:
        raise ValueError(f"max_table_bytes {max_table_bytes} must be >= 1")
    device = torch.device(device)
    pts, parsed, vw, dim = _parse_inputs(points, views, use_depth=use_depth, border_px=border_px,
                                         depth_rel_tol=depth_rel_tol, chunk=chunk,
                                         view_weights=view_weights, device=device)
    n_pts = pts.shape[0]
    if not parsed or n_pts == 0:
        empty = [(start, None, torch.zeros(min(chunk, n_pts - start), dtype=torch.int64, device=device))
                 for start in range(0, n_pts, chunk)]
        return n_pts, dim, iter(empty)
    return n_pts, dim, _chunks(
        pts, parsed, use_depth=use_depth, border_px=border_px, depth_rel_tol=depth_rel_tol, chunk=chunk,
        distance_power=distance_power, vw=vw, dim=dim, device=device, max_table_bytes=max_table_bytes)


def _chunks(
    pts: Tensor,  # (N, 3)
    parsed: list[OVView],
    *,
    use_depth: bool,
    border_px: float,
    depth_rel_tol: float,
    chunk: int,
    distance_power: float,
    vw: Tensor | None,  # (V, N) or None
    dim: int,
    device: torch.device,
    max_table_bytes: int,
) -> Iterator[tuple[int, Tensor | None, Tensor]]:
    # The projection (one batched op per chunk) and the gather (one embedding_bag per chunk and
    # group) run in torch; the selection, depth test and corner weights are float32 numpy ops over
    # all (view, point) pairs of a chunk at once, with each view's sizes broadcast per pair (the
    # same IEEE arithmetic as the torch ops of the reference). The pairs are taken point-major
    # (``nonzero`` of the (n, V) mask), so each point's taps are contiguous for ``embedding_bag``
    # in view order, as the reference sums them, without sorting.
    n_pts = pts.shape[0]
    n_views = len(parsed)
    cam_from_world, Ks, va = _view_arrays(parsed, use_depth=use_depth, device=device)
    vw_np = None if vw is None else vw.cpu().numpy()  # (V, N) float32
    img_w, img_h, ov_w, ov_h, ov_scale = va.img_w, va.img_h, va.ov_w, va.ov_h, va.ov_scale
    has_depth, d_w, d_h, d_scale, d_off, depth_flat = (va.has_depth, va.d_w, va.d_h, va.d_scale, va.d_off,
                                                       va.depth_flat)
    # Groups of views whose flattened maps form one gather table of <= max_table_bytes.
    groups: list[list[int]] = []
    size = 0
    for i, v in enumerate(parsed):
        nbytes = int(v.ov.shape[0]) * int(v.ov.shape[1]) * dim * 4
        if not groups or size + nbytes > max_table_bytes:
            groups.append([])
            size = 0
        groups[-1].append(i)
        size += nbytes
    group_of = np.zeros(n_views, np.int64)
    offsets = np.zeros(n_views, np.int64)  # each view's first row in its group's table
    for g, group in enumerate(groups):
        off = 0
        for i in group:
            group_of[i], offsets[i] = g, off
            off += int(ov_w[i] * ov_h[i])
    tables: list[Tensor | None] = [None] * len(groups)  # (sum h * w, D) float32, built when first hit
    eps = np.float32(DEFAULT_EPS)
    right = (img_w - border_px)[:, None]  # (V, 1) float64, as ``width - border_px`` per view
    bottom = (img_h - border_px)[:, None]

    def per_pair(values: np.ndarray, view: np.ndarray) -> np.ndarray:
        """A per-view value (V, ...) for each pair: one row when every view has the same (a
        window of one camera: no (m, ...) gather), else ``values[view]``."""
        return values[0] if (values == values[0]).all() else values[view]

    for start in range(0, n_pts, chunk):
        p = pts[start:start + chunk]  # (n, 3)
        n = p.shape[0]
        uv_t, z_t = project_points(p, Ks, cam_from_world)  # (V, n, 2), (V, n)
        uv_all, z_all = uv_t.cpu().numpy(), z_t.cpu().numpy()
        u_px, v_px = uv_all[..., 0], uv_all[..., 1]  # (V, n)
        ok = ((z_all > eps) & (u_px >= border_px) & (u_px <= right)
              & (v_px >= border_px) & (v_px <= bottom))  # in_view, (V, n)
        if vw_np is not None:
            ok &= vw_np[:, start:start + chunk] > 0
        pt, view = np.nonzero(ok.T)  # (m,) pairs, point-major, views ascending within a point
        uv_ok, z_ok = uv_all[view, pt], z_all[view, pt]  # (m, 2), (m,)
        if depth_flat is not None:  # only with use_depth
            tested = per_pair(has_depth, view)
            duv = uv_ok * per_pair(d_scale, view)  # scale_uv
            dw_pair = per_pair(d_w, view)
            col = np.clip(np.floor(duv[:, 0]), 0, dw_pair - 1).astype(np.int64)  # sample_nearest
            row = np.clip(np.floor(duv[:, 1]), 0, per_pair(d_h, view) - 1).astype(np.int64)
            d = depth_flat[d_off[view] + row * dw_pair + col]
            keep = (d > 0) & (np.abs(d - z_ok) <= depth_rel_tol * d)
            if not tested.all():
                keep |= ~tested
            pt, view, uv_ok, z_ok = pt[keep], view[keep], uv_ok[keep], z_ok[keep]
        if distance_power:
            w = np.maximum(z_ok, np.float32(1e-6)) ** np.float32(-distance_power)
        else:
            w = np.ones_like(z_ok)
        if vw_np is not None:
            w = w * vw_np[view, start + pt]
        count = np.bincount(pt, minlength=n).astype(np.int64)  # (n,)
        wsum = np.bincount(pt, weights=w, minlength=n).astype(np.float32)
        seen = count > 0
        inv = np.zeros(n, np.float32)
        inv[seen] = np.float32(1.0) / wsum[seen]
        corner, bw = _bilinear_corners_np(uv_ok * per_pair(ov_scale, view), per_pair(ov_w, view),
                                          per_pair(ov_h, view))  # (m, 4) each
        cols_all = corner + offsets[view, None]
        wts_all = bw * (w * inv[pt])[:, None]
        acc: Tensor | None = None  # (n, D) weighted means; rows without samples are zero
        for g, group in enumerate(groups):
            sel = slice(None) if len(groups) == 1 else np.flatnonzero(group_of[view] == g)
            rows = pt[sel]
            if rows.size == 0:
                continue
            table = tables[g]
            if table is None:
                table = torch.cat([
                    _as_tensor(parsed[i].ov, torch.float32, device).reshape(-1, dim) for i in group
                ])
                tables[g] = table
            bag_len = np.bincount(rows, minlength=n) * 4  # (n,)
            bag_off = np.cumsum(bag_len) - bag_len
            part = F.embedding_bag(
                torch.from_numpy(np.ascontiguousarray(cols_all[sel]).reshape(-1)).to(device), table,
                torch.from_numpy(bag_off).to(device), mode="sum",
                per_sample_weights=torch.from_numpy(np.ascontiguousarray(wts_all[sel]).reshape(-1)).to(device),
            )  # (n, D)
            acc = part if acc is None else acc.add_(part)
        yield start, acc, torch.from_numpy(count).to(device)


def _bilinear_corners_np(
    fuv: np.ndarray, width: int | np.ndarray, height: int | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Corners and weights of ``grid_sample(mode="bilinear", padding_mode="border",
    align_corners=False)`` at float32 pixel coordinates ``fuv`` (m, 2) of a (height, width) map
    (one size, or (m,) int sizes, one per coordinate): flat indices (m, 4) int64 into the
    row-major map and float32 weights (m, 4)."""
    w_i = np.asarray(width, np.int64)
    h_i = np.asarray(height, np.int64)
    w_f, h_f = w_i.astype(np.float32), h_i.astype(np.float32)  # exact for any map size
    size = np.stack(np.broadcast_arrays(w_f, h_f), axis=-1)  # (2,) or (m, 2)
    grid = np.clip(2.0 * fuv / size - 1.0, -2.0, 2.0)
    # grid_sample's unnormalisation (align_corners=False) and border padding (clip the coordinate)
    ix = np.clip(((grid[:, 0] + 1.0) * w_f - 1.0) / 2.0, 0.0, w_f - 1.0)
    iy = np.clip(((grid[:, 1] + 1.0) * h_f - 1.0) / 2.0, 0.0, h_f - 1.0)
    x0f, y0f = np.floor(ix), np.floor(iy)
    tx, ty = ix - x0f, iy - y0f
    x0, y0 = x0f.astype(np.int64), y0f.astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w_i - 1), np.minimum(y0 + 1, h_i - 1)
    idx = np.stack([y0 * w_i + x0, y0 * w_i + x1, y1 * w_i + x0, y1 * w_i + x1], axis=1)
    w = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], axis=1)
    return idx, w
