"""The multi-view averaging (OpenScene-2D) on numpy arrays: the driver of the compiled kernel
(:mod:`mapper.kernels.average_kernel`), torch-free.

The node's ``average`` / ``average_depth`` answers call :func:`average_similarities` here;
:mod:`mapper.model.baselines` (the torch API with its slow reference path) calls the same
:func:`kernel_average` on a CPU device, so there is one implementation. The per-view constants are
computed as the reference computes them (camera-from-world as ``[R^T, -R^T t]`` in float32, the
``R^T t`` sums in the same order as torch's), so the views that count are the reference's.

Example::

    >>> import numpy as np
    >>> ov = np.zeros((6, 8, 2), np.float32); ov[..., 0] = 1.0          # every pixel says text 0
    >>> view = OVView(ov, np.array([40.0, 40.0, 32.0, 24.0]), np.eye(4), (64, 48), None)
    >>> sims, n = average_similarities(np.array([[0.0, 0.0, 2.0]], np.float32), [view],
    ...                                np.eye(2, dtype=np.float32), use_depth=False)
    >>> sims.tolist(), n.tolist()
    ([[1.0, 0.0]], [1])
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from mapper.checks import check_shape
from mapper.kernels import average_kernel as _kernel

__all__ = ["DEFAULT_EPS", "OVView", "ViewArrays", "average_similarities", "kernel_average", "view_arrays"]

DEFAULT_EPS = 1e-6
"""Smallest camera-frame depth (metres) that counts as in front of the camera (the model's
``mapper.model.ops.geometry.DEFAULT_EPS``)."""


class OVView(NamedTuple):
    """One view for averaging (a plain tuple in this order works too)."""

    ov: Any
    """(h, w, D) OV feature map (any resolution; it covers the whole image): numpy or torch."""
    K: Any
    """(4,) [fx, fy, cx, cy] for the full image of size ``image_wh``."""
    world_from_cam: Any
    """(4, 4) camera-to-world pose."""
    image_wh: tuple[int, int]
    """(W, H) of the image ``K`` refers to."""
    depth_m: Any
    """(H', W') z-depth in metres (0 = unknown), any resolution covering the image; or None."""


def _numpy(x: Any, dtype: Any) -> np.ndarray:
    """``x`` (numpy array or CPU torch tensor) as a numpy array of ``dtype``."""
    if hasattr(x, "detach"):  # a torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x).astype(dtype, copy=False)


class ViewArrays(NamedTuple):
    """Per-view constants of the averaging, V views."""

    cam_from_world: np.ndarray  # (V, 4, 4) float32
    K: np.ndarray  # (V, 4) float32
    img_w: np.ndarray  # (V,) int64 image size
    img_h: np.ndarray
    ov_w: np.ndarray  # (V,) int64 OV map size
    ov_h: np.ndarray
    ov_scale: np.ndarray  # (V, 2) float32 OV map size / image size
    has_depth: np.ndarray  # (V,) bool: a depth map that the depth test reads
    d_w: np.ndarray  # (V,) int64 depth map size (1 without)
    d_h: np.ndarray
    d_scale: np.ndarray  # (V, 2) float32 depth map size / image size
    d_off: np.ndarray  # (V,) int64 offset of each view's depth map in ``depth_flat``
    depth_flat: np.ndarray | None  # (S,) float32 the depth maps one after another; None without


def invert_poses(world_from_cam: np.ndarray) -> np.ndarray:
    """(V, 4, 4) float32 ``cam_from_world`` = ``[R^T, -R^T t]`` of (V, 4, 4) float32 poses, with the
    sums of ``R^T t`` in the order torch's ``invert_pose`` takes them (bit-equal on CPU)."""
    rot_t = np.swapaxes(world_from_cam[:, :3, :3], 1, 2)
    out = np.zeros_like(world_from_cam)
    out[:, :3, :3] = rot_t
    out[:, :3, 3] = -np.einsum("vij,vj->vi", rot_t, world_from_cam[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def view_arrays(parsed: Sequence[OVView], *, use_depth: bool) -> ViewArrays:
    """The kernel's per-view constants of ``parsed`` (depth maps only with ``use_depth``)."""
    poses = np.stack([_numpy(v.world_from_cam, np.float32) for v in parsed])  # (V, 4, 4)
    Ks = np.stack([_numpy(v.K, np.float32) for v in parsed])  # (V, 4)
    img_w = np.array([int(v.image_wh[0]) for v in parsed], np.int64)  # (V,)
    img_h = np.array([int(v.image_wh[1]) for v in parsed], np.int64)
    ov_w = np.array([int(v.ov.shape[1]) for v in parsed], np.int64)
    ov_h = np.array([int(v.ov.shape[0]) for v in parsed], np.int64)
    ov_scale = np.stack([np.array([w_ / w, h_ / h], np.float32)
                         for w_, h_, w, h in zip(ov_w, ov_h, img_w, img_h, strict=True)])  # (V, 2)
    depths = [_numpy(v.depth_m, np.float32) if use_depth and v.depth_m is not None else None
              for v in parsed]  # (H', W') each
    has_depth = np.array([d is not None for d in depths], bool)  # (V,)
    d_w = np.array([d.shape[1] if d is not None else 1 for d in depths], np.int64)
    d_h = np.array([d.shape[0] if d is not None else 1 for d in depths], np.int64)
    d_scale = np.stack([np.array([dw / w, dh / h], np.float32)
                        for dw, dh, w, h in zip(d_w, d_h, img_w, img_h, strict=True)])  # (V, 2)
    d_off = np.concatenate([[0], np.cumsum(d_w * d_h)])[:-1]  # (V,)
    depth_flat = None  # the views' depth maps, flattened one after another
    if has_depth.any():
        depth_flat = np.concatenate([np.zeros(1, np.float32) if d is None else d.reshape(-1) for d in depths])
    return ViewArrays(invert_poses(poses), Ks, img_w, img_h, ov_w, ov_h, ov_scale, has_depth, d_w, d_h,
                      d_scale, d_off, depth_flat)


_TABLE_CACHE: list[tuple[tuple[Any, ...], np.ndarray]] = []
"""The last OV table the kernel read and what it was made of (the views' ``ov`` objects, which it
keeps alive); guarded by ``_TABLE_LOCK``."""
_TABLE_LOCK = threading.Lock()


def ov_table(parsed: Sequence[OVView], dim: int, *, cache: bool = True) -> np.ndarray:
    """(R, D) float32: the views' OV maps, row-major, one after another (the kernel's ``table``).
    The same views' ``ov`` objects as the last call (a window asked again) reuse that table: no
    new 10-20 MB array per query, and the kernel reads memory it read before. ``cache`` False:
    built for this call only, the cached one (the window's) left in place."""
    if not cache:
        return np.concatenate([_numpy(v.ov, np.float32).reshape(-1, dim) for v in parsed])
    key = tuple(v.ov for v in parsed)
    with _TABLE_LOCK:
        if _TABLE_CACHE and len(_TABLE_CACHE[0][0]) == len(key) and all(
            a is b for a, b in zip(_TABLE_CACHE[0][0], key, strict=True)
        ):
            return _TABLE_CACHE[0][1]
    table = np.concatenate([_numpy(v.ov, np.float32).reshape(-1, dim) for v in parsed])
    table.setflags(write=False)
    with _TABLE_LOCK:
        _TABLE_CACHE[:] = [(key, table)]
    return table


def kernel_average(
    pts: np.ndarray,  # (N, 3) float32
    parsed: Sequence[OVView],
    *,
    use_depth: bool,
    border_px: float,
    depth_rel_tol: float,
    distance_power: float,
    vw: np.ndarray | None,  # (V, N) float32
    dim: int,
    texts: np.ndarray | None,  # (T, D) float32
    threads: int = 0,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,  # (P, D), (N,) int64, (N,) float32
    raw: bool = False,
    cache_table: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """One launch of the compiled averaging over the views ``parsed`` (those that count):
    ``texts`` None: (N, D) unit features (or with ``raw`` the means themselves), else (N, T)
    cosines; and the views counted (N,) int64. ``threads`` 0: numba's default. ``prior``: the
    running means of views no longer given (:func:`average_similarities`). ``cache_table`` False
    builds the views' OV table without replacing the cached one (the window's)."""
    va = view_arrays(parsed, use_depth=use_depth)
    ov_off = np.concatenate([[0], np.cumsum(va.ov_w * va.ov_h)])[:-1]  # (V,)
    table = ov_table(parsed, dim, cache=cache_table)  # (R, D)
    right = (va.img_w - border_px).astype(np.float64)  # (V,) as ``width - border_px`` per view
    bottom = (va.img_h - border_px).astype(np.float64)
    depth_flat = np.zeros(1, np.float32) if va.depth_flat is None else va.depth_flat
    return _kernel.average_kernel(
        np.ascontiguousarray(pts, np.float32), va.cam_from_world, va.K, right, bottom, float(border_px),
        float(DEFAULT_EPS), ov_off, va.ov_w, va.ov_h, va.ov_scale, table,
        use_depth=use_depth and va.depth_flat is not None, has_depth=va.has_depth, depth_flat=depth_flat,
        d_off=va.d_off, d_w=va.d_w, d_h=va.d_h, d_scale=va.d_scale, depth_tol=depth_rel_tol,
        distance_power=distance_power, view_weights=vw, texts=texts, threads=threads, prior=prior, raw=raw)


def prior_only_similarities(
    n: int,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray],
    texts: np.ndarray,  # (T, D) float32
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`average_similarities` with a prior and no view: the prior rows' cosines."""
    table, row, weight = _kernel.check_prior(prior, int(texts.shape[1]), n)
    sims = np.zeros((n, texts.shape[0]), np.float32)
    use = (row >= 0) & (weight > 0)
    if use.any():
        feats = table[row[use]]
        feats /= np.maximum(np.linalg.norm(feats, axis=1, keepdims=True), 1e-12)
        sims[use] = feats @ texts.T
    return sims, np.zeros(n, np.int64)


def average_similarities(
    points: np.ndarray,  # (N, 3) float32 world metres
    views: Sequence[OVView | tuple],
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    *,
    use_depth: bool,
    border_px: float = 10.0,
    depth_rel_tol: float = 0.25,
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,  # (P, D) f32, (N,) i64, (N,) f32
    threads: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Cosines (N, T) float32 between the average of the views' OV samples at each point and the
    texts (zero rows where no view counts), and the views that counted (N,) int64. A view counts
    for a point in front of it, inside its image less ``border_px`` and, with ``use_depth``, where
    ``|depth - z| <= depth_rel_tol * depth`` (views without depth count nowhere then). ``prior``:
    ``(means (P, D), row (N,) (-1: none), weight (N,))``: point n's average also takes
    ``means[row[n]]`` as the mean of ``weight[n]`` more views (views no longer given, e.g. keyframes
    that left the node's window). Numpy in, numpy out; the compiled kernel."""
    pts = np.ascontiguousarray(points, np.float32)
    check_shape(pts, "N 3", "points must have shape (N points, xyz)")
    texts = np.ascontiguousarray(text_emb, np.float32)
    check_shape(texts, "T D", "text_emb must have shape (T texts, D)")
    parsed = [OVView(*v) for v in views]
    dims = {int(v.ov.shape[-1]) for v in parsed}
    if len(dims) > 1:
        raise ValueError(f"views have OV features of different dimensions {sorted(dims)}")
    dim = dims.pop() if dims else 0
    if dim and texts.shape[1] != dim:
        raise ValueError(f"text_emb has dimension {texts.shape[1]}, the views' features {dim}")
    parsed = [v for v in parsed if not use_depth or v.depth_m is not None]
    n = pts.shape[0]
    if not parsed and prior is not None and n > 0:
        return prior_only_similarities(n, prior, texts)
    if not parsed or n == 0:
        return np.zeros((n, texts.shape[0]), np.float32), np.zeros(n, np.int64)
    return kernel_average(pts, parsed, use_depth=use_depth, border_px=border_px, depth_rel_tol=depth_rel_tol,
                          distance_power=0.0, vw=None, dim=dim, texts=texts, threads=threads, prior=prior)
