"""``segment_points`` methods ``average`` and ``average_depth``: OpenScene-2D averaging.

The OV features of the window's keyframes where they see a point (10 px border; ``average_depth``:
only where the point passes the depth test against the keyframe's input depth, or, for keyframes
without depth, against the request's own points splatted as occluders: ``queries.point_occlusion``),
together with the views of keyframes that left the window at the point's nearest map voxel
(``queries.evicted_views``, :mod:`mapper.map.evicted_views`). Torch-free: the averaging runs in a
compiled kernel (:mod:`mapper.kernels.average_kernel`). The global map's answer beyond the window
is applied by :mod:`mapper.node.answers.segment`, as for every backend.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence

import numpy as np

from mapper.map.evicted_frames import EvictedFrameStore, merged_prior
from mapper.map.evicted_views import EvictedViewStore
from mapper.map.global_map import GlobalMapSnapshot
from mapper.map.window import Keyframe
from mapper.node.backends import PointAnswer, gather_answers
from mapper.node.context import NodeContext
from protocol.errors import ProtocolError
from protocol.messages import SegmentPoints

__all__ = ["AveragingBackend", "average_with_frames", "evicted_cosines"]

FRAMES_CHUNK = 65_536
"""Points averaged at a time with the kept evicted views (their merged prior is (chunk, D) float32)."""


def average_with_frames(
    xyz: np.ndarray,  # (N, 3) float32
    views: Sequence[tuple],  # the window's views (``segment_average_cosines``)
    text_emb: np.ndarray,  # (T, D) float32
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None,  # the voxels' evicted views
    frames: EvictedFrameStore,
    chunk: int = FRAMES_CHUNK,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``average`` with the kept views of evicted keyframes too: each point's average takes the
    window's views, its voxel's evicted views and every kept view it falls in
    (:func:`mapper.map.evicted_frames.merged_prior`), ``chunk`` points at a time. Returns
    (cosines (N, T), the window's views that counted (N,), the evicted views that counted (N,)
    float32: the voxel's and the kept ones)."""
    from mapper.node.queries import segment_average_cosines

    n, dim = xyz.shape[0], text_emb.shape[1]
    cos = np.zeros((n, text_emb.shape[0]), np.float32)
    n_views = np.zeros(n, np.int64)
    evicted = np.zeros(n, np.float32)
    for lo in range(0, n, chunk):
        part = xyz[lo: lo + chunk]
        m = part.shape[0]
        rows, mean, count = frames.means(part)
        part_prior = None if prior is None else (prior[0], prior[1][lo: lo + m], prior[2][lo: lo + m])
        merged = merged_prior(m, part_prior, rows, mean, count, dim)
        if not views and merged is None:
            continue
        cos[lo: lo + m], n_views[lo: lo + m] = segment_average_cosines(part, views, text_emb, use_depth=False,
                                                                       prior=merged)
        if merged is not None:
            evicted[lo: lo + m] = np.where(merged[1] >= 0, merged[2], 0.0)
    return cos, n_views, evicted


def evicted_cosines(
    xyz: np.ndarray,  # (N, 3) float32
    text_emb: np.ndarray,  # (T, D) float32 unit rows
    prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None,  # the voxels' evicted views
    frames: EvictedFrameStore | None,
    footprint_m: float,
    chunk: int = FRAMES_CHUNK,
    learned: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """The evicted views' own answer: (cosines (N, T) float32 of the mean of each point's
    voxel's evicted views and the kept views that count for it, zero rows where none does; their
    views (N,) float32). With ``footprint_m`` > 0 a kept view counts only where the request's other
    points do not hide the point in it (:meth:`EvictedFrameStore.means`); without it the kept views
    are left out (they carry no depth). ``learned``: the kept views' learned maps where they have one
    (``queries.evicted_frames_learned``)."""
    n, dim = xyz.shape[0], text_emb.shape[1]
    cos = np.zeros((n, text_emb.shape[0]), np.float32)
    count = np.zeros(n, np.float32)
    for lo in range(0, n, chunk):
        part = xyz[lo: lo + chunk]
        m = part.shape[0]
        part_prior = None if prior is None else (prior[0], prior[1][lo: lo + m], prior[2][lo: lo + m])
        rows, mean, views = np.zeros(0, np.int64), np.zeros((0, dim), np.float32), np.zeros(0, np.float32)
        if frames is not None and footprint_m > 0:
            rows, mean, views = frames.means(part, occlusion_footprint_m=footprint_m,
                                             occluders=xyz if n > m else None, learned=learned)
        merged = merged_prior(m, part_prior, rows, mean, views, dim)
        if merged is not None:
            cos[lo: lo + m] = prior_cosines(merged, text_emb)
            count[lo: lo + m] = np.where(merged[1] >= 0, merged[2], 0.0)
    return cos, count


def prior_cosines(
    prior: tuple[np.ndarray, np.ndarray, np.ndarray],  # (P, D) means, (N,) row (-1: none), (N,) views
    text_emb: np.ndarray,  # (T, D) float32 unit rows
) -> np.ndarray:  # (N, T) float32
    """The cosines of each point's evicted views' mean (an averaging ``prior``) with the texts; zero
    rows where it has none."""
    table, row, weight = prior
    out = np.zeros((row.shape[0], text_emb.shape[0]), np.float32)
    hit = np.flatnonzero((row >= 0) & (weight > 0))
    if hit.size:
        feat = np.asarray(table[row[hit]], np.float32)
        feat = feat / np.maximum(np.linalg.norm(feat, axis=1, keepdims=True), np.float32(1e-12))
        out[hit] = feat @ np.asarray(text_emb, np.float32).T
    return out


class AveragingBackend:
    """``average`` (``use_depth=False``) or ``average_depth`` (``use_depth=True``)."""

    ready = True

    def __init__(self, ctx: NodeContext, use_depth: bool) -> None:
        self.ctx = ctx
        self.use_depth = use_depth
        self.method = "average_depth" if use_depth else "average"

    def depth_tested(self, msg: SegmentPoints) -> bool:
        return self.use_depth

    def segment(self, msg: SegmentPoints, want_cos: bool, want_evicted: bool = False) -> PointAnswer:
        """The averaging's answer. With several robots, each point is averaged over the keyframes
        of the robots whose windows observed it (:func:`mapper.map.robot_windows.robot_groups`:
        a robot's keyframe from another room does not count for it), group by group; with
        ``want_evicted`` the answer's ``evicted_cos`` holds the evicted views' own cosines."""
        from mapper.map.robot_windows import robot_groups

        ctx = self.ctx
        with ctx.state.lock:
            windows = [(robot, window.keyframes) for robot, window in ctx.state.window.windows()]
        xyz = np.asarray(msg.xyz, np.float32)
        groups = robot_groups(windows, xyz, ctx.config.global_map.max_depth_m)
        if groups is None:
            return self._segment_sorted(msg, want_evicted, None)
        parts = []
        for robots, idx in groups:
            part = copy.copy(msg)  # a subset of points validated at the boundary: not checked again
            part.xyz = xyz[idx]
            parts.append((idx, self._segment_sorted(part, want_evicted, robots)))
        answer = gather_answers(xyz.shape[0], parts)
        answer.timing_ms["robot_groups"] = float(len(groups))
        return answer

    def _segment_sorted(self, msg: SegmentPoints, want_evicted: bool, robots: tuple[str, ...] | None
                        ) -> PointAnswer:
        """The averaging's answer (over ``robots``' keyframes; None: every window's) with the points
        in Z-order of map voxels where they do not come spatially coherent (``queries.spatial_sort``,
        :func:`mapper.node.queries.spatial_order`), returned in the request's order. (The learned
        model's path groups its points by view set and cell already: a shuffled request costs it
        about as much as a coherent one.)"""
        if not self.ctx.config.queries.spatial_sort:
            return self._segment_ordered(msg, want_evicted, robots)
        from mapper.node.queries import spatial_order

        started = time.perf_counter()
        xyz = np.asarray(msg.xyz, np.float32)
        order = spatial_order(xyz, self.ctx.config.global_map.voxel_size_m)
        if order is None:
            return self._segment_ordered(msg, want_evicted, robots)
        sorted_ms = 1e3 * (time.perf_counter() - started)
        in_order = copy.copy(msg)  # a permutation of points validated at the boundary: not checked again
        in_order.xyz = xyz[order]
        answer = self._segment_ordered(in_order, want_evicted, robots)
        # back to the request's order
        for name in ("label", "score", "seen", "cos", "nearest", "map_only", "views", "evicted_views",
                     "evicted_cos"):
            arr = getattr(answer, name)
            if arr is not None:
                back = np.empty_like(arr)
                back[order] = arr
                setattr(answer, name, back)
        answer.timing_ms["spatial_sort"] = sorted_ms
        return answer

    def _occluder_depths(self, xyz: np.ndarray, keyframes: Sequence[Keyframe]) -> dict[int, np.ndarray]:
        """``queries.point_occlusion``: for each of ``keyframes`` without input depth (by index), its
        (H, W) z-buffer of the request's points ``xyz`` (N, 3), the depth ``average_depth`` tests
        against there (all zeros for a request without points). Empty when the setting is off or no
        keyframe lacks depth."""
        need = [i for i, k in enumerate(keyframes) if k.depth_m is None]
        if not self.ctx.config.queries.point_occlusion or not need:
            return {}
        from mapper.geometry.splat import request_occluder_depths

        out = {}
        for size in {(keyframes[i].width, keyframes[i].height) for i in need}:  # one launch a size
            same = [i for i in need if (keyframes[i].width, keyframes[i].height) == size]
            z = request_occluder_depths(
                xyz, np.stack([np.asarray(keyframes[i].K, np.float64) for i in same]),
                np.stack([np.asarray(keyframes[i].world_from_cam, np.float64) for i in same]),
                size[0], size[1], self.ctx.config.model.point_occlusion_footprint, threads=0)
            out.update({i: z[j] for j, i in enumerate(same)})
        return out

    def _segment_ordered(self, msg: SegmentPoints, want_evicted: bool = False,
                         robots: tuple[str, ...] | None = None) -> PointAnswer:
        """The averaging over the window's keyframes where they see a point, together with the
        views of keyframes that left the window at its nearest map voxel (:meth:`_evicted_prior`)."""
        from mapper.node.queries import best_text, segment_average_cosines

        ctx, use_depth, method = self.ctx, self.use_depth, self.method
        started = time.perf_counter()
        with ctx.state.lock:
            window = ctx.state.window
            keyframes = window.keyframes if robots is None else window.keyframes_of(robots)
        with_ov = [k for k in keyframes if k.ov is not None]
        xyz = np.asarray(msg.xyz, np.float32)
        occluders = self._occluder_depths(xyz, with_ov) if use_depth else {}
        views = [
            (k.ov, k.K, k.world_from_cam, (k.width, k.height),
             k.depth_m if k.depth_m is not None else occluders.get(i))
            for i, k in enumerate(with_ov)
            if k.ov is not None and (not use_depth or k.depth_m is not None or i in occluders)
        ]
        gmap = ctx.state.global_map  # its snapshot and evicted views together (a load swaps the map)
        map_store = gmap.evicted
        map_snap = gmap.snapshot()  # one snapshot for the check and the fill
        map_has_features = map_snap.n_with_features > 0
        if not with_ov and not map_has_features:
            raise ProtocolError(
                "not_ready",
                f"segment_points method {method!r}: none of the {len(keyframes)} keyframes in the window "
                "carries ov features and the global map has none; send frames with ov",
            )
        if not views and not map_has_features:
            raise ProtocolError(
                "not_ready",
                f"segment_points method 'average_depth' needs keyframes with both depth and ov: the "
                f"window has {len(with_ov)} keyframes with ov, none with depth; send depth or use "
                "method 'average'",
            )
        encoder = ctx.text_encoder(f"segment_points ({method})")
        with ctx.state.lock:
            dim = ctx.state.ov_dim
        if dim is not None and dim != encoder.dim:
            raise ProtocolError(
                "not_ready",
                f"segment_points: the map's features have dimension {dim}, the text encoder of "
                f"{encoder.space!r} produces {encoder.dim}",
            )
        t_views = time.perf_counter()
        text_emb = encoder.encode(list(msg.texts))
        t_text = time.perf_counter()
        nearest = map_snap.nearest_with_feature(xyz, ctx.map_radius_m) if map_has_features else None
        t_near = time.perf_counter()
        prior = self._evicted_prior(map_store, map_snap, nearest, "depth" if use_depth else "all", text_emb)
        t_prior = time.perf_counter()
        frames = None if use_depth else self._evicted_frames(map_store, text_emb)
        evicted = np.zeros(xyz.shape[0], np.float32)
        if frames is not None:
            cos, n_views, evicted = average_with_frames(xyz, views, text_emb, prior, frames)
        elif views or prior is not None:
            cos, n_views = segment_average_cosines(xyz, views, text_emb, use_depth=use_depth, prior=prior)
            if prior is not None:
                evicted = np.where(prior[1] >= 0, prior[2], 0.0).astype(np.float32)
        else:
            cos = np.zeros((xyz.shape[0], text_emb.shape[0]), np.float32)
            n_views = np.zeros(xyz.shape[0], np.int64)
        evicted_cos = evicted_count = None
        if want_evicted:  # the evicted views' own answer, the kept views with the occlusion test
            # (asked for the learned answer's mix: the kept views' learned maps where they have one)
            kept = self._evicted_frames(map_store, text_emb)
            footprint = self._occlusion_footprint(xyz) if kept is not None else 0.0
            evicted_cos, evicted_count = evicted_cosines(xyz, text_emb, prior, kept, footprint, learned=True)
        with_prior = evicted > 0
        evicted_only = (n_views == 0) & with_prior
        seen = (n_views > 0) | evicted_only
        label, score = best_text(cos, seen)
        t_avg = time.perf_counter()
        timing = {
            "views": 1e3 * (t_views - started),
            "encode_text": 1e3 * (t_text - t_views),
            "nearest": 1e3 * (t_near - t_text),
            "evicted": 1e3 * (t_prior - t_near),
            "average": 1e3 * (t_avg - t_prior),
            "total": 1e3 * (t_avg - started),
            "n_views": float(len(views)),
            "from_evicted": float(np.count_nonzero(with_prior)),
        }
        return PointAnswer(label=label, score=score, timing_ms=timing, seen=seen, cos=cos, text_emb=text_emb,
                           snapshot=map_snap, nearest=nearest, map_only=evicted_only,
                           views=n_views.astype(np.float32),
                           evicted_views=evicted if evicted_count is None else evicted_count,
                           evicted_cos=evicted_cos)

    def _occlusion_footprint(self, xyz: np.ndarray) -> float:
        """The footprint (m) of each of the request's points splatted as an occluder into the kept
        views of evicted keyframes (``queries.point_occlusion``: ``model.point_occlusion_footprint``
        times the points' median spacing), 0 when that test is off or the points have no spacing."""
        if not self.ctx.config.queries.point_occlusion or xyz.shape[0] < 2:
            return 0.0
        from mapper.geometry.splat import point_spacing

        return float(self.ctx.config.model.point_occlusion_footprint * point_spacing(xyz))

    def _evicted_frames(self, store: EvictedViewStore, text_emb: np.ndarray) -> EvictedFrameStore | None:
        """The kept views of evicted keyframes without depth (``queries.evicted_frames_mb``), or
        None when there are none of the texts' dimension."""
        worker = self.ctx.evicted_views
        frames = store.frames
        if worker is None or not worker.both or frames.dim != text_emb.shape[1] or len(frames) == 0:
            return None
        return frames

    def _evicted_prior(
        self,
        store: EvictedViewStore,
        snap: GlobalMapSnapshot,
        nearest: np.ndarray | None,  # (N,) int64 nearest map rows with a feature (-1: none)
        channel: str,
        text_emb: np.ndarray,  # (T, D)
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The views of keyframes that left the window at each point's nearest map voxel, as the
        averaging's ``prior`` (means (P, D) float32, row (N,) int64 (-1: none), views (N,) float32),
        or None when there are none (``queries.evicted_views`` off, nothing evicted yet, no map
        voxel near, another feature dimension)."""
        worker = self.ctx.evicted_views
        if worker is None or nearest is None or snap.keys is None or len(store) == 0:
            return None
        if channel == "all" and not worker.both:
            return None
        if store.dim != text_emb.shape[1]:
            return None
        keys = np.full(nearest.shape[0], -1, np.int64)
        hit = nearest >= 0
        keys[hit] = snap.keys[nearest[hit]]
        table, row, weight = store.prior(keys, channel)
        row[~hit] = -1
        weight[~hit] = 0.0
        if not (row >= 0).any():
            return None
        return table, row, weight
