"""The window's keyframe poses adjusted jointly from dense matches (epipolar bundle adjustment).

A robot's odometry poses carry centimetres and a degree of error per frame. Two keyframes that see
the same surfaces tell their relative pose through their pixel correspondences, and many
keyframes together tell where every one of them was better than any one pose as sent:

1. **matches** (:func:`pair_matches`): OpenCV's DIS optical flow from a keyframe to a partner and
   back (:func:`mapper.geometry.dense_flow.flow_matches`: textured pixels whose round trip returns),
   thinned to at most ``pose_pair_matches`` spread over the image (one per grid cell). Dense flow
   needs no feature detector, so it holds on the low-texture 160 x 120 images where detected
   features are few;
2. **the joint adjustment** (:func:`adjust_poses`): every pose of the window is a 6-vector correction
   (the camera centre's shift and a rotation about the centre, in the world frame, as odometry
   errs) of the pose as sent. SciPy's ``least_squares`` (trust region, a sparse Jacobian by the chain
   rule, a Cauchy loss at ``pose_huber_px``: redescending, so that wrong matches stop pulling)
   minimises the matches' Sampson distances (the first-order distance of a
   correspondence from the epipolar geometry of the two corrected poses, in pixels, over
   ``sqrt(2) pose_flow_sigma_px``) plus a prior per pose towards the pose as sent (``pose_prior_m``
   and ``pose_prior_deg`` per axis). The matches fix what they can see: relative rotations and the
   directions of the baselines; the priors fix the rest (the window's common offset, averaged over
   its keyframes, and the baselines' lengths). No points are estimated: the epipolar constraint
   involves only the two poses, so the problem has 6 unknowns a keyframe;
3. **views left out**: a view whose matches the solution explains far worse than the others' (median
   Sampson distance over ``INCONSISTENT_RATIO`` times the window's median: a pose sent far off, to
   which the others would bend) keeps its pose as sent and the others are solved again without it;
   matches beyond ``pose_ransac_px`` at the first solution are dropped then too;
4. **acceptance** per pose: a corrected pose is used only when it moved within ``pose_max_sigmas`` of
   the prior (the 3-axis norm) and the median Sampson distance of its own matches dropped by at
   least ``pose_min_gain``; otherwise its pose as sent is.

Pure numpy float64 + OpenCV + SciPy, no torch. Pixel coordinates follow
docs/concepts/conventions.md (centres at +0.5). Tests: tests/mapper/geometry/test_window_adjust.py.

Example (views of a textured scene; ``views`` are :class:`mapper.geometry.dense_flow.FlowView`)::

    pairs = [m for a, b in edges if (m := pair_matches(views[a], views[b], a, b, cfg, flow_cfg))]
    out = adjust_poses(K_per_view, sent_poses, pairs, cfg)     # out.world_from_cam (N, 4, 4)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from mapper.geometry.config import DenseFlowConfig, TriangulationConfig
from mapper.geometry.dense_flow import FlowView, _texture, flow_matches
from mapper.geometry.pose_refine import pose_change, rotation_vector

INCONSISTENT_RATIO = 3.0
"""A view whose matches' median Sampson distance at the solution exceeds this many times the
window's median is left out (its pose as sent) and the others are solved again."""

_STEP = (1e-6, 1e-6, 1e-6, 1e-7, 1e-7, 1e-7)
"""Central-difference steps of a pose's F: metres for the centre, radians for the rotation."""

__all__ = ["PairMatches", "WindowAdjustment", "adjust_poses", "pair_matches", "rotations", "sampson_px"]


@dataclass(frozen=True)
class PairMatches:
    """Correspondences between views ``a`` and ``b`` (indices into the adjusted views)."""

    a: int
    b: int
    uv_a: np.ndarray  # (M, 2) float64 pixels in a (at the view's own K)
    uv_b: np.ndarray  # (M, 2) float64 pixels in b

    def __len__(self) -> int:
        return int(self.uv_a.shape[0])


@dataclass(frozen=True)
class WindowAdjustment:
    """What :func:`adjust_poses` found; a view's pose is the pose as sent unless ``accepted``."""

    world_from_cam: np.ndarray  # (N, 4, 4) adjusted where accepted, else as sent
    accepted: np.ndarray  # (N,) bool
    reason: list[str]  # per view: "refined", "fixed", "no matches", "inconsistent", "no gain" or "too far"
    translation_m: np.ndarray  # (N,) the solution's move of each centre (before acceptance)
    rotation_deg: np.ndarray  # (N,) ... and rotation angle
    error_before_px: np.ndarray  # (N,) median |Sampson distance| of each view's matches, poses as sent
    error_after_px: np.ndarray  # (N,) ... at the solution
    matches: np.ndarray  # (N,) int64 matches each view takes part in


def rotations(rotvec: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of axis-angle vectors ``rotvec`` (N, 3) (radians), Rodrigues' formula."""
    v = np.asarray(rotvec, np.float64).reshape(-1, 3)
    theta = np.linalg.norm(v, axis=1)
    safe = np.where(theta > 1e-12, theta, 1.0)
    k = v / safe[:, None]
    kx = _skew(k)
    s = np.where(theta > 1e-12, np.sin(theta), 0.0)[:, None, None]
    c = np.where(theta > 1e-12, 1.0 - np.cos(theta), 0.0)[:, None, None]
    return np.eye(3)[None] + s * kx + c * (kx @ kx)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _k_inv(K: np.ndarray) -> np.ndarray:
    """(N, 3, 3) inverse intrinsic matrices of (N, 4) [fx, fy, cx, cy]."""
    K = np.asarray(K, np.float64).reshape(-1, 4)
    out = np.zeros((len(K), 3, 3))
    out[:, 0, 0], out[:, 1, 1] = 1.0 / K[:, 0], 1.0 / K[:, 1]
    out[:, 0, 2], out[:, 1, 2] = -K[:, 2] / K[:, 0], -K[:, 3] / K[:, 1]
    out[:, 2, 2] = 1.0
    return out


def _fundamentals(Ka: np.ndarray, Kb: np.ndarray, Ra: np.ndarray, ca: np.ndarray,
                  Rb: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """(P, 3, 3) F with ``x_b^T F x_a = 0`` for P pairs: intrinsics (P, 4), world_from_cam rotations
    (P, 3, 3) and centres (P, 3). The baseline is normalised (F's scale does not matter)."""
    R_ba = np.swapaxes(Rb, 1, 2) @ Ra
    t = np.einsum("pji,pj->pi", Rb, ca - cb)  # R_b^T (c_a - c_b)
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    E = _skew(t) @ R_ba
    return np.swapaxes(_k_inv(Kb), 1, 2) @ E @ _k_inv(Ka)


def _epipolar_terms(F: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the Sampson distance of matches under per-match F (M, 3, 3) is made of: the homogeneous
    pixels ``xa``, ``xb`` (M, 3), ``F xa`` and ``F^T xb`` (M, 3), the epipolar residual
    ``e = xb^T F xa`` (M,) and the squared gradient norm ``d`` (M,, floored above 0)."""
    xa = np.concatenate([uv_a, np.ones((len(uv_a), 1))], axis=1)
    xb = np.concatenate([uv_b, np.ones((len(uv_b), 1))], axis=1)
    Fxa = np.einsum("mij,mj->mi", F, xa)
    Ftxb = np.einsum("mji,mj->mi", F, xb)
    e = np.einsum("mi,mi->m", xb, Fxa)
    d = np.maximum(Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2, 1e-300)
    return xa, xb, Fxa, Ftxb, e, d


def _sampson(F: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(M,) signed Sampson distance (pixels) of matches under per-match F (M, 3, 3)."""
    *_, e, d = _epipolar_terms(F, uv_a, uv_b)
    return e / np.sqrt(d)


def _sampson_gradient(F: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(M, 9) derivative of :func:`_sampson` with respect to each match's F (row-major)."""
    xa, xb, Fxa, Ftxb, e, d = _epipolar_terms(F, uv_a, uv_b)
    de = xb[:, :, None] * xa[:, None, :]  # d e / d F_ij = xb_i xa_j
    Fxa2, Ftxb2 = Fxa.copy(), Ftxb.copy()
    Fxa2[:, 2] = 0.0  # only the first two rows / columns enter d
    Ftxb2[:, 2] = 0.0
    dd = 2.0 * (Fxa2[:, :, None] * xa[:, None, :] + xb[:, :, None] * Ftxb2[:, None, :])
    grad = de / np.sqrt(d)[:, None, None] - (0.5 * e / d ** 1.5)[:, None, None] * dd
    return grad.reshape(-1, 9)


def sampson_px(Ka: np.ndarray, Kb: np.ndarray, world_from_a: np.ndarray, world_from_b: np.ndarray,
               uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(M,) signed Sampson distance (pixels) of the matches ``uv_a`` (M, 2) -> ``uv_b`` (M, 2) from
    the epipolar geometry of two cameras (intrinsics (4,), world_from_cam (4, 4) each)."""
    a, b = np.asarray(world_from_a, np.float64), np.asarray(world_from_b, np.float64)
    F = _fundamentals(np.asarray(Ka, np.float64)[None], np.asarray(Kb, np.float64)[None],
                      a[None, :3, :3], a[None, :3, 3], b[None, :3, :3], b[None, :3, 3])
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    return _sampson(np.repeat(F, len(uv_a), axis=0), uv_a, np.asarray(uv_b, np.float64).reshape(-1, 2))


def _rotation_homography(a: FlowView, b: FlowView) -> np.ndarray:
    """(3, 3) the homography of the rotation between the views (points at infinity), a's pixels ->
    b's pixels, in OpenCV's integer-centre pixel coordinates."""
    Ka, Kb = _k_inv(a.K[None])[0], np.linalg.inv(_k_inv(b.K[None])[0])
    Ra, Rb = a.world_from_cam[:3, :3], b.world_from_cam[:3, :3]
    H = Kb @ Rb.T @ Ra @ Ka
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])  # +0.5 centres
    return np.linalg.inv(shift) @ H @ shift


def pair_matches(a: FlowView, b: FlowView, ia: int, ib: int, config: TriangulationConfig,
                 flow: DenseFlowConfig) -> PairMatches | None:
    """Dense matches of view ``a`` in view ``b``, at most ``config.pose_pair_matches`` of them, one
    per cell of a grid over ``a``; None without ``config.pose_min_inliers`` matches. ``b`` is first
    warped into ``a`` by the rotation between their poses as sent (so the flow only has to find
    the parallax of the baseline, which DIS finds at any turn), the flow and its checks
    (:func:`mapper.geometry.dense_flow.flow_matches`) run on the warped image, and the matches go
    back to ``b``'s own pixels. The pixels are at each view's own K."""
    h, w = a.gray.shape
    H = _rotation_homography(a, b)
    size = (w, h)
    warped = cv2.warpPerspective(b.gray, H, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REPLICATE)
    valid = cv2.warpPerspective(np.ones(b.gray.shape, np.uint8), H, size,
                                flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0)
    _, uv_a, uv_w = flow_matches(a, replace(a, gray=warped), flow)
    if len(uv_a):
        r = np.clip(np.floor(uv_w[:, 1]).astype(np.int64), 0, h - 1)
        c = np.clip(np.floor(uv_w[:, 0]).astype(np.int64), 0, w - 1)
        inside = (valid[r, c] > 0) & (_texture(warped)[r, c] >= flow.min_texture)  # b textured there too
        uv_a, uv_w = uv_a[inside], uv_w[inside]
    if len(uv_a) < config.pose_min_inliers:
        return None
    cell = max(1.0, math.sqrt(h * w / max(config.pose_pair_matches, 1)))
    cols = int(math.ceil(w / cell))
    cell_id = (uv_a[:, 1] // cell).astype(np.int64) * cols + (uv_a[:, 0] // cell).astype(np.int64)
    _, first = np.unique(cell_id, return_index=True)
    first = np.sort(first)[: config.pose_pair_matches]
    xw = np.concatenate([uv_w[first] - 0.5, np.ones((len(first), 1))], axis=1) @ H.T  # to b (OpenCV px)
    uv_b = xw[:, :2] / xw[:, 2:3] + 0.5
    return PairMatches(ia, ib, uv_a[first], uv_b)


def _poses_of(sent: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World_from_cam rotations (N, 3, 3) and centres (N, 3) of the corrections ``x`` (N, 6)."""
    return rotations(x[:, 3:]) @ sent[:, :3, :3], sent[:, :3, 3] + x[:, :3]


def _solve(residuals: Callable[[np.ndarray], np.ndarray], jacobian: Callable[[np.ndarray], csr_matrix],
           x: np.ndarray, prior: np.ndarray, n_free: int, sigma: float,
           config: TriangulationConfig) -> np.ndarray:
    """SciPy's trust region from ``x`` with the Cauchy loss at ``pose_huber_px``."""
    return np.asarray(least_squares(residuals, x, jac=jacobian, method="trf", loss="cauchy",
                                    f_scale=config.pose_huber_px / sigma,
                                    x_scale=1.0 / np.tile(prior, n_free),
                                    max_nfev=config.pose_max_evaluations).x)


def _verdicts(sent: np.ndarray, R: np.ndarray, c: np.ndarray, before: np.ndarray, after: np.ndarray,
              ia: np.ndarray, ib: np.ndarray, fixed: np.ndarray, left_out: np.ndarray, counts: np.ndarray,
              config: TriangulationConfig) -> WindowAdjustment:
    """Each view's acceptance (see the module docstring) from the solution's rotations ``R`` (N, 3, 3)
    and centres ``c`` (N, 3), and the matches' Sampson distances ``before`` / ``after`` (M,)."""
    n = len(sent)
    out = sent.copy()
    accepted = np.zeros(n, bool)
    reasons: list[str] = []
    moved_t, moved_r = np.zeros(n), np.zeros(n)
    err_before, err_after = np.full(n, np.nan), np.full(n, np.nan)
    max_t = config.pose_max_sigmas * config.pose_prior_m * math.sqrt(3.0)
    max_r = config.pose_max_sigmas * config.pose_prior_deg * math.sqrt(3.0)
    for v in range(n):
        own = (ia == v) | (ib == v)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = R[v], c[v]
        moved_t[v], moved_r[v] = pose_change(sent[v], pose)
        if own.any():
            err_before[v] = float(np.median(np.abs(before[own])))
            err_after[v] = float(np.median(np.abs(after[own])))
        if fixed[v]:
            reasons.append("fixed")
        elif left_out[v]:
            reasons.append("inconsistent")
        elif not own.any():
            reasons.append("no matches")
        elif moved_t[v] > max_t or moved_r[v] > max_r:
            reasons.append("too far")
        elif err_after[v] > (1.0 - config.pose_min_gain) * err_before[v]:
            reasons.append("no gain")
        else:
            reasons.append("refined")
            accepted[v] = True
            out[v] = pose
    return WindowAdjustment(out, accepted, reasons, moved_t, moved_r, err_before, err_after,
                            counts.astype(np.int64))


def adjust_poses(
    K: np.ndarray, world_from_cam: np.ndarray, pairs: Sequence[PairMatches], config: TriangulationConfig,
    fixed: np.ndarray | None = None, start: np.ndarray | None = None,
) -> WindowAdjustment:
    """Adjust N poses as sent (``world_from_cam`` (N, 4, 4), intrinsics ``K`` (N, 4)) jointly from
    the ``pairs``' matches (see the module docstring). ``fixed`` (N,) bool: views held at their pose
    as sent (they still constrain the others). ``start`` (N, 4, 4): poses to start the search at
    (an earlier adjustment's; default the poses as sent); the prior stays at the poses as sent."""
    sent = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    K = np.asarray(K, np.float64).reshape(-1, 4)
    n = len(sent)
    if len(K) != n:
        raise ValueError(f"K has {len(K)} rows for {n} poses")
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool).reshape(n)
    pairs = [p for p in pairs if len(p) and 0 <= p.a < n and 0 <= p.b < n and p.a != p.b]
    pa = np.array([p.a for p in pairs], np.int64)
    pb = np.array([p.b for p in pairs], np.int64)
    pair_of = (np.concatenate([np.full(len(p), k) for k, p in enumerate(pairs)]) if pairs
               else np.zeros(0, np.int64))
    uv_a = np.concatenate([p.uv_a for p in pairs]) if pairs else np.zeros((0, 2))
    uv_b = np.concatenate([p.uv_b for p in pairs]) if pairs else np.zeros((0, 2))
    ia, ib = pa[pair_of], pb[pair_of]
    counts = np.bincount(np.concatenate([ia, ib]).astype(np.int64), minlength=n).astype(np.int64)
    free = ~fixed & (counts > 0)
    n_free = int(free.sum())
    col_of = np.full(n, -1, np.int64)
    col_of[free] = 6 * np.arange(n_free)  # first of the view's 6 unknowns
    sigma = math.sqrt(2.0) * max(config.pose_flow_sigma_px, 1e-3)
    inlier = np.ones(len(uv_a))  # 0 for the matches the first pass rejects
    prior = np.concatenate([np.full(3, 1.0 / config.pose_prior_m),
                            np.full(3, 1.0 / math.radians(config.pose_prior_deg))])

    def full(x: np.ndarray) -> np.ndarray:
        x_all = np.zeros((n, 6))
        x_all[free] = x.reshape(n_free, 6)
        return x_all

    def pair_fundamentals(xa: np.ndarray, xb: np.ndarray) -> np.ndarray:  # (P, 6) each -> (P, 3, 3)
        return _fundamentals(K[pa], K[pb],
                             rotations(xa[:, 3:]) @ sent[pa, :3, :3], sent[pa, :3, 3] + xa[:, :3],
                             rotations(xb[:, 3:]) @ sent[pb, :3, :3], sent[pb, :3, 3] + xb[:, :3])

    def fundamentals(x_all: np.ndarray) -> np.ndarray:  # (P, 3, 3)
        return pair_fundamentals(x_all[pa], x_all[pb])

    def residuals(x: np.ndarray) -> np.ndarray:
        x_all = full(x)
        return np.concatenate([_sampson(fundamentals(x_all)[pair_of], uv_a, uv_b) * (inlier / sigma),
                               (x_all[free] * prior).ravel()])

    def jacobian(x: np.ndarray) -> csr_matrix:
        # the chain rule: d r / d F (analytic, per match) x d F / d pose (central differences, per pair)
        x_all = full(x)
        xa, xb = x_all[pa], x_all[pb]
        dF = np.zeros((len(pairs), 9, 12))
        for k in range(12):
            step = np.zeros(6)
            step[k % 6] = _STEP[k % 6]
            if k < 6:
                f_hi, f_lo = pair_fundamentals(xa + step, xb), pair_fundamentals(xa - step, xb)
            else:
                f_hi, f_lo = pair_fundamentals(xa, xb + step), pair_fundamentals(xa, xb - step)
            dF[:, :, k] = (f_hi - f_lo).reshape(-1, 9) / (2.0 * _STEP[k % 6])
        dr = _sampson_gradient(fundamentals(x_all)[pair_of], uv_a, uv_b) * (inlier / sigma)[:, None]  # (M, 9)
        J = np.einsum("mi,mik->mk", dr, dF[pair_of])  # (M, 12)
        rows, cols, vals = [], [], []
        m_rows = np.arange(len(uv_a))
        for half, views in ((0, ia), (1, ib)):
            start = col_of[views]
            ok = start >= 0
            for k in range(6):
                rows.append(m_rows[ok])
                cols.append(start[ok] + k)
                vals.append(J[ok, 6 * half + k])
        rows.append(len(uv_a) + np.arange(6 * n_free))
        cols.append(np.arange(6 * n_free))
        vals.append(np.tile(prior, n_free))
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(uv_a) + 6 * n_free, 6 * n_free))

    before = _sampson(fundamentals(np.zeros((n, 6)))[pair_of], uv_a, uv_b)
    x = np.zeros(6 * n_free)
    if start is not None:
        begin = np.asarray(start, np.float64).reshape(n, 4, 4)
        x0 = np.zeros((n, 6))
        x0[:, :3] = begin[:, :3, 3] - sent[:, :3, 3]
        for view in np.flatnonzero(free):
            x0[view, 3:] = rotation_vector(begin[view, :3, :3] @ sent[view, :3, :3].T)
        x = x0[free].ravel()
    left_out = np.zeros(n, bool)
    if n_free and len(uv_a):
        x = _solve(residuals, jacobian, x, prior, n_free, sigma, config)
        dist = np.abs(_sampson(fundamentals(full(x))[pair_of], uv_a, uv_b))
        keep = dist <= config.pose_ransac_px
        # a view whose matches the solution still explains worst by far (a pose sent far off, which
        # the others would bend to) is left out, at its pose as sent, and the rest solved again
        per_view = np.zeros(n)
        for v in range(n):
            own = ((ia == v) | (ib == v)) & keep
            per_view[v] = float(np.median(dist[own])) if own.any() else 0.0
        matched = per_view > 0
        if matched.any():
            left_out = matched & (per_view > INCONSISTENT_RATIO * np.median(per_view[matched]))
        if not keep.all() or left_out.any():
            inlier[:] = keep & ~left_out[ia] & ~left_out[ib]
            x_all = full(x)
            x_all[left_out] = 0.0
            x = _solve(residuals, jacobian, x_all[free].ravel(), prior, n_free, sigma, config)
    x_all = full(x)
    after = _sampson(fundamentals(x_all)[pair_of], uv_a, uv_b)
    R, c = _poses_of(sent, x_all)
    return _verdicts(sent, R, c, before, after, ia, ib, fixed, left_out, counts, config)
